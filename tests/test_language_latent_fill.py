"""The ``fill="latents"`` plan: only the stride's grid is extracted and lifted; every in-between timestep of
the field is the normalized interpolation of each Gaussian's own latents at its two lifted neighbours."""
from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest
import torch

from fourlegs_engine.language.autoencoder import AETrainOptions, train_autoencoder
from fourlegs_engine.language.distill import distill_scene
from fourlegs_engine.language.extract import ExtractOptions, check_features, extract_features, feature_store
from fourlegs_engine.language.skipping import encoded_timesteps
from fourlegs_engine.pipeline import text_encoder
from fourlegs_engine.scene.bundle import load_bundle, write_bundle

from _language_helpers import micro_scene, one_thread  # noqa: F401  (one torch thread per test)

T, STRIDE = 7, 3
GRID = encoded_timesteps(T, STRIDE)                      # 0, 3, 6
BALL = 2                                                  # the label of the ball's Gaussians


def _fast_ball_scene():
    """The micro scene with its ball crossing the scene in 6 timesteps (0.27 per timestep, three ball widths
    between two grid timesteps), so crop features at fixed pixels lose it in between."""
    scene = micro_scene(T=T, cameras=4)
    means = np.array(scene.gaussians.means, dtype=np.float32)
    ball = np.asarray(scene.gaussians.labels[0]) == BALL
    for t in range(T):
        means[t, ball] = means[0, ball] - means[0, ball].mean(0) + [0.8 - 1.6 * t / (T - 1), 0.2, 0.9]
    scene.gaussians = dataclasses.replace(scene.gaussians, means=means)
    return scene


def _field(root, fill):
    """Extract with stride 3 and ``fill``, train a small autoencoder, lift; the bundle reopened."""
    scene = load_bundle(root)
    extract_features(scene, text_encoder(scene), ExtractOptions(timestep_stride=STRIDE, fill=fill))
    train_autoencoder(scene, AETrainOptions(epochs=4, samples=2048, batch_size=64))
    result = distill_scene(scene, mode="lift", view_scale=0.5)
    return load_bundle(root), result


@pytest.fixture(scope="module")
def latent_field(tmp_path_factory):
    root = write_bundle(_fast_ball_scene(), tmp_path_factory.mktemp("latentfill") / "scene")
    scene, result = _field(root, "latents")
    return root, scene, result


def test_only_the_grid_is_extracted_and_the_features_count_as_complete(latent_field):
    root, scene, result = latent_field
    store = feature_store(scene)
    assert store.config["fill"] == "latents" and store.config["timestep_stride"] == STRIDE
    assert [t for t in range(T) if store.step_path(t).is_file()] == GRID
    check = check_features(scene)
    assert check["complete"] and check["missing"] == []
    assert result.filled == [t for t in range(T) if t not in GRID]


def test_in_between_latents_are_the_float64_interpolation_of_each_gaussians_own(latent_field):
    _, scene, result = latent_field
    latents = np.load(result.latents, mmap_mode="r")
    assert latents.shape == (T, scene.num_gaussians, 128) and latents.dtype == np.float16
    lat = np.asarray(latents, np.float64)
    assert np.all(np.isfinite(lat))
    for t in range(T):
        if t in GRID:
            continue
        a, b = max(g for g in GRID if g < t), min(g for g in GRID if g > t)
        w = (t - a) / (b - a)
        mix = (1 - w) * lat[a] + w * lat[b]
        norm = np.linalg.norm(mix, axis=1, keepdims=True)
        expect = np.where(norm > 1e-8, mix / np.maximum(norm, 1e-8), 0.0)
        np.testing.assert_allclose(lat[t], expect, atol=2e-3)
        unseen = (np.abs(lat[a]).sum(1) == 0) & (np.abs(lat[b]).sum(1) == 0)
        assert np.all(lat[t][unseen] == 0)                        # seen by neither neighbour: zero latent
    norms = np.linalg.norm(lat, axis=-1)
    assert np.all((np.abs(norms - 1) < 3e-3) | (norms == 0)) and (norms > 0).mean() > 0.5


