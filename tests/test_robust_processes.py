"""Issue #30, items 5-7: one writer per scene and output folder, a child that ends with its parent, and no
temporary file of a killed run surviving the next run."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from _language_helpers import micro_bundle, one_thread  # noqa: F401 (one_thread: autouse fixture)
from fourlegs_engine.commands.main import main
from fourlegs_engine.runlock import (LockedError, RunLock, lock_file_of, release_all, remove_stale_parts,
                                     run_lock)

POSIX = os.name == "posix"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie (exited, not yet reaped by its parent) is not running
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return True


def _wait_gone(pid: int, seconds: float = 20.0) -> bool:
    deadline = time.time() + seconds
    while time.time() < deadline:
        if not _alive(pid):
            return True
        time.sleep(0.05)
    return False


def _wait_for(path: Path, seconds: float = 60.0) -> str:
    deadline = time.time() + seconds
    while time.time() < deadline:
        if path.is_file() and path.read_text().strip():
            return path.read_text().strip()
        time.sleep(0.05)
    raise AssertionError(f"{path} never appeared")


def _holder(target: Path, tmp_path: Path, shared: bool = False) -> subprocess.Popen:
    """Another process holding ``target``'s lock until killed."""
    ready = tmp_path / f"ready-{os.getpid()}-{time.time_ns()}"
    code = textwrap.dedent(f"""
        import sys, time
        from fourlegs_engine.runlock import hold_run_lock
        hold_run_lock({str(target)!r}, shared={shared})
        open({str(ready)!r}, "w").write("1")
        time.sleep(120)
    """)
    proc = subprocess.Popen([sys.executable, "-c", code, "fourlegs", "language", "SCENE"])
    _wait_for(ready)
    return proc


def _stop(proc: subprocess.Popen) -> None:
    proc.kill()
    proc.wait()


# ----------------------------------------------------------------------------- item 6: the run lock
@pytest.fixture(scope="module")
def bundle(tmp_path_factory) -> Path:
    return micro_bundle(tmp_path_factory.mktemp("procs") / "micro", T=2)


@pytest.mark.parametrize("argv", [["extract", "--no-progress"], ["train-ae", "--epochs", "1"],
                                  ["distill", "--no-progress"], ["language", "--no-progress"]])
def test_a_second_writer_of_a_scene_is_one_line_naming_the_holder(bundle, tmp_path, capsys, argv):
    holder = _holder(bundle, tmp_path)
    try:
        assert main([argv[0], str(bundle), *argv[1:]]) == 2
        err = capsys.readouterr().err
        assert "Traceback" not in err
        line = err.strip().splitlines()[-1]
        assert f"pid {holder.pid}" in line and "in use by another fourlegs run" in line and str(bundle) in line
        assert "fourlegs language SCENE" in line or "language" in line
    finally:
        _stop(holder)
    assert not (bundle / "language" / "steps").exists()


def test_a_check_reads_while_another_run_writes(bundle, tmp_path, capsys):
    holder = _holder(bundle, tmp_path)
    try:
        main(["extract", str(bundle), "--check"])
        assert "in use" not in capsys.readouterr().err
    finally:
        _stop(holder)


def test_shard_workers_share_the_lock_and_exclude_a_whole_run(tmp_path):
    target = tmp_path / "scene"
    holder = _holder(target, tmp_path, shared=True)
    try:
        with run_lock(target, shared=True):  # another shard worker
            pass
        with pytest.raises(LockedError):
            RunLock(target).acquire()
    finally:
        _stop(holder)
    with run_lock(target):  # the holder is gone (killed): the kernel released its lock
        pass


def test_the_lock_is_reentrant_in_one_process_and_released_after_a_command(tmp_path):
    target = tmp_path / "out"
    with run_lock(target), run_lock(target):
        assert f"pid {os.getpid()}" in lock_file_of(target).read_text()
    assert not lock_file_of(target).exists()  # removed by its holder: nothing is left beside the folder
    release_all()


def test_two_fits_into_one_scene_are_refused_before_any_work(tmp_path, capsys):
    target = tmp_path / "fitted"
    holder = _holder(target, tmp_path)
    try:
        assert main(["fit", str(tmp_path / "no-such-capture"), "-o", str(target)]) == 2
        assert f"pid {holder.pid}" in capsys.readouterr().err
    finally:
        _stop(holder)
    assert not target.exists()


def test_the_headless_job_refuses_an_output_folder_in_use(tmp_path, capsys):
    from fourlegs_addon import headless

    out = tmp_path / "out"
    holder = _holder(out, tmp_path)
    try:
        assert headless.main(["--demo", "a ball", "-o", str(out)]) == 2
        assert f"pid {holder.pid}" in capsys.readouterr().err
    finally:
        _stop(holder)
    assert not out.exists()


