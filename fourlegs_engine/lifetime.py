"""A worker process that ends with the process that started it.

``fourlegs highlight`` renders in a child process (headless Blender). When the parent is killed (SIGTERM,
SIGKILL, a closed terminal), the child must not render on alone: it would keep the output folder's lock
and finish a job nobody waits for. The parent passes its pid in :data:`PARENT_PID_ENV`; the child calls
:func:`die_with_parent`, which on Linux asks the kernel for SIGTERM when the parent dies
(``prctl(PR_SET_PDEATHSIG)``) and everywhere starts a watchdog thread that polls the parent (macOS and
Windows have no parent-death signal). Files are written atomically, so a child stopped at any point
leaves only temporary files, which the next run removes (:mod:`fourlegs_engine.runlock`).
"""
from __future__ import annotations

import os
import signal
import sys
import threading
import time
from typing import Optional

__all__ = ["PARENT_PID_ENV", "die_with_parent", "parent_alive"]

PARENT_PID_ENV = "FOURLEGS_PARENT_PID"
_PR_SET_PDEATHSIG = 1
#: seconds between the watchdog's looks at the parent, and the grace a SIGTERM gets before the hard exit
POLL_SECONDS = 0.5
GRACE_SECONDS = 10.0


def parent_alive(parent_pid: int) -> bool:
    """Whether ``parent_pid`` is still this process's parent (POSIX) or still running (Windows)."""
    if os.name == "posix":
        return os.getppid() == parent_pid
    try:
        import ctypes

        handle = ctypes.windll.kernel32.OpenProcess(0x1000, False, parent_pid)  # QUERY_LIMITED_INFORMATION
        if not handle:
            return False
        code = ctypes.c_ulong()
        ctypes.windll.kernel32.GetExitCodeProcess(handle, ctypes.byref(code))
        ctypes.windll.kernel32.CloseHandle(handle)
        return code.value == 259  # STILL_ACTIVE
    except (OSError, AttributeError):
        return True


def die_with_parent(parent_pid: Optional[int] = None) -> bool:
    """Make this process end when its parent does; returns whether a parent is being watched.

    ``parent_pid``: the parent to watch (default: :data:`PARENT_PID_ENV`, else nothing is watched). If the
    parent is already gone, this process ends at once.
    """
    if parent_pid is None:
        try:
            parent_pid = int(os.environ.get(PARENT_PID_ENV, ""))
        except ValueError:
            return False
    if sys.platform.startswith("linux"):
        _set_parent_death_signal()
    if not parent_alive(parent_pid):
        _end()
    watchdog = threading.Thread(target=_watch, args=(parent_pid,), name="fourlegs-parent-watchdog", daemon=True)
    watchdog.start()
    return True


def _set_parent_death_signal() -> None:
    try:
        import ctypes
        import ctypes.util

        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
    except (OSError, AttributeError):
        pass  # the watchdog still watches


def _watch(parent_pid: int) -> None:
    while parent_alive(parent_pid):
        time.sleep(POLL_SECONDS)
    _end()


def _end() -> None:
    """SIGTERM to this process (Python's default ends it; a handler may clean up), a hard exit if it lingers."""
    try:
        os.kill(os.getpid(), signal.SIGTERM)
    except OSError:
        pass
    time.sleep(GRACE_SECONDS)
    os._exit(143)
