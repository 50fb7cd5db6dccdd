"""Issue #30, item 8 and the silent acceptances: every numeric argument and preset field is bounded before
the work starts (the job's frames x pixels x bytes are estimated and refused with the estimate), the
numba cache falls back on a read-only install, Ctrl-C during start-up is a quiet 130, and capture image
paths stay inside the capture."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from _language_helpers import micro_bundle
from fourlegs_engine.commands.main import main
from fourlegs_engine.errors import InputError
from fourlegs_engine.highlights.timing import frames_for_duration


def _refused(capsys, argv: list[str]) -> str:
    """The one line a refused command printed (argparse errors exit 2 through SystemExit)."""
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err, err
    return err.strip().splitlines()[-1]


@pytest.fixture(scope="module")
def bundle(tmp_path_factory) -> Path:
    return micro_bundle(tmp_path_factory.mktemp("bounds") / "micro", T=2)


# ----------------------------------------------------------------- item 8: unbounded work is refused
@pytest.mark.parametrize("argv, needle", [
    (["plan", "--demo", "a ball", "-o", "{out}/p.json", "--fps", "1e9"], "--fps"),
    (["plan", "--demo", "a ball", "-o", "{out}/p.json", "--per-shot", "100000"], "--per-shot"),
    (["plan", "--demo", "a ball", "-o", "{out}/p.json", "--no-effect", "explode"], "explode"),
    (["highlight", "--demo", "a ball", "-o", "{out}/h", "--fps", "1e9"], "--fps"),
    (["highlight", "--demo", "a ball", "-o", "{out}/h", "--render-threads", "-5"], "--render-threads"),
    (["highlight", "--demo", "a ball", "-o", "{out}/h", "--encoder-batch-size", "0"], "--encoder-batch-size"),
    (["highlight", "--demo", "a ball", "-o", "{out}/h", "--encoder-batch-size", "-1"], "--encoder-batch-size"),
])
def test_cli_values_beyond_what_a_job_can_hold_are_refused_first(tmp_path, capsys, argv, needle):
    start = time.process_time()
    line = _refused(capsys, [a.replace("{out}", str(tmp_path)) for a in argv])
    assert needle in line, line
    assert time.process_time() - start < 20
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv, needle", [
    (["extract", "{scene}", "--steps", "1000000000", "--no-progress"], "steps"),
    (["extract", "{scene}", "--crop-size", "1000000000", "--no-progress"], "--crop-size"),
    (["extract", "{scene}", "--frame-scale", "1e-9", "--no-progress"], "--frame-scale"),
    (["distill", "{scene}", "--view-scale", "1e-9", "--no-progress"], "--view-scale"),
    (["distill", "{scene}", "--teacher-stride", "100000", "--no-progress"], "--teacher-stride"),
])
def test_language_stage_values_are_bounded(bundle, capsys, argv, needle):
    line = _refused(capsys, [a.replace("{scene}", str(bundle)) for a in argv])
    assert needle in line, line
    assert not (bundle / "features").exists() or needle in ("--view-scale", "--teacher-stride")


def test_fit_seed_must_not_be_negative(tmp_path, capsys):
    assert "--seed" in _refused(capsys, ["fit", str(tmp_path), "-o", str(tmp_path / "s"), "--seed", "-1"])


def test_a_preset_shot_of_an_hour_at_240_fps_is_refused_before_its_frames_exist():
    from fourlegs_engine.highlights.timing import play_frame_count
    with pytest.raises(InputError, match=r"3600 s at 240 fps needs 8\.64e\+05 frames, more than the 100000"):
        frames_for_duration(3600.0, 240)
    with pytest.raises(InputError, match="frames"):
        play_frame_count(0, 100, scene_fps=30, output_fps=240, speed=1e-4)


def test_the_job_size_is_estimated_before_rendering(tmp_path, monkeypatch):
    import shutil

    from fourlegs_engine.highlight_job import check_job_size

    plan = {"resolution": [1280, 720], "frame_start": 1, "frame_end": 240}
    check_job_size(plan, tmp_path / "highlight.mp4", "MP4")
    usage = shutil.disk_usage(tmp_path)
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage._replace(free=100 << 20))
    with pytest.raises(InputError, match=r"240 frames of 1280x720 need about 632\.8 MiB of disk.*100\.0 MiB free"):
        check_job_size(plan, tmp_path / "highlight.mp4", "MP4")
    monkeypatch.setattr("fourlegs_engine.validate.memory_bytes", lambda: 1 << 30)
    with pytest.raises(InputError, match=r"rendering one 16384x16384 frame needs about 16\.0 GiB"):
        check_job_size({"resolution": [16384, 16384], "frame_start": 1, "frame_end": 1}, tmp_path / "v.mp4", "PNG")


def test_plan_highlight_bounds_its_overrides():
    from fourlegs_engine.highlights.timing import MAX_SHOT_FRAMES

    assert frames_for_duration(MAX_SHOT_FRAMES / 24, 24) == MAX_SHOT_FRAMES
    with pytest.raises(InputError, match="frames"):
        frames_for_duration(3600, 1e9)


# ------------------------------------------------------------- silent acceptances, now refused
def test_a_bundle_version_of_true_is_refused(bundle, tmp_path):
    import shutil

    from fourlegs_engine.scene.bundle import load_bundle

    path = Path(shutil.copytree(bundle, tmp_path / "b"))
    meta = json.loads((path / "scene.json").read_text())
    meta["version"] = True
    (path / "scene.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="version"):
        load_bundle(path)


@pytest.mark.parametrize("fn", ["/etc/passwd", "C:\\\\frames\\\\a.jpg", "../outside.jpg"])
def test_capture_image_paths_outside_the_capture_are_refused(tmp_path, fn):
    from fourlegs_engine.scene.dynamic3dgs import read_camera_meta

    meta = {"w": 32, "h": 18, "k": [[[[30, 0, 16], [0, 30, 9], [0, 0, 1]]]],
            "w2c": [[[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]]], "fn": [[fn]], "cam_id": [[0]]}
    path = tmp_path / "train_meta.json"
    path.write_text(json.dumps(meta))
    with pytest.raises(InputError, match=r"fn\[0\]\[0\]"):
        read_camera_meta(path, require_files=True)


# ------------------------------------------------------------------ start-up: numba cache, Ctrl-C
def test_a_read_only_numba_cache_falls_back_to_no_cache(tmp_path):
    env = dict(os.environ, NUMBA_CACHE_DIR="/proc/fourlegs-not-writable")
    code = ("import fourlegs_engine, torch\n"
            "from fourlegs_engine.jit_cache import JIT_CACHE\n"
            "from fourlegs_engine.render import rasterize\n"
            "from fourlegs_engine.scene import Camera\n"
            "cam = Camera.look_at((0, -3, 0), (0, 0, 0), width=16, height=16, fov_y=0.8)\n"
            "out = rasterize(torch.zeros(1, 3), torch.tensor([[1., 0, 0, 0]]), torch.full((1, 3), -1.),\n"
            "                torch.tensor([3.]), cam, colors=torch.ones(1, 3))\n"
            "print(JIT_CACHE, float(out['rgb'].sum()) > 0)\n")
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split() == ["False", "True"]
    version = subprocess.run([sys.executable, "-m", "fourlegs_engine.commands.main", "--version"], env=env,
                             capture_output=True, text=True, timeout=120)
    assert version.returncode == 0 and "fourlegs" in version.stdout, version.stderr[-2000:]


def test_the_cache_moves_to_a_writable_folder_when_the_install_is_read_only(tmp_path, monkeypatch):
    from fourlegs_engine import jit_cache

    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setenv("FOURLEGS_CACHE", str(tmp_path))
    monkeypatch.setattr(jit_cache.os, "access", lambda path, mode: False)
    (tmp_path / "numba" / "0123456789abcdef").mkdir(parents=True)  # the kernels of other sources
    assert jit_cache.configure() is True
    assert os.environ["NUMBA_CACHE_DIR"] == str(tmp_path / "numba" / jit_cache.kernel_sources_digest())
    assert [p.name for p in (tmp_path / "numba").iterdir()] == [jit_cache.kernel_sources_digest()]
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    monkeypatch.setattr(jit_cache, "_writable", lambda folder: False)
    assert jit_cache.configure() is False
    monkeypatch.setattr(jit_cache, "JIT_CACHE", True)


def test_the_kernel_cache_folder_changes_with_any_numba_module(tmp_path):
    """numba checks only a kernel's own file; the cache folder is named by all numba modules' sources, so an
    edit to one that others inline (the lane kernels) compiles every kernel afresh."""
    from fourlegs_engine import jit_cache

    package = tmp_path / "pkg"
    (package / "render").mkdir(parents=True)
    (package / "render" / "lanes.py").write_text("import numba\nLANES = 16\n")
    (package / "render" / "kernels.py").write_text("from numba import njit\n")
    (package / "plain.py").write_text("VALUE = 1\n")
    before = jit_cache.kernel_sources_digest(package)
    (package / "plain.py").write_text("VALUE = 2\n")
    assert jit_cache.kernel_sources_digest(package) == before  # no numba there
    (package / "render" / "lanes.py").write_text("import numba\nLANES = 8\n")
    assert jit_cache.kernel_sources_digest(package) != before


def test_ctrl_c_while_the_commands_load_is_a_quiet_130(monkeypatch, capsys):
    from fourlegs_engine.commands import main as main_module

    def interrupted():
        raise KeyboardInterrupt

    monkeypatch.setattr(main_module, "build_parser", interrupted)
    assert main_module.main(["--version"]) == 130
    err = capsys.readouterr().err
    assert err.strip() == "fourlegs: cancelled"


@pytest.mark.skipif(os.name != "posix", reason="signals")
@pytest.mark.parametrize("delay", [0.3, 0.8, 1.5])
def test_ctrl_c_in_the_first_seconds_prints_no_traceback(tmp_path, delay):
    proc = subprocess.Popen([sys.executable, "-m", "fourlegs_engine.commands.main", "info", "--demo"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, FOURLEGS_CACHE=str(tmp_path)))
    time.sleep(delay)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert "Traceback" not in err, err
    assert proc.returncode in (0, 130, -signal.SIGINT), (proc.returncode, err)