# ---------------------------------------------------------------- item 7: stale temporary files
def test_temporary_files_of_a_killed_run_are_removed_by_the_next(tmp_path):
    out = tmp_path / "out"
    stale = [out / ".plan.k2j3.part.json", out / ".highlight.x1y2.part.mp4",
             out / ".frames-abc" / ".frame_0003.part.png",
             out / ".highlight.mp4.a8.part" / "frame_0001.png", out / "deep" / "language" / ".latents.q.part.npy",
             out / ".latents.zz.old" / "old"]
    kept = [out / "plan.json", out / ".frames-abc" / "frame_0002.png", out / "notes.part", out / ".hidden"]
    for path in stale + kept:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"x")
    with run_lock(out):
        pass
    assert [p for p in stale if p.exists()] == []
    assert all(p.exists() for p in kept)


def test_a_shared_lock_leaves_other_workers_temporaries(tmp_path):
    part = tmp_path / "scene" / "language" / "steps" / ".t000001.x.part.npy"
    part.parent.mkdir(parents=True)
    part.write_bytes(b"x")
    with run_lock(tmp_path / "scene", shared=True):
        pass
    assert part.exists()
    assert remove_stale_parts(tmp_path / "scene") == [part]


def test_a_killed_distill_leaves_no_part_file_after_the_rerun(bundle, tmp_path):
    import shutil

    path = tmp_path / "b"
    shutil.copytree(bundle, path)
    assert main(["extract", str(path), "--no-progress"]) == 0
    assert main(["train-ae", str(path), "--epochs", "1", "--samples", "512", "--ae-batch-size", "128"]) == 0
    planted = path / "language" / "steps" / ".t000001.abcd.part.npy"
    planted.parent.mkdir(parents=True, exist_ok=True)
    planted.write_bytes(b"\x93NUMPY half")  # what a SIGKILL during a write leaves
    assert main(["distill", str(path), "--no-progress"]) == 0
    leftovers = [p for p in path.rglob("*") if ".part" in p.name]
    assert leftovers == []


# ------------------------------------------------------------- item 5: the child ends with its parent
CHILD = """
import os, sys, time
from fourlegs_engine import lifetime
if {watchdog_only}:
    lifetime._set_parent_death_signal = lambda: None
lifetime.die_with_parent()
open(sys.argv[1], "w").write(str(os.getpid()))
time.sleep(120)
"""


@pytest.mark.skipif(not POSIX, reason="signals")
@pytest.mark.parametrize("watchdog_only", [False, True])
@pytest.mark.parametrize("how", [signal.SIGKILL, signal.SIGTERM])
def test_the_child_ends_when_its_parent_is_killed(tmp_path, watchdog_only, how):
    """``fourlegs highlight``'s parent runs the child through ``run_child``; killing the parent ends both."""
    pid_file = tmp_path / "child.pid"
    child = CHILD.format(watchdog_only=watchdog_only)
    parent = subprocess.Popen([sys.executable, "-c", textwrap.dedent(f"""
        import sys
        from fourlegs_addon.commands import run_child
        sys.exit(run_child([sys.executable, "-c", {child!r}, {str(pid_file)!r}]))
    """)], stderr=subprocess.PIPE, text=True)
    child_pid = int(_wait_for(pid_file))
    parent.send_signal(how)
    code = parent.wait(timeout=60)
    assert _wait_gone(child_pid), "the child outlived its parent"
    if how == signal.SIGTERM:
        assert code == 143
        err = parent.stderr.read()
        assert "Traceback" not in err and "stopped" in err, err


def test_without_a_parent_to_watch_nothing_is_watched(monkeypatch):
    from fourlegs_engine import lifetime

    monkeypatch.delenv(lifetime.PARENT_PID_ENV, raising=False)
    assert lifetime.die_with_parent() is False
    assert lifetime.parent_alive(os.getppid())


# ------------------------------------------- items 5-7 end to end: `fourlegs highlight` and its Blender child
HIGHLIGHT = ["ball flying in the air", "--preset", "bullet_time_only", "--resolution", "64x36", "--fps", "120"]


@pytest.fixture(scope="module")
def field_scene(tmp_path_factory) -> Path:
    pytest.importorskip("bpy")
    path = micro_bundle(tmp_path_factory.mktemp("hl") / "micro", T=4)
    assert main(["language", str(path), "--no-progress", "--epochs", "2", "--samples", "2048",
                 "--ae-batch-size", "256"]) == 0
    return path


def _highlight(scene: Path, out: Path, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "fourlegs_engine.commands.main", "highlight", str(scene),
                             *HIGHLIGHT, "-o", str(out)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True, **kw)


def _child_pid(out: Path, parent: subprocess.Popen, seconds: float = 120) -> int:
    """The Blender child's pid, from the output folder's lock (the child holds it)."""
    deadline = time.time() + seconds
    lock = lock_file_of(out)
    while time.time() < deadline:
        text = lock.read_text() if lock.is_file() else ""
        if text.startswith("pid ") and int(text.split()[1].rstrip(":")) != parent.pid:
            return int(text.split()[1].rstrip(":"))
        assert parent.poll() is None, parent.stderr.read()
        time.sleep(0.05)
    raise AssertionError("the child never took the output lock")


