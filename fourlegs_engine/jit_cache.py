"""Where numba keeps its compiled kernels, and whether it can keep them at all.

numba's ``cache=True`` checks only the file that defines a cached kernel: a kernel that inlines code of
another module (the lane kernels, the shared list walks) would be reused unchanged after that module
changed. :func:`configure` (run by ``import fourlegs_engine``, before numba is imported) therefore points
``NUMBA_CACHE_DIR`` at a folder named by :func:`kernel_sources_digest`, a digest of every engine module
that uses numba — any change to them compiles afresh (older folders beside it are removed) — in the
first writable place: the package's ``__pycache__``, then ``$FOURLEGS_CACHE/numba``, the home cache and
the temp folder. On a read-only install with no writable place numba would raise ``cannot cache
function ...`` when the kernel module is imported, which would stop every command, ``--version``
included; :data:`JIT_CACHE` is then False and the kernels are compiled on each run instead. An explicit
``NUMBA_CACHE_DIR`` in the environment is used as it is.
"""
from __future__ import annotations

import hashlib
import os
import re
import shutil
import tempfile
from pathlib import Path

__all__ = ["JIT_CACHE", "configure", "kernel_sources_digest"]

_PACKAGE = Path(__file__).resolve().parent

#: whether the numba kernels are cached on disk (``njit(cache=JIT_CACHE)``)
JIT_CACHE = True


def _writable(folder: Path) -> bool:
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".probe-"):
            return True
    except OSError:
        return False


def kernel_sources_digest(package: Path = _PACKAGE) -> str:
    """16 hex digits of a SHA-256 over the path and text of every module under ``package`` that uses numba."""
    digest = hashlib.sha256()
    for path in sorted(package.rglob("*.py")):
        text = path.read_bytes()
        if b"numba" in text:
            digest.update(path.relative_to(package).as_posix().encode() + b"\0" + text)
    return digest.hexdigest()[:16]


def _drop_stale(folder: Path, keep: str) -> None:
    """Remove the kernel caches of other sources (folders named by other digests) from ``folder``."""
    for child in folder.iterdir():
        if child.name != keep and re.fullmatch(r"[0-9a-f]{16}", child.name) and child.is_dir():
            shutil.rmtree(child, ignore_errors=True)


def configure() -> bool:
    """Choose numba's cache location (see the module docstring); returns :data:`JIT_CACHE`."""
    global JIT_CACHE
    if os.environ.get("NUMBA_CACHE_DIR"):
        JIT_CACHE = _writable(Path(os.environ["NUMBA_CACHE_DIR"]))
        return JIT_CACHE
    candidates = []
    if os.access(_PACKAGE, os.W_OK) and os.access(_PACKAGE / "render", os.W_OK):
        candidates.append(_PACKAGE / "__pycache__" / "numba")
    if os.environ.get("FOURLEGS_CACHE"):
        candidates.append(Path(os.environ["FOURLEGS_CACHE"]) / "numba")
    candidates += [Path.home() / ".cache" / "fourlegs" / "numba",
                   Path(tempfile.gettempdir()) / f"fourlegs-numba-{os.getuid() if hasattr(os, 'getuid') else 0}"]
    digest = kernel_sources_digest()
    for folder in candidates:
        if _writable(folder / digest):
            os.environ["NUMBA_CACHE_DIR"] = str(folder / digest)
            _drop_stale(folder, digest)
            return JIT_CACHE
    JIT_CACHE = False
    return JIT_CACHE
