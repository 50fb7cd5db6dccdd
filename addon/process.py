"""Process-level settings of the headless job's render (not Blender API work, not engine work)."""
from __future__ import annotations

import contextlib
import os
import sys
from typing import Iterator


@contextlib.contextmanager
def blender_log_silenced() -> Iterator[None]:
    """Send C-level stdout (file descriptor 1) to /dev/null during the block.

    Blender's renderer prints a few lines per rendered frame ("Saved: ...", "Time: ...") straight to
    the C stdout, past Python's ``sys.stdout``; over hundreds of frames they bury the job's own
    progress, which tqdm shows on stderr.
    """
    sys.stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


#: glibc ``mallopt`` parameters and their defaults
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_DEFAULT_TRIM, _DEFAULT_MMAP = 128 * 1024, 128 * 1024


@contextlib.contextmanager
def heap_kept(mmap_threshold: int = 32 * 1024 * 1024, trim_threshold: int = 1024 * 1024 * 1024) -> Iterator[None]:
    """Keep freed memory in the process heap during the block (glibc ``mallopt``; elsewhere a no-op).

    Every frame allocates and frees the rasterizer's tile buffers (megabytes each); by default glibc
    serves them with mmap or trims the heap top after each free, so every frame faults its memory in
    again. With large buffers kept in the heap the faults disappear. The heap is trimmed when the block
    ends.
    """
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt, malloc_trim = libc.mallopt, libc.malloc_trim
    except (OSError, AttributeError):  # not glibc
        yield
        return
    changed = bool(mallopt(_M_MMAP_THRESHOLD, int(mmap_threshold))) and bool(mallopt(_M_TRIM_THRESHOLD,
                                                                                    int(trim_threshold)))
    try:
        yield
    finally:
        if changed:
            mallopt(_M_TRIM_THRESHOLD, _DEFAULT_TRIM)
            mallopt(_M_MMAP_THRESHOLD, _DEFAULT_MMAP)
            malloc_trim(0)