def test_the_in_between_relevancy_of_a_moving_ball_follows_it(latent_field):
    """Rendered from the test camera at an in-between timestep, the field is most ball-like where the ball
    is then, not where either lifted neighbour saw it (the Gaussians carry their latents along)."""
    from fourlegs_engine.render import render_frame
    _, scene, result = latent_field
    lat = np.asarray(np.load(result.latents), np.float32)
    labels = np.asarray(scene.gaussians.labels[0])
    refs = np.stack([lat[GRID][:, labels == label].reshape(-1, 128).mean(0) for label in range(3)])
    refs /= np.linalg.norm(refs, axis=1, keepdims=True)               # each label's direction in the field
    camera = scene.cameras.cameras(0, "test")[0].scaled(4.0)
    centre = {t: camera.project(np.asarray(scene.gaussians.means[t])[labels == BALL].mean(0, keepdims=True))[0][0]
              for t in range(T)}
    for t in (1, 2, 4, 5):
        frame = scene.gaussians.at(t)
        out = render_frame(frame, camera, outputs=("features",), features=torch.from_numpy(lat[t]))
        feats = out["features"].numpy()                                # (H, W, 128); empty pixels zero
        score = feats @ refs[BALL] - feats @ refs[0]                   # ball against floor, per pixel
        ys, xs = np.mgrid[:score.shape[0], :score.shape[1]]

        def around(uv):                                                # mean score within 3 px of a point
            return np.mean(score[(xs - uv[0]) ** 2 + (ys - uv[1]) ** 2 <= 9.0])
        a, b = max(g for g in GRID if g < t), min(g for g in GRID if g > t)
        here, before, after = around(centre[t]), around(centre[a]), around(centre[b])
        assert here > max(before, after) + 0.1


def test_a_sharded_or_damaged_lift_resumes_to_the_uninterrupted_field(latent_field, tmp_path):
    root, scene, result = latent_field
    whole = np.asarray(np.load(result.latents), np.float32)
    out = tmp_path / "field"
    first = distill_scene(scene, mode="lift", view_scale=0.5, timesteps=[1], out_dir=out)
    assert first.latents is None and first.filled == [1]                  # lifts 0 and 3, fills 1
    assert sorted(p.name for p in (out / "steps").glob("t*.npy")) == ["t000000.npy", "t000001.npy", "t000003.npy"]
    damaged = out / "steps" / "t000003.npy"
    data = bytearray(damaged.read_bytes())
    data[-7] ^= 0x55                                                       # same shape, other bytes
    damaged.write_bytes(bytes(data))
    rest = distill_scene(scene, mode="lift", view_scale=0.5, out_dir=out)
    assert 3 not in rest.skipped and {0, 1} <= set(rest.skipped)          # the damaged step is lifted again
    np.testing.assert_array_equal(np.asarray(np.load(rest.latents), np.float32), whole)


def test_the_autoencoder_trains_on_the_extracted_grid_only(latent_field, tmp_path):
    root, _, _ = latent_field
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    scene = load_bundle(copy)
    (copy / "features" / "t000003.npy").unlink()
    with pytest.raises(Exception, match="timesteps 3 are missing"):
        train_autoencoder(scene, AETrainOptions(epochs=1, samples=512), overwrite=True)


def test_the_bench_check_counts_label_changes_between_encoded_timesteps():
    from fourlegs_bench.latent_fill_check import decode_interpolate_encode, label_change_share
    labels = np.zeros((5, 4), np.int32)                # grid of stride 4: 0, 4; in between 1, 2, 3
    labels[2:, 0] = 1                                  # Gaussian 0 changes at 2: differs from t=0 at 2 only
    labels[3, 1] = 2                                   # Gaussian 1 holds another label at 3 alone
    # nearer neighbours: 1 -> 0, 2 -> 0 (tie: earlier), 3 -> 4; changed pairs: (2, g0), (3, g1) of 3 x 4
    assert label_change_share(labels, 4) == pytest.approx(2 / 12)
    assert label_change_share(labels, 1) == 0.0
    identity = torch.nn.Identity()
    before = torch.tensor([[1.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    after = torch.tensor([[0.0, 1.0], [0.6, 0.8], [0.0, 0.0]])
    out = decode_interpolate_encode(lambda x: torch.nn.functional.normalize(x, dim=1), identity, before, after, 0.25)
    np.testing.assert_allclose(out[0].numpy(), np.array([0.75, 0.25]) / np.hypot(0.75, 0.25), rtol=1e-6)
    np.testing.assert_allclose(out[1].numpy(), [0.6, 0.8], rtol=1e-6)   # seen at one neighbour: its feature
    assert torch.all(out[2] == 0)                                        # seen by neither: zero
