"""Issue #30, item 4: readers (``query``, ``plan``, ``highlight``) hold the scene's run lock shared.

Several readers run together; a reader is refused (at once, no waiting) while a writer holds the lock,
and a writer while a reader does, each in one line naming the holder. The other process of each test is a
real one holding the lock as the named command would; the command under test runs in this process.
Item 5: the Windows byte-range emulation of shared locks, on a stand-in ``msvcrt``.
"""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time
import types
from pathlib import Path

import pytest

from _language_helpers import micro_bundle, one_thread  # noqa: F401 (one_thread: autouse fixture)
from fourlegs_engine import runlock
from fourlegs_engine.commands.main import main
from fourlegs_engine.runlock import LockedError, lock_file_of, release_all, run_lock


def _holder(target: Path, tmp_path: Path, *, shared: bool, argv: list[str]) -> subprocess.Popen:
    """Another process holding ``target``'s lock (as ``argv`` would) until killed."""
    ready = tmp_path / f"ready-{time.time_ns()}"
    code = textwrap.dedent(f"""
        import time
        from fourlegs_engine.runlock import hold_run_lock
        hold_run_lock({str(target)!r}, shared={shared})
        open({str(ready)!r}, "w").write("1")
        time.sleep(120)
    """)
    proc = subprocess.Popen([sys.executable, "-c", code, *argv])
    deadline = time.time() + 60
    while not ready.is_file():
        assert proc.poll() is None and time.time() < deadline, "the holder did not start"
        time.sleep(0.02)
    return proc


def _stop(*procs: subprocess.Popen) -> None:
    for proc in procs:
        proc.kill()
        proc.wait()


def _last_line(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    return err.strip().splitlines()[-1] if err.strip() else ""


@pytest.fixture(scope="module")
def field(tmp_path_factory) -> Path:
    path = micro_bundle(tmp_path_factory.mktemp("readers") / "micro", T=2)
    assert main(["language", str(path), "--no-progress", "--epochs", "1", "--samples", "1024",
                 "--ae-batch-size", "256"]) == 0
    return path


def _field_files(path: Path) -> dict[str, bytes]:
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted((path / "language").glob("*")) if p.is_file()}


def test_readers_run_together_and_a_writer_is_refused_naming_them(field, tmp_path, capsys):
    other = _holder(field, tmp_path, shared=True, argv=["fourlegs", "query", "SCENE", "a ball"])
    third = _holder(field, tmp_path, shared=True, argv=["fourlegs", "plan", "SCENE", "a ball"])
    try:
        assert main(["query", str(field), "person jumping", "--no-spatial"]) == 0, capsys.readouterr().err
        assert main(["plan", str(field), "person jumping", "-o", str(tmp_path / "plan.json"), "--effects",
                     "play"]) == 0, capsys.readouterr().err
        kept = _field_files(field)
        assert main(["distill", str(field), "--overwrite", "--no-progress"]) == 2
        line = _last_line(capsys)
        assert "in use by another fourlegs run" in line and str(field) in line
        assert f"pid {other.pid}: -c fourlegs query SCENE a ball; pid {third.pid}: -c fourlegs plan" in line, line
        assert f"pid {os.getpid()}" not in line  # this process read the scene before, but it is the one refused
        assert _field_files(field) == kept
    finally:
        _stop(other, third)
    with run_lock(field):  # the readers are gone (killed): a writer gets the scene
        pass
    assert not lock_file_of(field).exists()


@pytest.mark.parametrize("reader", ["query", "plan"])
def test_a_reader_is_refused_while_a_writer_holds_the_scene(field, tmp_path, capsys, reader):
    writer = _holder(field, tmp_path, shared=False, argv=["fourlegs", "distill", "SCENE"])
    try:
        argv = {"query": ["query", str(field), "person jumping", "--no-spatial"],
                "plan": ["plan", str(field), "person jumping", "-o", str(tmp_path / "plan.json")]}[reader]
        assert main(argv) == 2
        line = _last_line(capsys)
        assert f"in use by another fourlegs run (pid {writer.pid}: -c fourlegs distill SCENE)" in line, line
        assert not (tmp_path / "plan.json").exists()
    finally:
        _stop(writer)


def test_the_highlight_job_reads_the_scene_under_a_shared_lock(field, tmp_path):
    """``fourlegs highlight``'s child plans the job (prepare_highlight_job) holding the scene's lock shared."""
    from fourlegs_engine.highlight_job import HighlightJobOptions, StageTimer, prepare_highlight_job

    options = HighlightJobOptions(query="person jumping", output=tmp_path / "out", scene=field,
                                  preset="bullet_time_only", resolution=(64, 36), fps=12)
    writer = _holder(field, tmp_path, shared=False, argv=["fourlegs", "train-ae", "SCENE"])
    try:
        with pytest.raises(LockedError, match=f"pid {writer.pid}: -c fourlegs train-ae SCENE"):
            prepare_highlight_job(options, StageTimer())
    finally:
        _stop(writer)
    reader = _holder(field, tmp_path, shared=True, argv=["fourlegs", "query", "SCENE", "a ball"])
    try:
        job = prepare_highlight_job(options, StageTimer())
        with pytest.raises(LockedError):
            _probe(field, tmp_path, shared=False)  # no writer while the job reads (the render comes next)
        job.release()
    finally:
        _stop(reader)
    assert _probe(field, tmp_path, shared=False) == 0


