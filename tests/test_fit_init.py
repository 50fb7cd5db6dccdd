"""Initialisation of ``fourlegs fit``: triangulated feature matches with known cameras (OpenCV), the
``init`` option, and its errors."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from fourlegs_bench.fit import parse_runs
from fourlegs_engine.errors import InputError
from fourlegs_engine.fit import FitOptions
from fourlegs_engine.commands.fit import options_from_args, register
from fourlegs_engine.fit.init import initial_cloud
from fourlegs_engine.scene.camera import Camera

BASKETBALL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "panoptic-basketball"
needs_cv2 = pytest.mark.skipif(
    __import__("importlib").util.find_spec("cv2") is None,
    reason="OpenCV is not installed (pip install 'fourlegs[fit-features]')")


def _three_cameras() -> list[Camera]:
    """Three 640×480 cameras 4 m from the origin, 25° apart, looking at it (y down)."""
    cams = []
    for i, a in enumerate(np.radians([-25.0, 0.0, 25.0])):
        eye = (4.0 * np.sin(a), -1.0, 4.0 * np.cos(a))
        cams.append(Camera.look_at(eye, (0.0, 0.0, 0.0), up=(0.0, -1.0, 0.0), width=640, height=480, focal=500.0,
                                   name=str(i)))
    return cams


def _known_points(n: int = 60, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-0.8, 0.8, size=(n, 3))


def _identity_matches(n: int) -> dict[tuple[int, int], np.ndarray]:
    idx = np.stack([np.arange(n), np.arange(n)], 1)
    return {(0, 1): idx, (1, 2): idx, (0, 2): idx}


@needs_cv2
def test_triangulation_recovers_known_points_exactly_without_noise():
    from fourlegs_engine.fit.features import triangulate_matches

    cams, X = _three_cameras(), _known_points()
    keypoints = [c.project(X)[0] for c in cams]
    tri = triangulate_matches(cams, keypoints, _identity_matches(len(X)), min_views=3)
    assert tri.points.shape == X.shape and tri.inliers.all()
    # tracks come back in an order of their own: pair each with its nearest known point
    err = np.linalg.norm(tri.points[:, None] - X[None], axis=2).min(1)
    assert err.max() < 1e-6, err.max()
    assert tri.errors.max() < 1e-4


@needs_cv2
def test_triangulation_with_half_pixel_noise_stays_within_a_centimetre():
    """σ = 0.3 px at 4 m with f = 500 px is 2.4 mm across the view; depth from 25° baselines is worse,
    a few mm: every point lands within 1.5 cm, the median within 5 mm."""
    from fourlegs_engine.fit.features import triangulate_matches

    cams, X = _three_cameras(), _known_points(seed=1)
    rng = np.random.default_rng(2)
    keypoints = [c.project(X)[0] + rng.normal(0, 0.3, size=(len(X), 2)) for c in cams]
    tri = triangulate_matches(cams, keypoints, _identity_matches(len(X)), reprojection_px=1.5, min_views=3)
    assert len(tri.points) == len(X)
    err = np.linalg.norm(tri.points[:, None] - X[None], axis=2).min(1)
    assert np.median(err) < 0.005 and err.max() < 0.015, (np.median(err), err.max())


@needs_cv2
def test_wrong_and_two_view_matches_are_filtered_out():
    """A match that is inconsistent between its two views is not triangulated; a wrong match that two
    views cannot tell from a right one (a false point on the same ray of view 0) loses to the point the
    third view agrees with; a track seen by only two views is dropped when three must agree."""
    from fourlegs_engine.fit.features import triangulate_matches

    cams, X = _three_cameras(), _known_points(n=30, seed=3)
    keypoints = [c.project(X)[0] for c in cams]
    matches = _identity_matches(len(X))
    # view 2 loses its observation of point 0: that track has two views left
    matches[(1, 2)] = matches[(1, 2)][1:]
    matches[(0, 2)] = matches[(0, 2)][1:]
    # a wrong match between point 5 in view 0 and point 9 in view 1
    matches[(0, 1)] = np.concatenate([matches[(0, 1)], [[5, 9]]])
    # a false point 0.5 m behind point 7 on view 0's ray, seen as an extra keypoint of view 1
    ray = X[7] - cams[0].center
    false_point = X[7] + 0.5 * ray / np.linalg.norm(ray)
    keypoints[1] = np.concatenate([keypoints[1], cams[1].project(false_point[None])[0]])
    matches[(0, 1)] = np.concatenate([matches[(0, 1)], [[7, len(X)]]])
    tri = triangulate_matches(cams, keypoints, matches, min_views=3)
    err = np.linalg.norm(tri.points[:, None] - X[None], axis=2)
    assert err.min(1).max() < 1e-6  # every point is a true one
    assert np.linalg.norm(tri.points - false_point, axis=1).min() > 0.4
    assert sorted(err.argmin(1).tolist()) == list(range(1, len(X)))
    assert (tri.inliers.sum(1) == 3).all()
    two = triangulate_matches(cams, keypoints, matches, min_views=2)
    assert 0 in set(np.linalg.norm(two.points[:, None] - X[None], axis=2).argmin(1).tolist())


@needs_cv2
def test_fundamental_matrix_and_matching_enforce_the_epipolar_constraint():
    from fourlegs_engine.fit.features import FeatureOptions, fundamental_matrix, match_pair

    cams, X = _three_cameras(), _known_points(n=40, seed=4)
    uv_a, uv_b = cams[0].project(X)[0], cams[1].project(X)[0]
    F = fundamental_matrix(cams[0], cams[1])
    xa = np.concatenate([uv_a, np.ones((len(X), 1))], 1)
    xb = np.concatenate([uv_b, np.ones((len(X), 1))], 1)
    line = xa @ F.T
    dist = np.abs((line * xb).sum(1)) / np.linalg.norm(line[:, :2], axis=1)
    assert dist.max() < 1e-8
    # identical descriptors for corresponding points; ten of view b's keypoints moved 5 px off the line
    des = np.random.default_rng(5).random((len(X), 128)).astype(np.float32) * 100
    moved = uv_b.copy()
    normal = line[:10, :2] / np.linalg.norm(line[:10, :2], axis=1, keepdims=True)
    moved[:10] += 5.0 * normal
    pairs = match_pair(cams[0], cams[1], uv_a, des, moved, des, FeatureOptions(epipolar_px=1.5))
    assert sorted(pairs[:, 0].tolist()) == list(range(10, len(X)))
    assert (pairs[:, 0] == pairs[:, 1]).all()


def test_init_option_is_validated():
    with pytest.raises(InputError, match="init: must be one of hull, features, hull\\+features"):
        FitOptions(init="sfm").check()
    with pytest.raises(InputError, match="init: must be one of"):
        initial_cloud([], [], None, method="colmap")
    assert "init" not in FitOptions().fingerprint()  # fits started before the option still resume
    parser = __import__("argparse").ArgumentParser()
    register(parser.add_subparsers())
    args = parser.parse_args(["fit", "data", "-o", "out", "--init", "hull+features"])
    assert options_from_args(args).init == "hull+features"
    with pytest.raises(SystemExit):
        parser.parse_args(["fit", "data", "-o", "out", "--init", "voxels"])
    assert parse_runs("f:init=features,first_iterations=100") == [("f", {"init": "features", "first_iterations": 100})]


def test_features_without_opencv_give_one_clear_line(monkeypatch):
    monkeypatch.setitem(sys.modules, "cv2", None)  # import cv2 raises ImportError
    for method in ("features", "hull+features"):
        with pytest.raises(InputError) as info:
            FitOptions(init=method).check()
        assert "\n" not in str(info.value)
        assert str(info.value).startswith("init: the 'features' initialisation needs OpenCV")
        assert "pip install 'fourlegs[fit-features]'" in str(info.value)
    assert FitOptions(init="hull").check().init == "hull"


@needs_cv2
@pytest.mark.skipif(not BASKETBALL.is_dir(), reason=f"the shared Panoptic capture is not at {BASKETBALL}")
def test_basketball_foreground_features_lie_on_the_visual_hull():
    """Two independent reconstructions of the players at t = 0 (27 views at 160×90): the triangulated
    foreground features lie within 10 cm of the carved hull's surface voxels (4 cm); the mixed cloud
    keeps every triangulated point under its caps."""
    from scipy.spatial import cKDTree

    from fourlegs_engine.fit import Capture
    from fourlegs_engine.fit.features import FeatureOptions, feature_cloud
    from fourlegs_engine.fit.init import carve_visual_hull, look_at_point

    cap = Capture(BASKETBALL)
    idx = cap.camera_indices("train", None)
    cams = [cap.train.cameras[0][c].scaled(0.25) for c in idx]
    size = (cams[0].width, cams[0].height)
    images = [cap.load_image("train", 0, c, size) for c in idx]
    masks = [cap.load_mask("train", 0, c, size) for c in idx]
    points, colors, scales, fg = feature_cloud(cams, images, masks, FeatureOptions(upsample=4))
    assert fg.sum() >= 20 and (~fg).sum() >= 100, (fg.sum(), (~fg).sum())
    assert np.isfinite(points).all() and np.isfinite(scales).all() and (scales > 0).all()
    assert ((colors >= 0) & (colors <= 1)).all()
    hull, _ = carve_visual_hull(cams, masks, images, voxel=0.04, half_extent=2.5, center=look_at_point(cams))
    dist, _ = cKDTree(hull).query(points[fg])
    assert np.mean(dist < 0.10) >= 0.9, np.percentile(dist, [50, 90])
    # hull+features: the triangulated points are all there, the proxy fills the rest of the caps
    cloud = initial_cloud(cams, images, masks, voxel=0.04, max_foreground=1000, max_background=2000,
                          method="hull+features", feature_options=FeatureOptions(upsample=4))
    assert cloud.foreground.sum() == min(1000, len(hull) + fg.sum()) and (~cloud.foreground).sum() == 2000
    mixed = cKDTree(cloud.points)
    assert (mixed.query(points)[0] < 1e-9).all()
    assert np.isfinite(cloud.scales).all() and (cloud.scales > 0).all()


def test_bench_table_of_a_first_timestep_only_run_shows_the_init_columns(tmp_path):
    """A 0:1 run has no later timesteps: its seconds are JSON null (no NaN in the JSON), shown as –."""
    import json

    from fourlegs_bench.fit import _pareto_plot, markdown_table

    record = {"run": "hull", "knobs": {"init": "hull", "first_iterations": 100}, "num_gaussians": 51234,
              "resolution": [320, 180], "init_wall_s": 80.2, "init_cpu_s": 4.63, "init_points": 39266,
              "init_foreground_points": 9266, "init_train_psnr": 22.11, "first_timestep_wall_s": 900.0,
              "first_timestep_cpu_s": 340.0, "later_timestep_wall_s": None, "later_timestep_cpu_s": None,
              "psnr_first_timestep": 25.5, "ssim_first_timestep": 0.81, "psnr_mean": 25.5, "ssim_mean": 0.81,
              "psnr_first_k": 25.5, "psnr_last_k": 25.5, "drift_k": 1}
    json.dumps(record, allow_nan=False)
    row = markdown_table([record], 150).splitlines()[2]
    assert row.startswith("| hull | init=hull, first_iterations=100 | 80.2 (4.6) | 39266 (9266) | 22.11 | 51234 |")
    assert "| – (–) |" in row
    _pareto_plot([record], tmp_path / "pareto.png")
    assert (tmp_path / "pareto.png").stat().st_size > 0


def test_bench_fit_writes_each_timesteps_times_as_it_finishes_keeping_a_cancelled_runs(tmp_path):
    import json

    from fourlegs_bench.fit import _Timer
    from fourlegs_engine.fit import FitEvent

    path = tmp_path / "run.timing.json"
    path.write_text(json.dumps({"0": {"wall_s": 5.0, "cpu_s": 4.0, "train_psnr": 30.0}}))  # a cancelled run's
    timer = _Timer("r", 3, path)
    timer(FitEvent("timestep", 0, train_psnr=30.0, resumed=True))
    timer(FitEvent("timestep", 1, train_psnr=27.0))
    first = json.loads(path.read_text())
    assert set(first) == {"0", "1"} and first["0"]["cpu_s"] == 4.0 and first["1"]["train_psnr"] == 27.0
    timer(FitEvent("timestep", 2, train_psnr=float("nan")))
    last = json.loads(path.read_text())
    assert set(last) == {"0", "1", "2"} and last["2"]["train_psnr"] is None and last["2"]["cpu_s"] >= 0


def test_bench_fit_reports_each_fitted_timestep_as_it_finishes(capsys):
    from fourlegs_bench.fit import _Timer
    from fourlegs_engine.fit import FitEvent

    timer = _Timer("g1200", 3)
    timer(FitEvent("iteration", 0, 1, 10, 0.5, 20.0))
    timer(FitEvent("timestep", 0, train_psnr=21.5, resumed=True))  # resumed: not timed, not reported
    assert capsys.readouterr().out == "" and timer.per_timestep == {}
    timer(FitEvent("timestep", 1, train_psnr=27.25))
    line = capsys.readouterr().out.strip()
    rec = timer.per_timestep[1]
    assert line == (f"[bench fit] g1200: timestep 1 fitted (1/3) in {rec['wall_s']:.1f} s ({rec['cpu_s']:.1f} CPU s), "
                    "training PSNR 27.25 dB")
