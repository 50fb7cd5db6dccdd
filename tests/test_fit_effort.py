"""Iterations where the motion is (fit/effort.py) and the ball-region PSNR of the fit's evaluation."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy import ndimage
from hypothesis import given, settings
from hypothesis import strategies as st

import _fit_helpers as fh
from fourlegs_engine.errors import InputError
from fourlegs_engine.fit import FitOptions, fit_capture
from fourlegs_engine.fit.effort import MOVING_THRESHOLD, iterations_for, moving_pixels, moving_residual
from fourlegs_engine.fit.evaluate import TestMetrics as Metrics, evaluate_test_views, region_error
from fourlegs_engine.fit.options import preset_options
from fourlegs_engine.fit.presets import FIT_PRESETS
from fourlegs_engine.scene.bundle import load_bundle

ADAPTIVE = FitOptions(resolution_scale=1.0, first_iterations=60, iterations=8, min_iterations=3, max_iterations=20,
                      init_background=1500, background_stride=4, voxel=0.04, max_gaussians=4000)
#: the foreground's x translation per timestep: steady for three steps, then a jump the forecast misses
JERKY_X = (0.0, 0.04, 0.08, 0.40)


# ------------------------------------------------------------------------------------- the schedule
def test_moving_residual_is_the_mean_abs_error_over_the_pixels_that_changed():
    rng = np.random.default_rng(3)
    prev = [rng.random((6, 7, 3)) for _ in range(2)]
    cur = [p.copy() for p in prev]
    cur[0][1:3, 2:5] += 0.3 * rng.choice([-1, 1], size=(2, 3, 3))
    cur[1][4, 6, 1] += 0.5
    cur[1][0, 0, 2] += 0.5 * MOVING_THRESHOLD  # below the threshold: not moving
    render = [np.clip(c + rng.normal(0, 0.05, c.shape), 0, 1) for c in cur]
    as_t = lambda xs: [torch.from_numpy(x) for x in xs]  # noqa: E731
    got, count = moving_residual(as_t(render), as_t(cur), as_t(prev))
    errors = []
    for r, c, p in zip(render, cur, prev):
        moved = np.abs(c - p).max(-1) > MOVING_THRESHOLD
        errors.append(np.abs(r - c)[moved].mean(-1))
    expected = np.concatenate(errors)
    assert count == 6 + 1 == expected.size
    assert got == pytest.approx(float(expected.mean()), rel=1e-9)
    assert moving_pixels(torch.from_numpy(prev[1]), torch.from_numpy(cur[1])).sum() == 1
    # nothing moved: residual 0 over no pixels
    assert moving_residual(as_t(prev), as_t(prev), as_t(prev)) == (0.0, 0)


def test_iterations_scale_with_the_residual_against_the_earlier_median_within_floor_and_cap():
    assert iterations_for(0.2, [], base=30, floor=10, cap=90) == 30  # nothing to compare with yet
    assert iterations_for(0.0, [], base=30, floor=10, cap=90) == 10  # nothing moved
    earlier = [0.1, 0.3, 0.2]  # median 0.2
    assert iterations_for(0.2, earlier, base=30, floor=10, cap=90) == 30
    assert iterations_for(0.3, earlier, base=30, floor=10, cap=90) == 45
    assert iterations_for(0.05, earlier, base=30, floor=10, cap=90) == 10  # 7.5, raised to the floor
    assert iterations_for(1.0, earlier, base=30, floor=10, cap=90) == 90  # 150, capped
    assert iterations_for(0.25, [0.1, 0.3], base=30, floor=10, cap=90) == 38  # even count: mean of the middle two
    assert iterations_for(float("nan"), earlier, base=30, floor=10, cap=90) == 30


@settings(max_examples=200, deadline=None)
@given(st.floats(0, 10, allow_nan=False), st.lists(st.floats(0, 10, allow_nan=False), max_size=12),
       st.integers(0, 50), st.integers(0, 50), st.integers(0, 200))
def test_iterations_stay_within_floor_and_cap_and_grow_with_the_residual(residual, earlier, floor, base, extra):
    cap = max(floor, base) + extra
    n = iterations_for(residual, earlier, base=base, floor=floor, cap=cap)
    assert floor <= n <= cap and isinstance(n, int)
    assert iterations_for(residual * 2 + 0.01, earlier, base=base, floor=floor, cap=cap) >= n


def test_motion_step_scale_follows_each_centres_speed_within_its_range():
    from fourlegs_engine.fit.optimize import motion_step_scale

    prev2 = torch.zeros(5, 3, dtype=torch.float64)
    prev = torch.tensor([[0.01, 0, 0], [0.02, 0, 0], [0, 0.02, 0], [0.2, 0, 0], [0.001, 0, 0]], dtype=torch.float64)
    np.testing.assert_allclose(motion_step_scale(prev, prev2, 4.0).numpy(), [0.5, 1.0, 1.0, 4.0, 0.25])
    np.testing.assert_allclose(motion_step_scale(prev, prev2, 2.0).numpy(), [0.5, 1.0, 1.0, 2.0, 0.5])
    assert torch.equal(motion_step_scale(prev, prev2, 1.0), torch.ones(5, dtype=torch.float64))  # off
    assert torch.equal(motion_step_scale(prev2, prev2, 4.0), torch.ones(5, dtype=torch.float64))  # nothing moved
    assert motion_step_scale(prev[:0], prev2[:0], 4.0).shape == (0,)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-1e6, 1e6, allow_nan=False), min_size=3, max_size=30), st.floats(1.0, 50.0))
def test_motion_step_scale_is_finite_and_within_its_range_for_any_motion(coords, step_range):
    from fourlegs_engine.fit.optimize import motion_step_scale

    moved = torch.tensor(coords, dtype=torch.float64)[:, None].expand(-1, 3).clone()
    moved[0] = float("nan")  # a diverged centre
    scale = motion_step_scale(moved, torch.zeros_like(moved), step_range)
    assert torch.isfinite(scale).all()
    assert (scale >= 1.0 / step_range - 1e-12).all() and (scale <= step_range + 1e-12).all()


def test_bench_runs_take_the_motion_knob_and_name_an_unknown_one():
    from fourlegs_bench.fit import parse_runs

    assert parse_runs("m:lr_means_later=0.0008,motion_step_range=2") == [
        ("m", {"lr_means_later": 0.0008, "motion_step_range": 2.0})]
    with pytest.raises(InputError, match="unknown knob 'step_range'"):
        parse_runs("m:step_range=2")
    with pytest.raises(InputError, match="bad value for motion_step_range"):
        parse_runs("m:motion_step_range=fast")
    from fourlegs_engine.fit import FitOptions
    (name, knobs), = parse_runs("r:w_rigid=8,w_iso=4,knn_lambda=1000")
    assert knobs == {"weights": {**FitOptions().weights, "rigid": 8.0, "iso": 4.0}, "knn_lambda": 1000.0}
    assert FitOptions(**knobs).weights["rot"] == FitOptions().weights["rot"]
    with pytest.raises(InputError, match="bad value for w_rot"):
        parse_runs("r:w_rot=strong")


def test_motion_step_option_is_checked_and_left_out_of_the_fingerprint_when_off():
    # off, it is left out: a fit started before the knob existed (with its options then) still resumes
    assert "motion_step_range" not in FitOptions(motion_step_range=1.0).fingerprint()
    assert FitOptions(motion_step_range=4.0).fingerprint()["motion_step_range"] == 4.0
    for bad in (0.5, 0.0, 1000.0, float("nan")):
        with pytest.raises(InputError, match="motion_step_range"):
            FitOptions(motion_step_range=bad).check()


def test_part_options_are_checked_and_left_out_of_the_fingerprint_when_off():
    off = FitOptions(part_extent=0.0).fingerprint()
    assert not {"part_extent", "part_fraction", "free_part_fraction", "part_scale"} & set(off)
    assert FitOptions().fingerprint()["free_part_fraction"] == 0.25
    on = preset_options("accurate").fingerprint()
    assert on["part_extent"] == 0.4 and on["part_scale"] == 0.5 and on["free_part_fraction"] == 0.5
    for bad in ({"part_extent": -0.1}, {"part_extent": float("nan")}, {"part_extent": float("inf")},
                {"part_fraction": -1.0}, {"free_part_fraction": 5.0}, {"part_scale": 0.0}, {"part_scale": 1.5}):
        with pytest.raises(InputError, match=next(iter(bad))):
            FitOptions(**bad).check()


def test_schedule_options_are_checked_and_left_out_of_the_fingerprint_when_off():
    fixed = FitOptions(max_iterations=0).fingerprint()
    assert "max_iterations" not in fixed and "min_iterations" not in fixed
    assert FitOptions(max_iterations=90).fingerprint()["max_iterations"] == 90
    with pytest.raises(InputError, match="iterations <= max_iterations"):
        FitOptions(iterations=30, max_iterations=20).check()
    with pytest.raises(InputError, match="preset"):
        preset_options("fastest")
    accurate = preset_options("accurate", seed=3)
    assert accurate.resolution_scale == FIT_PRESETS["accurate"]["resolution_scale"] and accurate.seed == 3
    accurate.check()


# ------------------------------------------------------------------------------------- a fit with it
@pytest.fixture(scope="module")
def jerky_capture(tmp_path_factory) -> Path:
    """The synthetic capture whose foreground moves steadily, then jumps at the last timestep."""
    original = fh.rigid_motion

    def motion(t: int):
        R, _ = original(t)
        return R, np.array([JERKY_X[t], 0.0, 0.0])

    fh.rigid_motion = motion
    try:
        return fh.write_capture(tmp_path_factory.mktemp("jerky"), num_timesteps=len(JERKY_X))
    finally:
        fh.rigid_motion = original


@pytest.mark.slow
def test_later_timesteps_get_their_steps_from_the_forecast_residual(jerky_capture, tmp_path):
    events = []
    out = fit_capture(jerky_capture, tmp_path / "scene", ADAPTIVE, progress=events.append)
    effort = load_bundle(out).metadata["fit"]["later_iterations"]
    assert sorted(effort) == ["1", "2", "3"]
    r = {int(t): e["residual"] for t, e in effort.items()}
    n = {int(t): e["iterations"] for t, e in effort.items()}
    assert all(e["moving_pixels"] > 0 for e in effort.values())
    # t=1 has no earlier residual: the base count; t=3's forecast misses the jump: the largest residual
    # and more steps than the base, as the residual says
    assert n[1] == ADAPTIVE.iterations
    assert r[3] > 1.3 * max(r[1], r[2]), r
    assert n[2] == iterations_for(r[2], [r[1]], ADAPTIVE.iterations, ADAPTIVE.min_iterations, ADAPTIVE.max_iterations)
    assert n[3] == iterations_for(r[3], [r[1], r[2]], ADAPTIVE.iterations, ADAPTIVE.min_iterations,
                                  ADAPTIVE.max_iterations)
    assert max(n[1], n[2]) < n[3] <= ADAPTIVE.max_iterations
    steps = {t: max(e.index for e in events if e.kind == "iteration" and e.timestep == t) for t in (1, 2, 3)}
    assert steps == n
    json.dumps(effort, allow_nan=False)


@pytest.mark.slow
def test_a_resumed_adaptive_fit_takes_the_same_steps(jerky_capture, tmp_path):
    fh.fit_straight_and_resumed(jerky_capture, tmp_path, ADAPTIVE, kill_after=2)
    a, b = load_bundle(tmp_path / "straight"), load_bundle(tmp_path / "resumed")
    assert a.metadata["fit"]["later_iterations"] == b.metadata["fit"]["later_iterations"]
    assert np.array_equal(np.asarray(a.gaussians.means), np.asarray(b.gaussians.means))


# ------------------------------------------------------------------------------------- ball region
def _disk(h: int, w: int, cy: float, cx: float, radius: float) -> np.ndarray:
    yy, xx = np.mgrid[:h, :w]
    return (yy - cy) ** 2 + (xx - cx) ** 2 <= radius ** 2


def test_ball_region_error_covers_the_ball_in_the_truth_and_in_the_render():
    from fourlegs_bench.real_annotations import ball_mask

    h, w = 40, 60
    grey = np.full((h, w, 3), 0.45)
    orange = np.array([0.9, 0.35, 0.1])
    target, render = grey.copy(), grey.copy() + 0.02
    truth_ball, render_ball = _disk(h, w, 12, 15, 4), _disk(h, w, 25, 40, 4)
    target[truth_ball] = orange
    render[render_ball] = orange  # the render put the ball in the wrong place
    sse, pixels = region_error(render, target, ball_mask)
    region = truth_ball | render_ball
    # the colour threshold finds both disks (its hole filling may add a rim pixel, never more)
    assert region.sum() <= pixels <= ndimage.binary_dilation(region).sum()
    region = ball_mask((target * 255).round().astype(np.uint8)) | ball_mask((render * 255).round().astype(np.uint8))
    diff = render[region] - target[region]
    assert pixels == int(region.sum())
    assert sse == pytest.approx(float((diff ** 2).sum()), rel=1e-12)
    # the whole frame forgives it more than the ball's region does
    frame_mse = float(((render - target) ** 2).mean())
    assert sse / (3 * pixels) > 5 * frame_mse
    assert region_error(grey, grey + 0.01, ball_mask) == (0.0, 0)


def test_region_psnr_of_the_whole_frame_is_the_frame_psnr_and_empty_regions_give_none(tmp_path):
    capture = fh.write_capture(tmp_path / "capture", num_timesteps=2)
    opts = FitOptions(resolution_scale=1.0, first_iterations=10, iterations=2, init_background=400,
                      background_stride=4, voxel=0.05, max_gaussians=2000)
    fit_capture(capture, tmp_path / "scene", opts, progress=False)
    everything = evaluate_test_views(tmp_path / "scene", capture, resolution_scale=1.0,
                                     region=lambda im: np.ones(im.shape[:2], bool))
    np.testing.assert_allclose(np.array(everything.region_psnr(), float), everything.psnr, rtol=1e-6)
    assert everything.mean_region_psnr == pytest.approx(everything.mean_psnr, rel=1e-6)
    nothing = evaluate_test_views(tmp_path / "scene", capture, resolution_scale=1.0,
                                  region=lambda im: np.zeros(im.shape[:2], bool))
    assert nothing.mean_region_psnr is None and nothing.region_psnr_per_timestep() == [None, None]
    plain = evaluate_test_views(tmp_path / "scene", capture, resolution_scale=1.0)
    assert plain.mean_region_psnr is None and plain.region_pixels.sum() == 0


def test_bench_ball_record_pools_cameras_and_the_table_shows_it(tmp_path):
    from fourlegs_bench.fit import _pareto_plot, ball_record, markdown_table, pareto_front

    sse = np.array([[0.0, 3 * 10 * 1e-2], [3 * 20 * 1e-3, 3 * 5 * 1e-3], [0.0, 0.0]])
    pixels = np.array([[0, 10], [20, 5], [0, 0]])
    metrics = Metrics([0, 1, 2], ["0", "10"], np.full((3, 2), 25.0), np.full((3, 2), 0.8), {}, {}, sse, pixels)
    rec = ball_record(metrics, 1)
    assert rec["ball_psnr_per_timestep"] == [20.0, 30.0, None]
    assert rec["ball_psnr_mean"] == pytest.approx((20 + 30 + 30) / 3)
    assert rec["ball_psnr_first_k"] == 20.0 and rec["ball_psnr_last_k"] == 30.0
    assert rec["ball_pixels_per_timestep"] == [10, 25, 0]
    json.dumps(rec, allow_nan=False)
    record = {"run": "adaptive", "knobs": {"max_iterations": 90}, "num_gaussians": 100, "resolution": [320, 180],
              "first_timestep_wall_s": 60.0, "first_timestep_cpu_s": 50.0, "later_timestep_wall_s": 5.0,
              "later_timestep_cpu_s": 4.0, "psnr_first_timestep": 27.0, "ssim_first_timestep": 0.85,
              "psnr_mean": 26.5, "ssim_mean": 0.84, "psnr_first_k": 26.8, "psnr_last_k": 26.2, "drift_k": 1,
              "measured_fit_cpu_min": 18.25, "measured_fit_wall_min": 19.0, **rec,
              "later_iterations": {"1": 30, "2": 12, "3": 90}}
    row = markdown_table([record], 150).splitlines()[2]
    assert "| 19 (18.2) |" in row and "| 26.67, 20.00 → 30.00 | 44.0 (12–90) |" in row
    assert pareto_front([(3.0, 26.0), (1.0, 25.0), (2.0, 24.0), (4.0, 27.5)]) == [(1.0, 25.0), (3.0, 26.0),
                                                                                   (4.0, 27.5)]
    _pareto_plot([record], tmp_path / "pareto.png")
    assert (tmp_path / "pareto.png").stat().st_size > 0
    assert math.isfinite(rec["ball_psnr_mean"])


def test_bench_fit_pareto_merges_runs_of_several_files_and_refuses_other_json(tmp_path, capsys):
    from fourlegs_engine.commands.main import main

    def record(run, cpu_min, psnr, ball, a, b, measured):
        r = {"run": run, "knobs": {"iterations": 30}, "timesteps": [a, b], "psnr_mean": psnr, "ball_psnr_mean": ball,
             "psnr_first_k": psnr + 0.3, "psnr_last_k": psnr - 0.3, "first_timestep_cpu_s": 60.0,
             "later_timestep_cpu_s": 5.0, "later_iterations": {}}
        r["measured_fit_cpu_min" if measured else "extrapolated_sequence_cpu_min"] = cpu_min
        return r

    (tmp_path / "a.json").write_text(json.dumps({"records": [record("default", 17.5, 27.1, 24.0, 0, 150, True)]}))
    short = record("short", 1.5, 26.0, 21.0, 0, 12, True)  # 12 timesteps measured: not the sequence's minutes
    short["extrapolated_sequence_cpu_min"] = 14.0
    (tmp_path / "b.json").write_text(json.dumps({"records": [record("x4", 42.0, 27.7, 25.5, 0, 3, False),
                                                             record("fast", 6.0, 25.0, None, 0, 3, False), short]}))
    assert main(["bench", "fit-pareto", str(tmp_path / "a.json"), str(tmp_path / "b.json"),
                 "--out", str(tmp_path / "out")]) == 0
    table = (tmp_path / "out" / "fit_pareto.md").read_text().splitlines()
    assert [row.split(" | ")[0] for row in table[2:]] == ["| fast (0:3)", "| short (0:12)", "| default (0:150)",
                                                          "| x4 (0:3)"]
    assert "| 14.0 (extrapolated) |" in table[3]
    assert "| 17.5 (measured) | 27.10 | 24.00 | 27.40 → 26.80 |" in table[4]
    assert "| 6.0 (extrapolated) | 25.00 | – |" in table[2]
    assert (tmp_path / "out" / "fit_pareto.png").stat().st_size > 0
    (tmp_path / "bad.json").write_text(json.dumps({"runs": []}))
    assert main(["bench", "fit-pareto", str(tmp_path / "bad.json"), "--out", str(tmp_path / "out2")]) != 0
    err = capsys.readouterr().err
    assert "bad.json" in err and "records" in err


def test_cli_preset_sets_the_knobs_and_explicit_options_override_it():
    from fourlegs_engine.commands.fit import options_from_args
    from fourlegs_engine.commands.main import build_parser

    parse = lambda *extra: options_from_args(build_parser().parse_args(["fit", "ds", "-o", "out", *extra]))  # noqa: E731
    accurate = parse("--preset", "accurate", "--iterations", "60")
    assert accurate.resolution_scale == 1.0 and accurate.iterations == 60
    assert parse("--preset", "accurate", "--part-extent", "0").part_extent == 0.0
    assert accurate.first_iterations == FIT_PRESETS["accurate"]["first_iterations"]
    default = parse("--max-iterations", "0")
    assert default.resolution_scale == 0.5 and default.max_iterations == 0 and default == FitOptions(max_iterations=0)
    assert parse().motion_step_range == 1.0 and parse("--motion-step-range", "4").motion_step_range == 4.0
