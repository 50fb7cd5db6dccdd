"""Keep freed memory in the process between frames (glibc's malloc).

Every rendered frame allocates the same large buffers again (tile lists, projections, images, torch
intermediates) and frees them. glibc serves a block above its mmap threshold (128 KiB at first, adapting
up to 32 MiB) with a fresh mapping and unmaps it when it is freed, and gives the top of its heap back to
the system beyond its trim threshold: the next frame's buffers then arrive as new pages that the kernel
must fault in and zero, which costs a render as much system time as a large part of its blending.
:func:`keep_freed_memory` raises both thresholds so that freed blocks are reused instead.

``import fourlegs_engine`` calls it unless ``FOURLEGS_RETURN_FREED_MEMORY=1`` is set. The cost is that a
process keeps up to :data:`TRIM_THRESHOLD` of free heap after its largest frame; other C libraries
(macOS, Windows, musl) are left alone.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os

__all__ = ["MMAP_THRESHOLD", "TRIM_THRESHOLD", "keep_freed_memory", "freed_memory_kept"]

#: blocks up to this size come from the heap (and are reused) instead of a mapping of their own
MMAP_THRESHOLD = 256 << 20
#: free memory at the top of the heap up to this size stays with the process
TRIM_THRESHOLD = 512 << 20
#: mallopt parameters (glibc's malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3

_kept = False


def keep_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds to :data:`MMAP_THRESHOLD` and :data:`TRIM_THRESHOLD`.
    Returns whether they are set (False on another C library, or when glibc refuses)."""
    global _kept
    if _kept:
        return True
    name = ctypes.util.find_library("c")
    if os.name != "posix" or not name:
        return False
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
        libc.gnu_get_libc_version  # only glibc has this
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    _kept = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
    return _kept


def freed_memory_kept() -> bool:
    """Whether :func:`keep_freed_memory` is in effect in this process."""
    return _kept