def test_prepare_holding_its_scene_leaves_the_panels_query_working(field, tmp_path):
    """The add-on's Prepare Language Field holds its scene's lock between steps; the panel's query (the API's
    open_query_engine, no lock) still answers in the same process, and a command-line reader of the prepared
    scene in another process is refused with Blender named."""
    from fourlegs_engine import api

    prepared = api.open_scene(micro_bundle(tmp_path / "prepared", T=2))
    steps = api.language_field_steps(prepared)
    assert next(steps).stage == "extract features"
    try:
        engine = api.open_query_engine(api.open_scene(field))
        assert engine.localize("person jumping").temporal is not None
        with pytest.raises(LockedError, match=f"pid {os.getpid()}"):
            _probe(prepared.root, tmp_path, shared=True)
    finally:
        steps.close()
    assert _probe(prepared.root, tmp_path, shared=True) == 0


def test_a_reader_that_must_build_the_field_is_refused_while_others_read(tmp_path, capsys):
    scene = micro_bundle(tmp_path / "nofield", T=2)
    other = _holder(scene, tmp_path, shared=True, argv=["fourlegs", "query", "SCENE", "a ball"])
    try:
        assert main(["plan", str(scene), "person jumping", "-o", str(tmp_path / "plan.json")]) == 2
        line = _last_line(capsys)
        assert f"in use by another fourlegs run (pid {other.pid}: -c fourlegs query SCENE a ball)" in line, line
        assert not (scene / "features").exists() and not (tmp_path / "plan.json").exists()
        with run_lock(scene, shared=True):  # this process still reads alongside the other reader
            pass
    finally:
        _stop(other)
    release_all()


def test_one_process_reads_then_writes_then_reads_again(tmp_path):
    target = tmp_path / "scene"
    with run_lock(target, shared=True):
        with run_lock(target):  # exclusive inside: no other process may even read
            with pytest.raises(LockedError):
                _probe(target, tmp_path, shared=True)
        assert _probe(target, tmp_path, shared=True) == 0  # shared again: other readers are let in
        with pytest.raises(LockedError):
            _probe(target, tmp_path, shared=False)
    assert _probe(target, tmp_path, shared=False) == 0


def test_a_scene_reached_through_a_link_shares_the_lock_of_its_real_path(tmp_path):
    real = tmp_path / "scene"
    real.mkdir()
    (tmp_path / "link").symlink_to(real, target_is_directory=True)
    assert lock_file_of(tmp_path / "link") == lock_file_of(real)
    with run_lock(tmp_path / "link"):
        with pytest.raises(LockedError):
            _probe(real, tmp_path, shared=True)


def _probe(target: Path, tmp_path: Path, *, shared: bool) -> int:
    """Try ``target``'s lock from another process; LockedError with its message if refused."""
    code = textwrap.dedent(f"""
        import sys
        from fourlegs_engine.runlock import LockedError, RunLock
        try:
            RunLock({str(target)!r}, shared={shared}).acquire()
        except LockedError as exc:
            print(exc, file=sys.stderr)
            sys.exit(3)
    """)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    if done.returncode == 3:
        raise LockedError(target, done.stderr.strip())
    return done.returncode


# ------------------------------------------------------------------------ item 5: Windows, emulated
class _FakeMsvcrt(types.ModuleType):
    """``msvcrt.locking`` over one table of byte ranges shared by every "process" (file handle), refusing
    an overlapping range as Windows' LockFile does (its own ranges included)."""
    LK_NBLCK, LK_UNLCK = 2, 0

    def __init__(self):
        super().__init__("msvcrt")
        self.ranges: dict[int, list[tuple[int, int]]] = {}
        self.positions: dict[int, object] = {}

    def locking(self, fd: int, mode: int, nbytes: int) -> None:
        start = os.lseek(fd, 0, os.SEEK_CUR)
        mine = (start, start + nbytes)
        if mode == self.LK_UNLCK:
            self.ranges[fd].remove(mine)
            return
        for ranges in self.ranges.values():
            if any(a < mine[1] and mine[0] < b for a, b in ranges):
                raise PermissionError(13, "Permission denied")
        self.ranges.setdefault(fd, []).append(mine)


def test_windows_readers_share_and_writers_exclude(tmp_path, monkeypatch):
    fake = _FakeMsvcrt()
    monkeypatch.setitem(sys.modules, "msvcrt", fake)
    handles = [open(tmp_path / "lock", "a+", encoding="utf-8") for _ in range(4)]
    reader1, reader2, writer, late = handles
    monkeypatch.setattr(runlock.os, "getpid", lambda: 1000)
    assert runlock._try_lock_windows(reader1, shared=True)
    monkeypatch.setattr(runlock.os, "getpid", lambda: 2001)
    assert runlock._try_lock_windows(reader2, shared=True)  # another slot: readers run together
    assert not runlock._try_lock_windows(writer, shared=False)  # refused while anyone reads
    runlock._unlock_windows(reader1)
    runlock._unlock_windows(reader2)
    assert fake.ranges[reader1.fileno()] == [] and fake.ranges[reader2.fileno()] == []
    assert runlock._try_lock_windows(writer, shared=False)
    assert not runlock._try_lock_windows(late, shared=True)  # a reader while a writer holds it
    assert runlock._try_lock_windows(writer, shared=True)  # a writer turning back into a reader
    assert fake.ranges[writer.fileno()] == [(1 + 2001 % (runlock.WINDOWS_SLOTS - 1), 2 + 2001 % (runlock.WINDOWS_SLOTS - 1))]
    monkeypatch.setattr(runlock.os, "getpid", lambda: 1000)
    assert runlock._try_lock_windows(late, shared=True)
    for handle in handles:
        runlock._unlock_windows(handle)
        handle.close()
