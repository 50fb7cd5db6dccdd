"""One writer per scene and per output folder, and no stale temporary files after a killed run.

A run that writes into a scene bundle (the language stages, ``fit``) or an output folder (``highlight``)
holds an advisory lock on a small file beside it (``.NAME.fourlegs-lock`` in the same parent folder, so
the lock exists before the folder does; the holder removes it when it is done). A run that only reads a
scene (``query``, ``plan``, ``highlight``) holds its lock shared: readers run side by side, a writer is
refused while any reads, a reader while one writes (at once, with the holder named: no waiting). The lock
is ``fcntl.flock`` on POSIX and ``msvcrt.locking`` byte ranges on Windows: the operating system releases
it when the holder exits, however it exits (SIGKILL included), so a lock is never left behind. Each
holder writes its pid and command line into the file; a refused run gets one line naming them
(:class:`LockedError`).

When a run acquires the lock exclusively it removes the temporary files (``.*.part*``) and folders an
earlier, killed run left in the locked tree: while it holds the lock nobody else can be writing them.
Workers that split one stage (``--shard i/n``) take the lock shared: they may run side by side, and none
of them cleans up the others' temporary files.
"""
from __future__ import annotations

import contextlib
import os
import re
import shutil
import sys
from pathlib import Path
from typing import Iterator

from .errors import FourlegsError

__all__ = ["LockedError", "RunLock", "hold_run_lock", "lock_file_of", "release_all", "remove_stale_parts",
           "run_lock"]

LOCK_SUFFIX = ".fourlegs-lock"
#: temporary names of :func:`fileio.atomic_path`/``atomic_directory`` and the renderer's frames: a dot,
#: a name, ``.part`` (or ``.old``), then optionally an extension
STALE_NAME = re.compile(r"^\..+\.(part|old)(\.[A-Za-z0-9]+)*$")
#: how deep below the locked folder stale temporary files are looked for (bundle/language/steps/ is 2)
STALE_DEPTH = 2


class LockedError(FourlegsError):
    """Another run holds the lock of a scene or output folder."""

    def __init__(self, target: str | Path, holder: str):
        self.target, self.holder = str(target), holder
        super().__init__(f"{target}: in use by another fourlegs run ({holder}); wait for it to finish or stop "
                         "it, then run the same command again")


def lock_file_of(target: str | Path) -> Path:
    """The lock file of a scene or output folder: ``.NAME.fourlegs-lock`` beside it (symbolic links resolved,
    so a scene reached through a link and its real path share one lock)."""
    target = Path(os.path.realpath(target))
    return target.parent / f".{target.name}{LOCK_SUFFIX}"


#: locks this process holds: lock file -> [open file, modes] where ``modes`` lists the ``shared`` flag of each
#: nested acquisition. A process never blocks itself; it holds the lock exclusively while any acquisition is.
_HELD: dict[Path, list] = {}


