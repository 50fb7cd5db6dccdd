"""RelevancyHead: relevancy straight from latents equals decode-then-score (float64 reference)."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from fourlegs_engine.language.autoencoder import FeatureDecoder
from fourlegs_engine.query.engine import QueryEngine, QueryOptions
from fourlegs_engine.query.head import RelevancyHead
from fourlegs_engine.query.lerf import l2_normalize, relevancy_reference

from _query_helpers import CANON, two_cluster_scene


def trained_like_decoder(dims=(16, 24, 32, 48), seed=0) -> FeatureDecoder:
    """A decoder in eval mode with non-trivial BatchNorm statistics (as after training)."""
    torch.manual_seed(seed)
    dec = FeatureDecoder(dims).eval()
    for m in dec.net:
        if isinstance(m, torch.nn.BatchNorm1d):
            m.running_mean.normal_()
            m.running_var.uniform_(0.2, 3.0)
            m.weight.data.normal_()
            m.bias.data.normal_()
    return dec


def reference(dec: FeatureDecoder, z: np.ndarray, queries: np.ndarray, refs: np.ndarray) -> np.ndarray:
    """(M,Q) float64 relevancy of the decoded features (decoder run in float64)."""
    d64 = FeatureDecoder(dec.dims).double().eval()
    d64.load_state_dict(dec.state_dict())
    with torch.no_grad():
        feats = d64(torch.from_numpy(z).double()).numpy()
    return np.stack([relevancy_reference(feats, q, refs) for q in queries], 1)


def unit(rng, n, d):
    x = rng.normal(size=(n, d))
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def test_head_equals_float64_decode_then_score():
    dec = trained_like_decoder()
    head = RelevancyHead.from_decoder(dec)
    assert head is not None
    rng = np.random.default_rng(1)
    z = rng.normal(size=(700, 16)) * rng.uniform(0.01, 3.0, size=(700, 1))
    z[:5] = 0.0  # empty pixels: their rendered latent is 0
    queries, refs = unit(rng, 3, 48), unit(rng, 5, 48)
    got = head.relevancy_many(torch.from_numpy(z).float(), torch.from_numpy(queries).float(),
                              torch.from_numpy(refs).float(), scale=10.0).numpy()
    np.testing.assert_allclose(got, reference(dec, z.astype(np.float32).astype(np.float64), queries, refs), atol=2e-6)


def test_query_equal_to_a_reference_scores_at_most_one_half_exactly():
    dec = trained_like_decoder(seed=3)
    head = RelevancyHead.from_decoder(dec)
    rng = np.random.default_rng(4)
    refs = torch.from_numpy(unit(rng, 4, 48)).float()
    z = torch.randn(200, 16)
    r = head.relevancy_many(z, refs[2:3], refs, scale=10.0)[:, 0]
    assert torch.all(r <= 0.5) and torch.any(r == 0.5)


@settings(max_examples=40, deadline=None)
@given(st.one_of(st.floats(min_value=-40, max_value=40), st.sampled_from([36.0, 37.5, 38.0])),
       st.sampled_from(["none", "nan", "inf", "-inf"]))
def test_extreme_latents_stay_finite(log_scale, poison):
    dec = trained_like_decoder(seed=5)
    head = RelevancyHead.from_decoder(dec)
    z = torch.randn(64, 16, generator=torch.Generator().manual_seed(0)) * float(10.0 ** log_scale)
    if poison != "none":
        z[::3, 1] = float(poison)
    refs = l2_normalize(torch.randn(4, 48, generator=torch.Generator().manual_seed(1)))
    q = l2_normalize(torch.randn(1, 48, generator=torch.Generator().manual_seed(2)))
    r = head.relevancy_many(z, q, refs, scale=10.0)
    assert torch.isfinite(r).all() and (r >= 0).all() and (r <= 1).all()
    if poison == "none" and abs(log_scale) <= 6:
        np.testing.assert_allclose(r.numpy(), reference(dec, z.double().numpy(), q.double().numpy(),
                                                        refs.double().numpy()), atol=2e-5)


def test_only_qualifying_decoders_get_a_head():
    assert RelevancyHead.from_decoder(FeatureDecoder((16, 24, 32, 48)).train()) is None  # batch statistics
    assert RelevancyHead.from_decoder(FeatureDecoder((16, 24, 32, 48)).eval().to(torch.bfloat16)) is None
    assert RelevancyHead.from_decoder(FeatureDecoder((16, 64, 8)).eval()) is None  # nothing to save
    assert RelevancyHead.from_decoder(object()) is None
    assert RelevancyHead.from_decoder(FeatureDecoder((16, 24, 32, 48)).eval()) is not None


class DecoderField:
    """A field with a real FeatureDecoder; ``use_head=False`` hides the decoder from the engine."""

    canonical_phrases = CANON

    def __init__(self, latents, decoder, use_head=True):
        self.latents = latents
        self._decoder = decoder
        if use_head:
            self.decoder = decoder

    @torch.no_grad()
    def decode(self, z):
        return self._decoder(torch.nan_to_num(torch.as_tensor(z, dtype=torch.float32)))


@pytest.mark.parametrize("spatial", ["exact", "fast"])
def test_engine_with_and_without_head_agree(spatial):
    scene, field, enc, _ = two_cluster_scene()
    T, N, d = field.latents.shape
    dec = trained_like_decoder(dims=(d, 12, 10, 16), seed=7)  # D=16: the helper encoder's dimension
    lat = np.asarray(field.latents, dtype=np.float32)
    with_head = QueryEngine(scene, DecoderField(lat, dec), enc, QueryOptions.exact(spatial=spatial))
    plain = QueryEngine(scene, DecoderField(lat, dec, use_head=False), enc, QueryOptions.exact(spatial=spatial))
    assert with_head.head is not None and plain.head is None
    q = "a ball flying"
    a, b = with_head.temporal(q), plain.temporal(q)
    np.testing.assert_allclose(with_head.gaussian_relevancy(q, 1).numpy(), plain.gaussian_relevancy(q, 1).numpy(),
                               atol=1e-5)
    assert a.segment == b.segment
    cam = scene.cameras.cameras(1, "all")[0]
    np.testing.assert_allclose(with_head.relevancy_map(q, cam, 1)["relevancy"],
                               plain.relevancy_map(q, cam, 1)["relevancy"], atol=1e-5)


# ----------------------------------------------------------------------------- windowed relevancy (norm bounds)
WIDE = (16, 40, 80, 120)  # last hidden width 80 > BOUND_RANK: |Rh|² is bounded, not computed


def decaying_decoder(dims, seed, decay=0.85) -> FeatureDecoder:
    """``trained_like_decoder`` whose last layer has singular values 2·decay^i, as trained decoders'
    concentrate (the bench decoder keeps ~97% of |Rh|² in its top 16 directions)."""
    dec = trained_like_decoder(dims, seed=seed)
    last = dec.net[-1]
    u, _, vt = torch.linalg.svd(last.weight.data, full_matrices=False)
    s = 2.0 * decay ** torch.arange(vt.shape[0], dtype=torch.float32)
    last.weight.data = (u * s) @ vt
    return dec


@settings(max_examples=40, deadline=None)
@given(st.floats(min_value=0.3, max_value=0.9), st.floats(min_value=0.0, max_value=0.05),
       st.integers(min_value=0, max_value=3))
def test_windowed_relevancy_is_exact_inside_and_decides_as_exact_outside(low, width, seed):
    dec = (decaying_decoder if seed % 2 else trained_like_decoder)(WIDE, seed=seed)
    head = RelevancyHead.from_decoder(dec)
    assert head._bounds is None and head.norm_bounds.vectors.shape == (80, 32)  # built on first use
    rng = np.random.default_rng(seed)
    z = rng.normal(size=(400, 16)) * rng.uniform(0.01, 3.0, size=(400, 1))
    q, refs = unit(rng, 1, 120), unit(rng, 4, 120)
    high = low + width
    values, exact = head.relevancy_windowed(torch.from_numpy(z).float(), torch.from_numpy(q[0]).float(),
                                            torch.from_numpy(refs).float(), scale=10.0, window=(low, high))
    want = reference(dec, z.astype(np.float32).astype(np.float64), q, refs)[:, 0]
    values, exact = values.double().numpy(), exact.numpy()
    np.testing.assert_allclose(values[exact], want[exact], atol=2e-6)
    below, above = ~exact & (values <= low), ~exact & (values > high)
    assert np.array_equal(below | above, ~exact)  # a bound is always clear of the window
    assert np.all(want[below] <= low) and np.all(want[above] > high)
    assert np.all(values[below] >= want[below] - 2e-6) and np.all(values[above] <= want[above] + 2e-6)  # bounds


def test_windowed_relevancy_skips_most_rows_of_a_narrow_window():
    dec = decaying_decoder(WIDE, seed=1)
    head = RelevancyHead.from_decoder(dec)
    rng = np.random.default_rng(2)
    z = torch.from_numpy(rng.normal(size=(2000, 16))).float()
    q, refs = torch.from_numpy(unit(rng, 1, 120)[0]).float(), torch.from_numpy(unit(rng, 4, 120)).float()
    full = head.relevancy_many(z, q[None], refs, scale=10.0)[:, 0]
    mid = float(full.median())
    _, exact = head.relevancy_windowed(z, q, refs, scale=10.0, window=(mid, mid + 1e-3))
    assert 0 < int(exact.sum()) < 0.5 * len(exact)  # rows near the window still get their exact value


@pytest.mark.parametrize("poison", [float("nan"), float("inf"), 1e38])
def test_windowed_relevancy_of_extreme_latents_is_finite(poison):
    dec = trained_like_decoder(WIDE, seed=2)
    head = RelevancyHead.from_decoder(dec)
    z = torch.randn(50, 16, generator=torch.Generator().manual_seed(0))
    z[::4, 3] = poison
    refs = l2_normalize(torch.randn(4, 120, generator=torch.Generator().manual_seed(1)))
    q = l2_normalize(torch.randn(120, generator=torch.Generator().manual_seed(2)), dim=0)
    values, exact = head.relevancy_windowed(z, q, refs, scale=10.0, window=(0.45, 0.55))
    full = head.relevancy_many(z, q[None], refs, scale=10.0)[:, 0]
    assert torch.isfinite(values).all()
    np.testing.assert_allclose(values[exact].numpy(), full[exact].numpy(), atol=1e-6)
    assert torch.equal(values[~exact] > 0.55, full[~exact] > 0.55) and torch.equal(values[~exact] <= 0.45,
                                                                                    full[~exact] <= 0.45)
    if poison == 1e38:  # activations overflow: no bound, the exact path scores them as zero features (0.5)
        assert exact[::4].all() and torch.all(values[::4] == 0.5)


def test_codebook_refine_with_norm_bounds_answers_as_the_exact_path(tmp_path):
    from _query_helpers import TableTextEncoder

    scene, field, _, _ = two_cluster_scene(T=6, active=(2, 3), D=128)
    T, N, d = field.latents.shape
    dec = decaying_decoder((d, 24, 48, 128), seed=7)  # H=48: |Rh|² bounded from 32 directions
    rng = np.random.default_rng(0)
    lat = (np.asarray(field.latents) + rng.normal(scale=0.2, size=(T, N, d))).astype(np.float32)
    with torch.no_grad():  # texts embedded where the decoder puts the two clusters' latents
        at = {name: dec(torch.from_numpy(lat[t, rows].mean(0, keepdims=True))).numpy()[0]
              for name, t, rows in (("a ball flying", 2, slice(0, N // 2)), ("object", 0, slice(N // 2, N)))}
    table = dict(at, **{c: rng.normal(size=128) for c in CANON[1:]})
    enc = TableTextEncoder(table, 128)
    exact = QueryEngine(scene, DecoderField(lat, dec), enc, QueryOptions.exact())
    refined = QueryEngine(scene, DecoderField(lat, dec), enc, QueryOptions(path="codebook", codebook_size=6, codebook_refine=1.0, codebook_samples=10 ** 9), codebook_dir=tmp_path)
    want = exact.temporal("a ball flying")
    assert want.found and want.segment == (1, 4)  # timesteps 2, 3 dilated by 1
    got = refined.temporal("a ball flying")
    np.testing.assert_array_equal(got.positive, want.positive)
    assert got.segment == want.segment and got.r_avg == pytest.approx(want.r_avg, abs=1e-6)
    # the same engine scoring every re-scored row exactly returns the very same counts
    unbounded = QueryEngine(scene, DecoderField(lat, dec), enc, QueryOptions(path="codebook", codebook_size=6, codebook_refine=1.0, codebook_samples=10 ** 9), codebook_dir=tmp_path)
    score_any, score_any_rows = unbounded.scorer.score_any, unbounded.scorer.score_any_rows
    unbounded.scorer.score_any = lambda q, flat, window=None: score_any(q, flat, None)
    unbounded.scorer.score_any_rows = lambda q, flat, window=None: score_any_rows(q, flat, None)
    plain = unbounded.temporal("a ball flying")
    np.testing.assert_array_equal(got.scores, plain.scores)
    assert got.r_avg == plain.r_avg and unbounded.stats["bounded_latents"] == 0
    assert refined.stats["rescored_latents"] == unbounded.stats["rescored_latents"] > 0
    assert refined.stats["bounded_latents"] > 0  # some re-scored rows were decided by their bounds alone


def test_relevancy_gradient_matches_central_differences_of_the_float64_reference():
    dec = trained_like_decoder(seed=5)
    head = RelevancyHead.from_decoder(dec)
    rng = np.random.default_rng(7)
    z = rng.normal(size=(12, 16)) * rng.uniform(0.2, 2.0, size=(12, 1))
    query, refs = unit(rng, 1, 48), unit(rng, 4, 48)
    with torch.inference_mode():  # callers score inside inference mode; the gradient must still work
        grad = head.relevancy_gradient(torch.from_numpy(z).float(), torch.from_numpy(query[0]).float(),
                                       torch.from_numpy(refs).float(), scale=10.0).numpy()
    h = 1e-6
    numeric = np.zeros_like(z)
    for j in range(z.shape[1]):
        step = np.zeros_like(z)
        step[:, j] = h
        numeric[:, j] = (reference(dec, z + step, query, refs)[:, 0] - reference(dec, z - step, query, refs)[:, 0]) / (2 * h)
    assert grad.dtype == np.float64 and np.abs(numeric).max() > 1e-3  # a gradient worth checking
    np.testing.assert_allclose(grad, numeric, rtol=1e-4, atol=1e-7)
    bad = head.relevancy_gradient(torch.tensor([[np.nan] * 16, [np.inf] * 16]), torch.from_numpy(query[0]).float(),
                                  torch.from_numpy(refs).float(), scale=10.0)
    assert torch.isfinite(bad).all()


def test_the_engine_samples_r_avg_with_first_order_controls_closer_to_exact_than_the_codes(tmp_path):
    from _query_helpers import TableTextEncoder

    scene, field, _, _ = two_cluster_scene(T=6, active=(2, 3), D=128)
    T, N, d = field.latents.shape
    dec = decaying_decoder((d, 24, 48, 128), seed=7)
    rng = np.random.default_rng(0)
    lat = (np.asarray(field.latents) + rng.normal(scale=0.1, size=(T, N, d))).astype(np.float32)
    with torch.no_grad():
        at = dec(torch.from_numpy(lat[2, :N // 2].mean(0, keepdims=True))).numpy()[0]
    enc = TableTextEncoder(dict({"a ball flying": at}, **{c: rng.normal(size=128) for c in CANON}), 128)
    eng = QueryEngine(scene, DecoderField(lat, dec), enc,  # soft scores: relevancies spread below saturation
                      QueryOptions(path="codebook", codebook_size=8, relevancy_scale=1.0), codebook_dir=tmp_path)
    held = np.flatnonzero(eng.codebook.histogram.sum(0))
    [(codes, exact, controls)] = eng.codebook_path.sample_members("a ball flying", [held], [T * N], np.arange(T),
                                                                  np.random.default_rng(1))
    coded = eng.codebook_path.code_scores("a ball flying").double().numpy()[codes]
    assert controls is not None and np.abs(exact - coded).mean() > 1e-4
    assert np.abs(exact - controls).mean() * 3 < np.abs(exact - coded).mean()  # first order: much closer
    # every member sampled: the controls sum, code by code, to the code's relevancy times its count
    np.testing.assert_allclose(np.bincount(codes, controls, minlength=8)[held],
                               (np.bincount(codes, minlength=8) * eng.codebook_path.code_scores("a ball flying")
                                .double().numpy())[held], rtol=0, atol=1e-4)
    [(_, _, strided)] = eng.codebook_path.sample_members("a ball flying", [held], [10], np.arange(0, T, 2),
                                                         np.random.default_rng(1))
    assert strided is None  # a code is the mean of its members over every timestep, not over a stride
