"""Scoped thread counts: torch's intra-op threads and the fused CPU kernels' worker threads."""
from __future__ import annotations

import os

from contextlib import contextmanager
from typing import Iterator, Optional

import torch

#: workers of the fused CPU kernels (:mod:`fourlegs_engine.render.cpu_kernels`); None: torch's thread count
_kernel_threads: Optional[int] = None


@contextmanager
def torch_threads(count: Optional[int]) -> Iterator[None]:
    """Run the block with ``count`` torch intra-op threads (None or < 1: leave torch's setting), then
    restore the previous setting."""
    before = torch.get_num_threads()
    if count is not None and count >= 1:
        torch.set_num_threads(int(count))
    try:
        yield
    finally:
        torch.set_num_threads(before)


def kernel_thread_count() -> int:
    """Worker threads the fused CPU kernels may use: the :func:`kernel_threads` setting, else torch's
    intra-op thread count."""
    return _kernel_threads if _kernel_threads is not None else torch.get_num_threads()


@contextmanager
def kernel_threads(count: Optional[int]) -> Iterator[None]:
    """Run the block with ``count`` worker threads for the fused CPU kernels (None or < 1: leave the
    setting), independently of torch's intra-op threads, then restore the previous setting.

    The kernels' workers are Python threads that block while idle (the kernels release the GIL),
    so unlike OpenMP threads that spin at barriers between thousands of small tensor ops, they cost
    nothing when another process needs the core.
    """
    global _kernel_threads
    before = _kernel_threads
    if count is not None and count >= 1:
        _kernel_threads = int(count)
    try:
        yield
    finally:
        _kernel_threads = before


def openmp_wait_policy() -> str:
    """What OpenMP's idle workers were told to do at barriers: the ``OMP_WAIT_POLICY`` of this process
    ("PASSIVE": sleep, set by ``import fourlegs_engine`` unless the environment says otherwise;
    "ACTIVE": spin), or "default" (the OpenMP runtime's own: spin for a while, then sleep). The runtime
    reads it once, when torch is first imported."""
    return os.environ.get("OMP_WAIT_POLICY", "default")


def usable_cpu_count() -> int:
    """The CPU cores this process may run on (its affinity mask where the OS has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