@pytest.mark.skipif(not POSIX, reason="signals")
@pytest.mark.parametrize("how", [signal.SIGKILL, signal.SIGTERM])
def test_killing_highlight_ends_its_blender_child_and_the_rerun_finishes(field_scene, tmp_path, how):
    out = tmp_path / "out"
    parent = _highlight(field_scene, out)
    child = _child_pid(out, parent)
    deadline = time.time() + 120  # kill it while it renders: some frames done, some not
    while time.time() < deadline and not any(out.glob(".frames-*/frame_*.png")):
        time.sleep(0.02)
    parent.send_signal(how)
    parent.wait(timeout=60)
    assert _wait_gone(child), "the Blender child outlived fourlegs highlight"
    assert not (out / "report.json").exists()
    rerun = _highlight(field_scene, out)
    assert rerun.wait(timeout=600) == 0, rerun.stderr.read()
    assert (out / "highlight.mp4").stat().st_size > 0 and (out / "report.json").is_file()
    assert [p for p in out.rglob("*") if ".part" in p.name or p.name.startswith(".frames-")] == []


@pytest.mark.skipif(not POSIX, reason="signals")
def test_two_highlights_into_one_folder_one_refused_in_one_line(field_scene, tmp_path):
    out = tmp_path / "out"
    first = _highlight(field_scene, out)
    child = _child_pid(out, first)
    second = _highlight(field_scene, out)
    assert second.wait(timeout=300) == 2
    err = second.stderr.read()
    assert "Traceback" not in err and f"in use by another fourlegs run (pid {child}" in err, err
    assert first.wait(timeout=600) == 0, first.stderr.read()
    assert (out / "highlight.mp4").stat().st_size > 0


# ------------------------------------------------- item 8: a native crash of the child is one line
CRASHING_CHILD = """
import os, signal, sys
from fourlegs_engine.highlight_job import StageTimer
with StageTimer()("render"):
    if sys.argv[1] == "signal":
        os.kill(os.getpid(), signal.SIGSEGV)
    os._exit(int(sys.argv[1]))
"""


@pytest.mark.skipif(not POSIX, reason="signals")
@pytest.mark.parametrize("how, status", [("signal", "SIGSEGV"), ("245", "SIGSEGV"), ("250", "SIGABRT")])
def test_a_native_crash_of_the_child_is_one_line_with_its_stage(tmp_path, capsys, how, status):
    from fourlegs_addon.commands import run_child

    code = run_child([sys.executable, "-c", CRASHING_CHILD, how], stage_file=tmp_path / "stage.txt")
    assert code == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("fourlegs: error: the Blender child crashed"), err
    assert status in err[0] and "'render' stage" in err[0] and "memory" in err[0]


def test_an_ordinary_failure_of_the_child_keeps_its_own_line_and_code(tmp_path, capsys):
    from fourlegs_addon.commands import run_child

    assert run_child([sys.executable, "-c", "import sys; sys.exit(2)"], stage_file=tmp_path / "s.txt") == 2
    assert capsys.readouterr().err == ""


def test_a_killed_fit_leaves_nothing_stale_after_the_next_run_takes_the_lock(tmp_path):
    out = tmp_path / "scene"
    stale = [tmp_path / ".scene.ab12.part" / "means.npy", tmp_path / ".scene.fit" / ".t000003.x9.part.npz"]
    kept = [tmp_path / ".scene.fit" / "t000002.npz", tmp_path / ".other.ab12.part" / "x"]
    for path in stale + kept:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"x")
    with run_lock(out):
        pass
    assert not (tmp_path / ".scene.ab12.part").exists() and not stale[1].exists()
    assert all(p.exists() for p in kept)


def test_contending_writers_never_hold_the_lock_together(tmp_path):
    """The holder removes the lock file on release; a writer that locked the removed file retries."""
    target, marker = tmp_path / "scene", tmp_path / "inside"
    code = textwrap.dedent(f"""
        import os, sys, time
        from fourlegs_engine.runlock import LockedError, RunLock
        held = 0
        while held < 15:
            lock = RunLock({str(target)!r}, clean=False)
            try:
                lock.acquire()
            except LockedError:
                time.sleep(0.001)
                continue
            try:
                fd = os.open({str(marker)!r}, os.O_CREAT | os.O_EXCL)  # fails if another holder is inside
                os.close(fd)
                time.sleep(0.002)
                os.unlink({str(marker)!r})
            finally:
                lock.release()
            held += 1
    """)
    procs = [subprocess.Popen([sys.executable, "-c", code], stderr=subprocess.PIPE, text=True) for _ in range(4)]
    for proc in procs:
        _, err = proc.communicate(timeout=300)
        assert proc.returncode == 0, err
    assert not lock_file_of(target).exists()
