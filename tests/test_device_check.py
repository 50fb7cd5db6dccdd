"""The CUDA check (`scripts/device_check.sh`, `fourlegs bench device`) proven on the CPU before device time
is spent on it: the whole script at toy sizes, the time caps, the budget, the gsplat build's states, the
fit's schedule and the capture subset."""
from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from fourlegs_bench import device, device_gsplat
from fourlegs_bench.device_data import build_device_data, write_synthetic_capture
from fourlegs_bench.device_report import REPORT_FILES, STEP_TITLES
from fourlegs_bench.device_fit import calibrate_fit, choose_fit_schedule
from fourlegs_bench.device_steps import parse_pytest_output
from fourlegs_engine.errors import InputError, OutputExistsError

REPO = Path(__file__).resolve().parents[1]
BASKETBALL = REPO.parent / "shared" / "data" / "panoptic-basketball"
#: what the device tool brings back from $OUT: at most 8 files, names of letters, digits, '.', '_', '-'
VALID_NAME = re.compile(r"^[A-Za-z0-9._-]+$")
CPU_STEPS_OK = ("env", "viclip", "raster_torch", "main_job", "cuda_tests", "fit")


def _device_args(tmp_path: Path, *extra: str) -> list[str]:
    return ["--size", "toy", "--device", "cpu", "--threads", "1", "--out", str(tmp_path / "out"),
            "--work", str(tmp_path / "work"), *extra]


