"""Where numba keeps its compiled kernels, and whether it can keep them at all.

numba's ``cache=True`` writes compiled kernels beside the source (``__pycache__``) or into its user-wide
cache directory; on a read-only install with no writable home neither works and numba raises
``cannot cache function ...`` when the kernel module is imported, which would stop every command,
``--version`` included. :func:`configure` (run by ``import fourlegs_engine``, before numba is imported)
points ``NUMBA_CACHE_DIR`` at the first writable place when the install is read-only, and when there is
none, :data:`JIT_CACHE` is False: the kernels are compiled on each run instead of failing.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

__all__ = ["JIT_CACHE", "configure"]

#: whether the numba kernels are cached on disk (``njit(cache=JIT_CACHE)``)
JIT_CACHE = True


def _writable(folder: Path) -> bool:
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".probe-"):
            return True
    except OSError:
        return False


def configure() -> bool:
    """Choose numba's cache location (see the module docstring); returns :data:`JIT_CACHE`."""
    global JIT_CACHE
    if os.environ.get("NUMBA_CACHE_DIR"):
        JIT_CACHE = _writable(Path(os.environ["NUMBA_CACHE_DIR"]))
        return JIT_CACHE
    package = Path(__file__).resolve().parent
    if os.access(package, os.W_OK) and os.access(package / "render", os.W_OK):
        return JIT_CACHE  # numba's own __pycache__ beside the sources
    candidates = [Path(os.environ["FOURLEGS_CACHE"]) / "numba"] if os.environ.get("FOURLEGS_CACHE") else []
    candidates += [Path.home() / ".cache" / "fourlegs" / "numba",
                   Path(tempfile.gettempdir()) / f"fourlegs-numba-{os.getuid() if hasattr(os, 'getuid') else 0}"]
    for folder in candidates:
        if _writable(folder):
            os.environ["NUMBA_CACHE_DIR"] = str(folder)
            return JIT_CACHE
    JIT_CACHE = False
    return JIT_CACHE