class RunLock:
    """The advisory lock of ``target``; :meth:`acquire` raises :class:`LockedError` when it is taken.

    Shared holders (readers: ``query``, ``plan``, ``highlight``; ``--shard`` workers) run side by side; an
    exclusive holder (a writer) runs alone. A process that reads a scene and then writes it (``query`` on a
    scene without a language field builds it) turns its shared lock exclusive for the writing, which is
    refused while other processes read, and shared again afterwards.
    """

    def __init__(self, target: str | Path, *, shared: bool = False, clean: bool = True):
        self.target = Path(target)
        self.path = lock_file_of(target)
        self.shared = shared
        self.clean = clean

    def acquire(self) -> "RunLock":
        held = _HELD.get(self.path)
        if held is not None:
            if not self.shared and all(held[1]):
                self._upgrade(held[0])
            held[1].append(self.shared)
            return self
        for _ in range(100):  # the holder removes the file when it releases: lock the file that is there
            try:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                handle = open(self.path, "a+", encoding="utf-8")
            except OSError:
                return self  # an unwritable place: the run's own writes will fail with their own line
            if not _try_lock(handle, self.shared):
                holder = _read_holder(self.path)
                handle.close()
                raise LockedError(self.target, holder)
            if _same_file(handle, self.path):
                break
            _unlock(handle)
            handle.close()
        else:
            raise LockedError(self.target, _read_holder(self.path))
        _describe_holder(handle, self.shared)
        _HELD[self.path] = [handle, [self.shared]]
        if self.clean and not self.shared:
            self._clean()
        return self

    def _upgrade(self, handle) -> None:
        """Turn this process's shared lock exclusive (LockedError naming the other readers if they remain)."""
        if not _try_lock(handle, shared=False):
            holder = _read_holder(self.path)
            _try_lock(handle, shared=True)  # the failed conversion dropped the shared lock: take it again
            raise LockedError(self.target, holder)
        _describe_holder(handle, shared=False)
        if self.clean:
            self._clean()

    def _clean(self) -> None:
        remove_stale_parts(self.target)
        _remove_stale_siblings(self.target)

    def release(self) -> None:
        held = _HELD.get(self.path)
        if held is None:
            return
        was_shared = all(held[1])
        held[1].pop()
        if not held[1]:
            del _HELD[self.path]
            with contextlib.suppress(OSError):
                if not was_shared:  # an exclusive holder removes the file (shared holders may still use it)
                    self.path.unlink()
                _unlock(held[0])
            held[0].close()
        elif all(held[1]) and not was_shared:  # back to reading: let other readers in again
            _try_lock(held[0], shared=True)

    def __enter__(self) -> "RunLock":
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


@contextlib.contextmanager
def run_lock(target: str | Path, *, shared: bool = False) -> Iterator[RunLock]:
    """Hold the lock of ``target`` for the block (see :class:`RunLock`)."""
    lock = RunLock(target, shared=shared)
    with lock:
        yield lock


def hold_run_lock(target: str | Path, *, shared: bool = False) -> RunLock:
    """Take the lock of ``target`` until the command ends (:func:`release_all`) or this process exits."""
    return RunLock(target, shared=shared).acquire()


def release_all() -> None:
    """Release every lock this process holds (the command line calls it when a command ends)."""
    for path in list(_HELD):
        del _HELD[path][1][1:]
        lock = RunLock.__new__(RunLock)
        lock.path = path
        lock.release()


def remove_stale_parts(root: str | Path, depth: int = STALE_DEPTH) -> list[Path]:
    """Remove the temporary files and folders an interrupted run left in ``root`` and its sub-folders (down
    to ``depth`` levels). Only call it while holding ``root``'s lock exclusively. Returns what was removed."""
    root = Path(root)
    removed: list[Path] = []
    if not root.is_dir() or root.is_symlink():
        return removed
    try:
        entries = list(os.scandir(root))
    except OSError:
        return removed
    for entry in entries:
        path = Path(entry.path)
        if STALE_NAME.match(entry.name):
            with contextlib.suppress(OSError):
                if entry.is_dir(follow_symlinks=False):
                    shutil.rmtree(path)
                else:
                    path.unlink()
                removed.append(path)
        elif depth > 0 and entry.is_dir(follow_symlinks=False):
            removed += remove_stale_parts(path, depth - 1)
    return removed


def _remove_stale_siblings(target: Path) -> None:
    """The target's own temporaries beside it: ``.NAME.*.part`` (a folder written whole, cut short) and the
    stale temporaries inside its work folders ``.NAME.*`` (e.g. a fit's ``.NAME.fit``)."""
    target = Path(os.path.abspath(target))
    try:
        siblings = [p for p in target.parent.iterdir() if p.name.startswith(f".{target.name}.")]
    except OSError:
        return
    for path in siblings:
        if STALE_NAME.match(path.name):
            with contextlib.suppress(OSError):
                shutil.rmtree(path) if path.is_dir() and not path.is_symlink() else path.unlink()
        elif path.is_dir() and not path.is_symlink():
            remove_stale_parts(path)


