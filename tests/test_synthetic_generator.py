"""Synthetic scene generator: determinism, labels, plausibility, the demo cache, the CLI."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from fourlegs_engine.errors import InputError, OutputExistsError
from fourlegs_engine.demo import synthetic
from fourlegs_engine.demo.synthetic import (LABELS, QUERIES, SCRIPT, bundle_digest, ensure_demo_bundle,
                                            generate_scene, matrix_to_quaternion, read_queries,
                                            write_synthetic_bundle)
from fourlegs_engine.scene import load_bundle, quaternion_to_matrix


@pytest.fixture(scope="module")
def tiny():
    return generate_scene("tiny", 0)


def test_same_seed_gives_identical_bundle_and_other_seed_differs(tmp_path):
    a = write_synthetic_bundle(tmp_path / "a", "tiny", 3)
    b = write_synthetic_bundle(tmp_path / "b", "tiny", 3)
    c = write_synthetic_bundle(tmp_path / "c", "tiny", 4)
    assert bundle_digest(a) == bundle_digest(b)
    assert bundle_digest(a) != bundle_digest(c)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no staging left behind


def test_bundle_round_trip_keeps_labels_and_queries(tmp_path, tiny):
    path = write_synthetic_bundle(tmp_path / "s", "tiny", 0)
    scene = load_bundle(path)
    np.testing.assert_array_equal(np.asarray(scene.gaussians.labels), tiny.gaussians.labels)
    np.testing.assert_array_equal(np.asarray(scene.gaussians.means), tiny.gaussians.means)
    assert scene.metadata["labels"] == list(LABELS)
    assert read_queries(path) == {q: list(l) for q, l in QUERIES}
    assert scene.cameras.num_cameras("train") == 4 and scene.cameras.num_cameras("test") == 2


def test_sizes_match_the_spec(tiny):
    spec = synthetic.SIZES["tiny"]
    assert tiny.num_gaussians == spec.num_gaussians
    assert tiny.num_timesteps == spec.num_timesteps
    cam = tiny.cameras.cameras(0, "train")[0]
    assert (cam.width, cam.height) == (spec.width, spec.height)
    demo = generate_scene("demo", 0)
    assert abs(demo.num_gaussians - 30_000) <= 300 and demo.num_timesteps == 48
    assert demo.cameras.num_cameras("train") == 8


def test_labels_follow_the_script(tiny):
    labels = tiny.gaussians.labels
    T = tiny.num_timesteps
    assert labels.dtype == np.int32 and labels.shape == (T, tiny.num_gaussians)
    assert labels.min() >= 0 and labels.max() < len(LABELS)
    # every scripted action is present exactly on its frames (some action labels repeat or overlap)
    for action in SCRIPT:
        frames = synthetic._frames_of(action.start, action.end, T)
        if frames:
            for t in range(frames[0], frames[1] + 1):
                assert (labels[t] == LABELS.index(action.label)).any()
    # background never changes label; the ball is labelled flying only while it is in flight
    fg = tiny.gaussians.foreground
    assert (labels[:, ~fg] == labels[0, ~fg]).all()
    flying = LABELS.index("ball flying in the air")
    assert 0 < sum((labels[t] == flying).any() for t in range(T)) < T


def test_overlapping_and_repeated_actions_exist():
    jumps = [a for a in SCRIPT if a.label == "person jumping"]
    assert len(jumps) >= 2 and len({a.actor for a in jumps}) >= 2
    assert any(a.start < b.end and b.start < a.end for a in jumps for b in jumps if a is not b)


def test_scene_is_plausible(tiny):
    g = tiny.gaussians
    scales = np.exp(g.log_scales.max(axis=1))
    fg = g.foreground
    assert 0.005 <= scales[fg].min() and scales[fg].max() <= 0.06       # actors: ~1-5 cm splats
    person = np.isin(g.labels[0], [LABELS.index(n) for n in LABELS if n.startswith("person")])
    height = g.means[0, person, 2].max()
    assert 1.6 < height < 1.95                                           # people-sized
    assert g.means[0, :, 2].min() > -0.05                                # nothing below the floor
    # the ball flies above the hands and lands where the catcher's hands are
    flying = LABELS.index("ball flying in the air")
    ball = g.labels == flying
    heights = [g.means[t][ball[t], 2].mean() for t in range(tiny.num_timesteps) if ball[t].any()]
    assert max(heights) > 1.8
    for cam in tiny.cameras.cameras(0, "all"):   # every camera looks at the action
        uv, z = cam.project(g.means[0][fg])
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        assert inside.mean() > 0.6


def test_rotations_are_unit_and_finite(tiny):
    q = tiny.gaussians.rotations
    assert np.isfinite(q).all()
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-5)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda v: np.linalg.norm(v) > 1e-3),
       st.sampled_from([0.0, 1e-9, 1e-4]))
def test_matrix_to_quaternion_inverts_quaternion_to_matrix(v, eps):
    import torch
    q = np.asarray(v, dtype=np.float64)
    q /= np.linalg.norm(q)
    R = quaternion_to_matrix(torch.tensor(q)).numpy()
    # near-180-degree rotations are the delicate case: perturb toward them
    R = Rotation.from_matrix(R).as_matrix() if eps == 0 else Rotation.from_rotvec(
        Rotation.from_matrix(R).as_rotvec() / max(np.linalg.norm(Rotation.from_matrix(R).as_rotvec()), 1e-12)
        * (np.pi - eps)).as_matrix()
    back = matrix_to_quaternion(R)
    assert back[0] >= 0 and abs(np.linalg.norm(back) - 1) < 1e-12
    np.testing.assert_allclose(quaternion_to_matrix(torch.tensor(back)).numpy(), R, atol=1e-10)


def test_bad_arguments_are_input_errors(tmp_path):
    with pytest.raises(InputError, match="size"):
        generate_scene("huge", 0)
    with pytest.raises(InputError, match="seed"):
        generate_scene("tiny", -1)
    write_synthetic_bundle(tmp_path / "x", "tiny", 0)
    with pytest.raises(OutputExistsError):
        write_synthetic_bundle(tmp_path / "x", "tiny", 0)


def test_ensure_demo_bundle_generates_once_and_reuses(tmp_path, monkeypatch):
    monkeypatch.setenv("FOURLEGS_CACHE", str(tmp_path))
    path = ensure_demo_bundle("tiny", 1)
    stamp = (path / "scene.json").stat().st_mtime_ns
    assert ensure_demo_bundle("tiny", 1) == path
    assert (path / "scene.json").stat().st_mtime_ns == stamp
    assert path.parent.parent == tmp_path and f"v{synthetic.GENERATOR_VERSION}" in path.name
    assert ensure_demo_bundle("tiny", 2) != path


def test_generate_cli_writes_a_bundle(tmp_path, capsys):
    from fourlegs_engine.commands.main import main
    out = tmp_path / "scene"
    assert main(["generate", "--size", "tiny", "--seed", "5", "-o", str(out)]) == 0
    assert (out / "scene.json").is_file() and (out / "queries.json").is_file()
    assert main(["generate", "--size", "tiny", "-o", str(out)]) == 2     # exists: one-line error
    assert "already exists" in capsys.readouterr().err
