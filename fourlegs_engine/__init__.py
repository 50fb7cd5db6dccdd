"""4-LEGS highlights engine: pure Python + torch + numpy (never imports bpy).

Data flows one way: scene -> render -> language (fit, cluster) -> demo -> query -> highlights -> pipeline
-> highlight_job, api -> commands (docs/CONTRACTS.md; tests/test_architecture.py holds it).

Importing the package before torch makes OpenMP's idle workers sleep at barriers instead of spinning
(``OMP_WAIT_POLICY=PASSIVE``, see :mod:`fourlegs_engine.threads`): with spinning workers, one competing
busy process on a shared machine or laptop slows every parallel torch operation many-fold. An explicit
``OMP_WAIT_POLICY`` in the environment is kept; ``FOURLEGS_OPENMP_SPIN=1`` keeps OpenMP's own default.
It also chooses where numba caches its kernels (:mod:`fourlegs_engine.jit_cache`), and keeps freed
memory in the process so that every frame's large buffers are reused instead of faulted in again
(:mod:`fourlegs_engine.memory`; ``FOURLEGS_RETURN_FREED_MEMORY=1`` keeps glibc's defaults).
"""
import os as _os

__version__ = "0.1.0"

if "OMP_WAIT_POLICY" not in _os.environ and _os.environ.get("FOURLEGS_OPENMP_SPIN") != "1":
    _os.environ["OMP_WAIT_POLICY"] = "PASSIVE"

from . import jit_cache as _jit_cache  # noqa: E402 (before numba: a read-only install caches elsewhere or not)

_jit_cache.configure()

if _os.environ.get("FOURLEGS_RETURN_FREED_MEMORY") != "1":
    from . import memory as _memory

    _memory.keep_freed_memory()