def _same_file(handle, path: Path) -> bool:
    """Whether ``path`` still names the file ``handle`` locked (not removed by a releasing holder meanwhile)."""
    try:
        return os.path.samestat(os.fstat(handle.fileno()), os.stat(path))
    except OSError:
        return False


def _describe_self() -> str:
    command = " ".join([Path(sys.argv[0]).name if sys.argv and sys.argv[0] else "python", *sys.argv[1:]])
    return f"pid {os.getpid()}: {command[:300]}\n"


def _describe_holder(handle, shared: bool) -> None:
    """Name this process in the lock file: an exclusive holder alone, a shared one beside the other readers
    (whose lines stay until a writer takes the lock; those of ended processes are skipped when read)."""
    with contextlib.suppress(OSError):
        if not shared:
            handle.seek(0)
            handle.truncate()
        handle.write(_describe_self())
        handle.flush()


def _read_holder(path: Path) -> str:
    """The other holders named in the lock file: the running processes among them (all if none is known to
    run; this process's own lines never: it is the one refused)."""
    try:
        lines = [line.strip() for line in path.read_text(encoding="utf-8", errors="replace").splitlines()]
    except OSError:
        lines = []
    lines = [line for line in dict.fromkeys(lines) if line and _pid_of(line) != os.getpid()]
    running = [line for line in lines if _is_running(_pid_of(line))]
    shown = (running or lines)[:3]
    more = f" and {len(running or lines) - 3} more" if len(running or lines) > 3 else ""
    return "; ".join(line[:300] for line in shown) + more if shown else "a running fourlegs process"


def _pid_of(line: str) -> int | None:
    match = re.match(r"pid (\d+):", line)
    return int(match.group(1)) if match else None


def _is_running(pid: int | None) -> bool:
    """Whether a process ``pid`` exists (True where that cannot be told)."""
    if pid is None:
        return False
    if os.name == "nt":
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True
    return True


def _try_lock(handle, shared: bool) -> bool:
    try:
        import fcntl
    except ImportError:  # Windows
        return _try_lock_windows(handle, shared)
    try:
        fcntl.flock(handle.fileno(), (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
        return True
    except BlockingIOError:
        return False
    except OSError:
        return True  # a file system without locks: proceed unlocked rather than refuse every run


#: Windows has exclusive byte-range locks only: a reader locks one byte of ``WINDOWS_SLOTS`` (chosen by its
#: pid), a writer all of them, so readers exclude writers and writers everyone, while readers rarely meet
WINDOWS_SLOTS = 4096
#: the byte range each open lock file holds on Windows: file descriptor -> (offset, length)
_WINDOWS_RANGES: dict[int, tuple[int, int]] = {}


def _try_lock_windows(handle, shared: bool) -> bool:
    import msvcrt

    _unlock_windows(handle)  # a conversion: drop what this handle holds first (flock converts the same way)
    offset, length = (1 + os.getpid() % (WINDOWS_SLOTS - 1), 1) if shared else (0, WINDOWS_SLOTS)
    try:
        handle.seek(offset)
        msvcrt.locking(handle.fileno(), msvcrt.LK_NBLCK, length)
    except OSError:
        return False
    _WINDOWS_RANGES[handle.fileno()] = (offset, length)
    return True


def _unlock_windows(handle) -> None:
    import msvcrt

    offset, length = _WINDOWS_RANGES.pop(handle.fileno(), (0, 0))
    if length:
        with contextlib.suppress(OSError):
            handle.seek(offset)
            msvcrt.locking(handle.fileno(), msvcrt.LK_UNLCK, length)


def _unlock(handle) -> None:
    try:
        import fcntl
    except ImportError:
        _unlock_windows(handle)
        return
    fcntl.flock(handle.fileno(), fcntl.LOCK_UN)
