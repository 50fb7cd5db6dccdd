"""Simulated text and video encoders: ranking, genericity, determinism, documented corruptions."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from fourlegs_engine.errors import InputError
from fourlegs_engine.demo.synthetic import LABELS, QUERIES, generate_scene
from fourlegs_engine.language.encoders import CANONICAL_PHRASES, get_encoder
from fourlegs_engine.demo.simulated import SimulatedTextEncoder, SimulatedVideoEncoder
from fourlegs_engine.language.coverage import label_coverage_tube, render_label_coverage
from fourlegs_engine.language.phrase_space import EMBED_DIM, lemmatize
from fourlegs_engine.query.lerf import relevancy_reference

TEXT = SimulatedTextEncoder()
BACKGROUND = ["floor", "wall", "wooden box", "bench"]


def test_text_embeddings_are_unit_768d_and_deterministic():
    e = TEXT.encode_text(["a person jumping", "", "zxqv blorp", "!!"])
    assert e.shape == (4, EMBED_DIM) and e.dtype == torch.float32
    assert torch.isfinite(e).all()
    torch.testing.assert_close(e.norm(dim=1), torch.ones(4), atol=1e-6, rtol=0)
    torch.testing.assert_close(SimulatedTextEncoder().encode_text(["zxqv blorp"]), e[2:3])


@pytest.mark.parametrize("query,labels", QUERIES)
def test_each_query_is_closest_to_its_label(query, labels):
    L = TEXT.encode_text64(list(LABELS))
    q = TEXT.encode_text64([query])[0]
    assert LABELS[int(np.argmax(L @ q))] in labels
    # relevancy (LERF, float64 reference) of the right label is high, of every other label below 0.5
    rel = relevancy_reference(L, q, TEXT.encode_text64(list(CANONICAL_PHRASES)))
    for name, r in zip(LABELS, rel):
        assert (r > 0.9) if name in labels else (r < 0.5), (name, r)


@pytest.mark.parametrize("paraphrase,label", [
    ("someone leaps", "person jumping"), ("A man throws the basketball!", "person throwing the ball"),
    ("players walking", "person walking"), ("the ball flies through the air", "ball flying in the air"),
    ("a woman waves", "person waving"), ("wooden crate", "wooden box")])
def test_paraphrases_from_vocabulary_words_find_their_label(paraphrase, label):
    L = TEXT.encode_text64(list(LABELS))
    assert LABELS[int(np.argmax(L @ TEXT.encode_text64([paraphrase])[0]))] == label


def test_canonical_phrases_are_generic_and_unrelated_queries_score_low():
    L = TEXT.encode_text64(list(LABELS))
    C = TEXT.encode_text64(list(CANONICAL_PHRASES))
    sims = C @ L.T
    assert sims.std() < 0.02 and 0.3 < sims.mean() < 0.7            # equidistant to every label
    for unrelated in ("a cat sleeping on a sofa", "quantum chromodynamics", "xyzzy"):
        rel = relevancy_reference(L, TEXT.encode_text64([unrelated])[0], C)
        assert rel.max() < 0.5


def test_lemmatizer_handles_inflections_and_unknown_words():
    assert lemmatize("Two men were JUMPING, leaping!") == ["two", "person", "jump", "jump"]
    assert lemmatize("") == []
    with pytest.raises(InputError):
        lemmatize(None)  # type: ignore[arg-type]


# ------------------------------------------------------------------------------------------ video
def _pure_clip(label: int, cover: float = 1.0, h: int = 6, w: int = 5) -> torch.Tensor:
    clip = torch.zeros(1, 8, len(LABELS), h, w)
    clip[:, :, label] = cover
    return clip


def test_clean_video_encoder_ranks_the_right_label_first_on_clean_crops():
    enc = SimulatedVideoEncoder(LABELS, background_labels=BACKGROUND).clean()
    L = TEXT.encode_text(list(LABELS))
    for i in range(len(LABELS)):
        v = enc.encode_video(_pure_clip(i))
        assert int(torch.argmax(v @ L.T)) == i
        # a foreground label covering a quarter of the crop still wins over the floor around it
        mixed = torch.zeros(1, 8, len(LABELS), 4, 4)
        mixed[:, :, 0] = 1.0
        mixed[:, :, i, :2, :2] = 1.0
        mixed[:, :, 0, :2, :2] = 0.0
        if LABELS[i] not in BACKGROUND:
            assert int(torch.argmax(enc.encode_video(mixed) @ L.T)) == i


def test_noise_has_the_documented_cosine_and_bias_depends_on_the_camera():
    labels = list(LABELS)
    clips = torch.rand(6, 8, len(labels), 3, 3) / len(labels)
    clean = SimulatedVideoEncoder(labels, noise_cosine=1.0, camera_bias=0.0, wrong_label_fraction=0.0)
    noisy = SimulatedVideoEncoder(labels, noise_cosine=0.8, camera_bias=0.0, wrong_label_fraction=0.0)
    cos = (clean.encode_video(clips) * noisy.encode_video(clips)).sum(1)
    torch.testing.assert_close(cos, torch.full((6,), 0.8), atol=1e-5, rtol=0)
    biased = SimulatedVideoEncoder(labels, noise_cosine=1.0, camera_bias=0.5, wrong_label_fraction=0.0)
    a, b = biased.bind_camera("cam00"), biased.bind_camera("cam01")
    da = a.encode_video(clips) - clean.encode_video(clips)
    assert not torch.allclose(a.encode_video(clips), b.encode_video(clips))
    torch.testing.assert_close(a.encode_video(clips), biased.encode_video(clips, camera="cam00"))
    assert da.norm(dim=1).min() > 0.05


def test_defaults_are_deterministic_and_unit_norm():
    enc = SimulatedVideoEncoder(LABELS, seed=7)
    clips = torch.rand(5, 8, len(LABELS), 4, 4) / len(LABELS)
    a = enc.encode_video(clips)
    torch.testing.assert_close(a, SimulatedVideoEncoder(LABELS, seed=7).encode_video(clips), atol=0, rtol=0)
    assert not torch.allclose(a, SimulatedVideoEncoder(LABELS, seed=8).encode_video(clips))
    torch.testing.assert_close(a.norm(dim=1), torch.ones(5), atol=1e-6, rtol=0)
    # encode_video == encode_coverage of the per-frame means (the extractor's fast path)
    torch.testing.assert_close(a, enc.encode_coverage(clips.double().mean(dim=(3, 4))), atol=1e-6, rtol=0)


def test_every_frame_wrong_means_no_frame_shows_the_true_label():
    enc = SimulatedVideoEncoder(LABELS, noise_cosine=1.0, camera_bias=0.0, wrong_label_fraction=1.0)
    L = TEXT.encode_text(list(LABELS))
    for i in (4, 6, 11):
        v = enc.encode_video(_pure_clip(i))
        assert int(torch.argmax(v @ L.T)) != i


@settings(max_examples=40, deadline=None)
@given(st.one_of(st.floats(-1e6, 1e6), st.sampled_from([math.nan, math.inf, -math.inf])), st.integers(1, 3))
def test_extreme_and_empty_clips_stay_finite(value, batch):
    enc = SimulatedVideoEncoder(LABELS)
    clips = torch.full((batch, 8, len(LABELS), 2, 2), value)
    out = enc.encode_video(clips)
    assert torch.isfinite(out).all()
    torch.testing.assert_close(out.norm(dim=1), torch.ones(batch), atol=1e-5, rtol=0)
    empty = enc.encode_video(torch.zeros(batch, 8, len(LABELS), 1, 1))   # nothing covered: background
    assert torch.isfinite(empty).all()


def test_bad_video_input_is_an_input_error():
    enc = SimulatedVideoEncoder(LABELS)
    with pytest.raises(InputError, match="clips"):
        enc.encode_video(torch.zeros(1, 8, 3, 4, 4))
    with pytest.raises(InputError):
        SimulatedVideoEncoder([])
    with pytest.raises(InputError):
        SimulatedVideoEncoder(LABELS, noise_cosine=0.0)


def test_registry_builds_the_simulated_encoder_from_a_scene():
    scene = generate_scene("tiny", 0)
    enc = get_encoder("simulated", scene=scene)
    assert enc.input_kind == "labels" and enc.dim == 768 and enc.labels == list(LABELS)
    assert enc.background_labels == BACKGROUND
    with pytest.raises(InputError):
        get_encoder("simulated")


def test_label_coverage_is_a_partition_of_alpha_and_matches_labels():
    from fourlegs_engine.render import render_frame
    scene = generate_scene("tiny", 0)
    cam = scene.cameras.cameras(0, "test")[0]
    t = 6
    cov = render_label_coverage(scene, cam, t)
    assert cov.shape == (len(LABELS), cam.height, cam.width)
    alpha = render_frame(scene.gaussians.at(t), cam, outputs=("alpha",))["alpha"][..., 0]
    torch.testing.assert_close(cov.sum(0), alpha.clamp(0, 1), atol=1e-4, rtol=0)
    present = set(np.unique(scene.gaussians.labels[t]).tolist())
    shown = {i for i in range(len(LABELS)) if cov[i].max() > 0.05}
    assert shown <= present and {0, 1} <= shown                          # floor and wall are seen
    tube = label_coverage_tube([cov] * 3, 0)
    assert tube.shape == (8,) + tuple(cov.shape)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**64 - 1), st.integers(1, 40), st.integers(1, 120), st.integers(0, 5000))
def test_hash_kernels_are_bit_identical_to_the_numpy_reference(head, batch, width, first_counter):
    from fourlegs_engine.demo import simulated, simulated_kernels

    if not simulated_kernels.available():
        pytest.skip("numba is not installed")
    rng = np.random.default_rng(head % 1000)
    values = rng.integers(0, 4097, (batch, width)).astype(np.uint64)
    reference = np.full(batch, head, dtype=np.uint64)
    for col in values.T:
        reference = simulated._splitmix64(reference ^ col)
    keys = simulated_kernels.fold_keys(head, values)
    np.testing.assert_array_equal(keys, reference)
    counters = np.arange(width) + first_counter
    np.testing.assert_array_equal(simulated_kernels.uniforms(keys, first_counter, width),
                                  simulated._uniform(keys, counters))


def test_encoder_features_do_not_depend_on_the_hash_kernels(monkeypatch):
    """The numba path and the numpy fallback give the same bits (the fallback serves where numba is missing)."""
    from fourlegs_engine.demo import simulated_kernels

    enc = SimulatedVideoEncoder(LABELS, background_labels=BACKGROUND, camera="cam01")
    cov = torch.rand(37, 8, len(LABELS), dtype=torch.float64) / len(LABELS)
    fast = enc.encode_coverage(cov)
    monkeypatch.setattr(simulated_kernels, "available", lambda: False)
    torch.testing.assert_close(enc.encode_coverage(cov), fast, rtol=0, atol=0)