@pytest.fixture(scope="module")
def dry_run(tmp_path_factory) -> dict:
    """The script itself, as the device runs it, at toy sizes on the CPU (one torch thread per step)."""
    tmp = tmp_path_factory.mktemp("device_dry_run")
    out = tmp / "out"
    env = {**os.environ, "OUT": str(out), "PYTHON": sys.executable, "TMPDIR": str(tmp),
           "TORCH_EXTENSIONS_DIR": str(tmp / "torch_extensions")}
    start = time.perf_counter()
    proc = subprocess.run(["bash", str(REPO / "scripts" / "device_check.sh"), "--size", "toy", "--device", "cpu",
                           "--threads", "1"], cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    return {"proc": proc, "out": out, "seconds": time.perf_counter() - start,
            "report": json.loads((out / "device_report.json").read_text()) if (out / "device_report.json").is_file()
            else None}


def test_the_dry_run_finishes_every_step_and_returns_only_what_the_device_tool_can_bring_back(dry_run):
    proc, out, report = dry_run["proc"], dry_run["out"], dry_run["report"]
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    files = sorted(p.relative_to(out) for p in out.rglob("*"))
    assert 0 < len(files) <= 8
    assert all(len(p.parts) <= 2 and all(VALID_NAME.match(part) for part in p.parts) for p in files), files
    names = {str(p) for p in files}
    assert {"device_report.json", "device_report.md", "device_contact.png", "cuda_tests.txt",
            "device_log.txt"} <= names <= {*REPORT_FILES, "device_log.txt"}
    assert report["format"] == "fourlegs-device-report" and report["device"] == "cpu" and report["size"] == "toy"
    assert list(report["steps"]) == list(device.STEP_ORDER)
    for name in CPU_STEPS_OK:
        assert report["steps"][name]["status"] == "ok", (name, report["steps"][name])
        assert 0 < report["steps"][name]["seconds"] <= report["steps"][name]["cap_s"]
    assert report["steps"]["raster_gsplat"]["status"] == "skipped: no CUDA"
    # no CUDA here: the build says why, and nothing was put on the steps' path
    assert report["gsplat_build"]["state"] == "skipped"
    assert all(s["gsplat_at_start"] == "skipped" for s in report["steps"].values())
    log = (out / "device_log.txt").read_text()
    assert "[device] done" in log and "[device_check] exit status 0" in log


def test_the_dry_run_figures_are_measurements_that_agree_with_each_other(dry_run):
    steps = dry_run["report"]["steps"]
    env = steps["env"]
    assert env["python"] == ".".join(map(str, sys.version_info[:3])) and env["cuda_available"] is False
    assert env["packages"]["torch"] and "gsplat" in env["missing"]

    vc = steps["viclip"]
    rows = [r for r in vc["rows"] if r.get("supported")]
    assert {(r["dtype"], r["batch_size"]) for r in rows} == {("float32", 2), ("bfloat16", 2), ("bfloat16", 4),
                                                             ("float16", 2)}
    for r in rows:
        assert r["seconds_per_clip"] > 0 and r["finite"]
        assert r["clips_per_second"] == pytest.approx(1 / r["seconds_per_clip"])
        per_ct = (vc["decode_seconds_per_frame"] + vc["crop_resize_seconds_per_camera_timestep"]
                  + vc["clips_per_camera_timestep"] * r["seconds_per_clip"])
        assert r["seconds_per_camera_timestep"] == pytest.approx(per_ct)
        assert r["extrapolated_hours"]["all"] == pytest.approx(27 * 150 * per_ct / 3600)
        low = 0.999 if r["dtype"] == "float32" else 0.99
        assert low <= r["min_cosine_to_float32"] <= 1 + 1e-9
    assert any(r["dtype"] == "bfloat16" for r in vc["cpu_rows"])        # the docs' CPU row beside it

    raster = steps["raster_torch"]
    assert len(raster["rows"]) == 8 and raster["backend"] == "torch"
    for r in raster["rows"]:
        assert r["fps"] == pytest.approx(1000 / r["ms_median"]) and r["timed_runs"] >= 0

    job = steps["main_job"]
    assert job["frames"]["rendered"] == job["frames"]["planned"] > 0
    assert {"scene", "localize + plan", "render frames (cpu)"} <= set(job["stages"])
    assert "not run" in job["blender"]

    tests = steps["cuda_tests"]
    assert tests["returncode"] == 0 and tests["counts"].get("skipped", 0) >= 1
    assert "passed" not in tests["counts"] and "failed" not in tests["counts"]
    assert all(t["outcome"] == "SKIPPED" for t in tests["tests"])

    fit = steps["fit"]
    assert fit["backend"] == "torch" and fit["schedule"]["timesteps"] == fit["timesteps"][1]
    assert fit["fitted_timesteps"] == fit["timesteps"][1] and len(fit["psnr_per_timestep"]) == fit["timesteps"][1]
    # the tiny capture is fitted well enough to be recognizable, and the mean is the mean
    assert 15.0 < fit["psnr_mean"] < 60.0
    assert fit["psnr_mean"] == pytest.approx(sum(fit["psnr_per_timestep"]) / len(fit["psnr_per_timestep"]), abs=1e-3)
    assert fit["paper_psnr"] == 28.7 and fit["cpu_row"]["psnr_mean"] > 20


def test_the_dry_run_markdown_and_contact_sheet(dry_run):
    from PIL import Image

    out = dry_run["out"]
    md = (out / "device_report.md").read_text()
    assert md.startswith("## Device check dry run")
    for title in device.STEP_ORDER:
        assert f"| {STEP_TITLES[title]} |" in md
    assert "Blender was not run" in md and "28.7 dB" in md
    with Image.open(out / "device_contact.png") as im:
        assert im.width >= 300 and im.height >= 100           # the fit strip above the main job's frames
        colours = im.convert("L").getcolors(256)               # None: more than 256 grey levels
        assert colours is None or len(colours) > 50            # real images, not an empty canvas


def test_the_gpu_section_names_the_device_and_sets_1080p_beside_gsplats_published_figure(dry_run):
    """The branches only a CUDA run reaches (device name, gsplat built, 1920x1080 rows), on the dry run's report
    with those parts as a GPU run would fill them."""
    from fourlegs_bench.device_report import markdown

    report = json.loads(json.dumps(dry_run["report"]))
    report["device"] = "cuda"
    report["steps"]["env"].update(device_name="NVIDIA H100 80GB HBM3", memory_gib=79.2, capability="9.0",
                                  driver="580.1", torch_cuda="13.0")
    report["gsplat_build"] = {"state": "ok", "seconds": 151.0, "version": "1.5.3", "arch": "9.0 (the visible GPU)"}
    rows = [{"width": w, "height": h, "output": o, "mode": m, "ms_median": ms, "fps": 1000 / ms, "timed_runs": 5,
             "peak_mb": 900.0} for (w, h), ms in (((640, 360), 2.0), ((1920, 1080), 4.0))
            for o in ("rgb", "features") for m in ("forward", "backward")]
    report["steps"]["raster_gsplat"] = {"status": "ok", "seconds": 9.0, "cap_s": 45, "backend": "gsplat",
                                        "device": "cuda", "n": 300000, "channels": 128, "rows": rows,
                                        "gsplat_published_fps_1080p": 160.0}
    md = markdown(report)
    assert md.startswith("## GPU (NVIDIA H100 80GB HBM3)")
    assert "compute capability 9.0" in md and "gsplat build: **ok** in 151 s, gsplat 1.5.3" in md
    assert "RGB forward at 1920×1080: **250 FPS**, against gsplat's published 160 FPS" in md


def test_a_step_over_its_cap_is_timed_out_and_the_next_step_still_runs(tmp_path):
    start = time.perf_counter()
    code = device.main(_device_args(tmp_path, "--steps", "env,raster_torch", "--cap", "env=1"))
    report = json.loads((tmp_path / "out" / "device_report.json").read_text())
    assert code == 1                                       # a timed-out step makes the run's exit status 1
    assert report["steps"]["env"]["status"] == "timed out after 1 s (its cap)"
    assert report["steps"]["env"]["seconds"] < 10          # killed at its cap, not when it finished
    assert report["steps"]["raster_torch"]["status"] == "ok" and len(report["steps"]["raster_torch"]["rows"]) == 8
    assert time.perf_counter() - start < 120
    assert "timed out after 1 s" in (tmp_path / "out" / "device_report.md").read_text()


def test_a_running_step_publishes_what_it_has_measured_so_far(tmp_path, monkeypatch):
    monkeypatch.setattr(device, "PROGRESS_EVERY_S", 0.02)  # the fused kernels finish the toy step in well under a second
    partials = []
    config = {"size": "toy", "device": "cpu", "data": None, "work": str(tmp_path),
              "plan": device.PLANS["toy"]["raster_torch"]}
    result = device.run_step("raster_torch", config, tmp_path, cap=120, env={**os.environ, "OMP_NUM_THREADS": "1"},
                             progress=partials.append)
    assert result["status"] == "ok" and len(result["rows"]) == 8
    assert partials and all(p["status"].startswith("running (") for p in partials)
    assert [p["seconds"] for p in partials] == sorted(p["seconds"] for p in partials)
    assert any(0 < len(p.get("rows", [])) < 8 for p in partials)     # rows arrive while the step runs


def test_steps_past_the_budget_are_skipped_and_said_so(tmp_path):
    code = device.main(_device_args(tmp_path, "--steps", "env,fit", "--budget", "3"))
    report = json.loads((tmp_path / "out" / "device_report.json").read_text())
    assert code == 0
    for name in ("env", "fit"):
        assert report["steps"][name]["status"].startswith("skipped: the run's 3 s budget is spent")


def test_bad_arguments_are_one_clear_error(tmp_path, capsys):
    assert device.main(_device_args(tmp_path, "--steps", "env,warp")) == 2
    assert "warp" in capsys.readouterr().err
    assert device.main(_device_args(tmp_path, "--cap", "fit=soon")) == 2
    assert "STEP=SECONDS" in capsys.readouterr().err
    assert device.main(_device_args(tmp_path, "--set", "fit.iterationz=3")) == 2
    assert "iterationz" in capsys.readouterr().err
    assert device.main(_device_args(tmp_path, "--data", str(tmp_path), "--steps", "fit")) == 2
    assert "train_meta.json" in capsys.readouterr().err


def test_plan_overrides_take_json_values():
    plans = device.apply_overrides(device.PLANS["full"], ["fit.first_iterations=3000",
                                                         'viclip.batches={"bfloat16": [512]}', "main_job.preset=x"])
    assert plans["fit"]["first_iterations"] == 3000 and plans["viclip"]["batches"] == {"bfloat16": [512]}
    assert plans["main_job"]["preset"] == "x" and device.PLANS["full"]["fit"]["first_iterations"] == 2000


# ------------------------------------------------------------------------------------------ gsplat build
def test_the_gsplat_build_without_a_carried_wheel_is_skipped_with_its_reason(tmp_path):
    status = device_gsplat.build(tmp_path / "site", tmp_path / "status.json", tmp_path / "log.txt", cap=30)
    assert status["state"] == "skipped" and "no gsplat package" in status["reason"]
    assert json.loads((tmp_path / "status.json").read_text()) == status


def test_a_gsplat_build_over_its_cap_is_killed_and_reported(tmp_path, monkeypatch):
    """A compiler that never finishes (a stand-in module first on the build's path) is stopped at the cap."""
    monkeypatch.chdir(tmp_path)  # `python -m` puts the working directory first: not the repository's package
    site = tmp_path / "site"
    (site / "gsplat").mkdir(parents=True)
    (site / "gsplat" / "__init__.py").write_text("")
    (site / "fourlegs_bench").mkdir()
    (site / "fourlegs_bench" / "__init__.py").write_text("")
    (site / "fourlegs_bench" / "device_gsplat.py").write_text("import time\ntime.sleep(120)\n")
    start = time.perf_counter()
    status = device_gsplat.build(site, tmp_path / "status.json", tmp_path / "log.txt", cap=2)
    assert time.perf_counter() - start < 20
    assert status["state"] == "timed out" and "2 s cap" in status["reason"] and status["seconds"] >= 2


def test_a_gsplat_build_on_a_machine_without_cuda_is_skipped(tmp_path):
    site = tmp_path / "site"
    (site / "gsplat").mkdir(parents=True)
    (site / "gsplat" / "__init__.py").write_text("raise RuntimeError('must not be imported without CUDA')\n")
    status = device_gsplat.build(site, tmp_path / "status.json", tmp_path / "log.txt", cap=120)
    assert status["state"] == "skipped" and "CUDA" in status["reason"]


# ------------------------------------------------------------------------------------------- fit schedule
TIMING = st.fixed_dictionaries({
    "setup_s": st.floats(0.0, 30.0), "first_iteration_s": st.floats(1e-4, 2.0), "later_setup_s": st.floats(0.0, 3.0),
    "later_iteration_s": st.floats(1e-4, 2.0), "finish_s": st.floats(0.0, 5.0)})


@given(timing=TIMING, budget=st.floats(1.0, 400.0), timesteps=st.integers(1, 30))
def test_the_fit_schedule_fits_the_budget_or_is_the_smallest_there_is(timing, budget, timesteps):
    plan = device.PLANS["full"]["fit"]
    s = choose_fit_schedule(plan, timing, budget, timesteps)
    assert 1 <= s["timesteps"] <= timesteps
    assert 1 <= s["first_iterations"] <= plan["first_iterations"]
    assert plan["min_iterations"] <= s["iterations"] <= plan["iterations"]
    k = 1.25
    cost = k * (timing["setup_s"] + timing["finish_s"] + s["first_iterations"] * timing["first_iteration_s"]
                + (s["timesteps"] - 1) * (timing["later_setup_s"] + s["iterations"] * timing["later_iteration_s"]))
    assert s["estimated_s"] == pytest.approx(cost, abs=0.06)
    if cost > budget + 1e-6:     # over only when not even one iteration of the first timestep fits
        assert s["timesteps"] == 1 and s["first_iterations"] == 1


def test_a_plan_that_fits_is_run_as_planned():
    plan = device.PLANS["full"]["fit"]
    timing = {"setup_s": 5.0, "first_iteration_s": 0.01, "later_setup_s": 0.3, "later_iteration_s": 0.01,
              "finish_s": 1.0}
    s = choose_fit_schedule(plan, timing, budget_s=300.0, timesteps=25)
    assert (s["first_iterations"], s["iterations"], s["timesteps"]) == (2000, 150, 25)
    slow = dict(timing, first_iteration_s=0.1, later_iteration_s=0.1)
    s = choose_fit_schedule(plan, slow, budget_s=200.0, timesteps=25)     # fewer iterations of every timestep
    assert s["timesteps"] == 25 and 300 <= s["first_iterations"] < 2000 and 30 <= s["iterations"] < 150
    assert s["estimated_s"] <= 200.0
    s = choose_fit_schedule(plan, slow, budget_s=120.0, timesteps=25)     # at the minimums: fewer timesteps
    assert (s["first_iterations"], s["iterations"]) == (300, 30) and s["timesteps"] < 25 and s["estimated_s"] <= 120


def test_a_calibration_over_its_time_is_stopped_and_its_missing_parts_estimated(tmp_path):
    from fourlegs_engine.fit import Capture, FitOptions
    from fourlegs_engine.threads import torch_threads

    capture = Capture(write_synthetic_capture(tmp_path / "capture", timesteps=2))
    opts = FitOptions(resolution_scale=1.0, max_gaussians=3000, init_background=400, init_foreground=1000,
                      voxel=0.05, device="cpu")
    with torch_threads(1):
        timing = calibrate_fit(capture, opts, tmp_path / "calibration", (50, 10), limit_s=0.0)
    assert timing["complete"] is False and timing["setup_s"] > 0 and timing["first_iteration_s"] > 0
    assert timing["later_iteration_s"] == timing["first_iteration_s"]       # no later timestep was reached
    assert timing["later_setup_s"] == pytest.approx(0.2 * timing["setup_s"])
    # stopped at its third iteration of 50
    assert timing["seconds"] < timing["setup_s"] + 10 * timing["first_iteration_s"]


# ------------------------------------------------------------------------------------------- pytest output
def test_pytest_outcomes_are_read_from_a_real_run(tmp_path):
    (tmp_path / "test_x.py").write_text(
        "import pytest\n\ndef test_ok():\n    pass\n\ndef test_bad():\n    assert 1 == 2, 'differs'\n\n"
        "@pytest.mark.skip(reason='not here')\ndef test_skip():\n    pass\n")
    run = subprocess.run([sys.executable, "-m", "pytest", "-rA", "-p", "no:cacheprovider", "-q", str(tmp_path)],
                         capture_output=True, text=True, cwd=tmp_path, timeout=120)
    parsed = parse_pytest_output(run.stdout)
    assert parsed["counts"] == {"passed": 1, "failed": 1, "skipped": 1}
    outcomes = {t["test"].split("::")[-1].split(":")[0]: t["outcome"] for t in parsed["tests"]}
    assert outcomes["test_ok"] == "PASSED" and outcomes["test_bad"] == "FAILED"
    assert any(t["outcome"] == "SKIPPED" and "not here" in t["detail"] for t in parsed["tests"])


# ------------------------------------------------------------------------------------------- capture subset
@pytest.mark.skipif(not BASKETBALL.is_dir(), reason=f"the shared Panoptic capture is not at {BASKETBALL}")
def test_the_capture_subset_holds_every_camera_of_the_first_timesteps(tmp_path):
    from fourlegs_engine.fit import Capture

    summary = build_device_data(BASKETBALL, tmp_path / "dd", 2)
    cap, full = Capture(tmp_path / "dd"), Capture(BASKETBALL)
    assert cap.num_timesteps == 2 and (cap.width, cap.height) == (640, 360)
    assert cap.train.cam_ids[1] == full.train.cam_ids[1] and cap.test.cam_ids[1] == ["0", "10", "15", "30"]
    assert summary["files"] == 2 * (31 + 27) and summary["cameras"] == 31
    assert (cap.image_path("test", 1, 3).read_bytes() == full.image_path("test", 1, 3).read_bytes())
    assert cap.train.cameras[1][5].K.tolist() == full.train.cameras[1][5].K.tolist()
    cap.check_frames("train", range(2), range(27), masks=True)
    with pytest.raises(OutputExistsError):
        build_device_data(BASKETBALL, tmp_path / "dd", 2)
    with pytest.raises(InputError, match="151 were asked for"):
        build_device_data(BASKETBALL, tmp_path / "dd2", 151)
    assert not (tmp_path / "dd2").exists()


def test_a_capture_without_metadata_is_refused(tmp_path):
    with pytest.raises(InputError, match="train_meta.json"):
        build_device_data(tmp_path, tmp_path / "dd", 2)
    assert math.isfinite(device.DEFAULT_BUDGET_S["full"]) and device.DEFAULT_BUDGET_S["full"] <= 390
