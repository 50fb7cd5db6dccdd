"""Atomic file writes and safe array loading (no pickle is ever executed)."""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from .errors import InputError, OutputExistsError


@contextlib.contextmanager
def atomic_path(path: str | Path, *, overwrite: bool = True, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` only if the block succeeds.

    The temporary file keeps ``path``'s suffix (or ``suffix``) so libraries that dispatch on the
    extension (numpy, matplotlib, OpenEXR) write the right format. Nothing half-written is ever left
    at ``path``: on error the temporary file is removed.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise OutputExistsError(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".part" + (suffix or path.suffix),
                               dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.chmod(tmp_path, 0o666 & ~_umask())  # mkstemp creates 0600; give outputs normal permissions
        os.replace(tmp_path, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


@contextlib.contextmanager
def atomic_directory(path: str | Path, *, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary directory beside ``path``; it replaces ``path`` only if the block succeeds.

    An existing ``path`` is refused unless ``overwrite``; when replaced, the old directory is moved
    aside first and deleted after the new one is in place, so ``path`` is never half-written.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise OutputExistsError(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent))
    try:
        yield tmp
        if path.exists():
            trash = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".old", dir=path.parent))
            path.rename(trash / "old")
            tmp.rename(path)
            shutil.rmtree(trash, ignore_errors=True)
        else:
            tmp.rename(path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_bytes_atomic(path: str | Path, data: bytes, *, overwrite: bool = True) -> None:
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_bytes(data)


def write_json_atomic(path: str | Path, obj: Any, *, overwrite: bool = True) -> None:
    text = json.dumps(obj, indent=2, sort_keys=False, allow_nan=False)
    write_bytes_atomic(path, (text + "\n").encode("utf-8"), overwrite=overwrite)


def save_npy_atomic(path: str | Path, array: np.ndarray, *, overwrite: bool = True) -> None:
    """Write one ``.npy`` file atomically. Object arrays are refused (they would need pickle)."""
    array = np.asarray(array)
    if array.dtype.hasobject:
        raise InputError("object arrays cannot be stored (they would need pickle)", file=path)
    with atomic_path(path, overwrite=overwrite) as tmp:
        with open(tmp, "wb") as fh:
            np.save(fh, array, allow_pickle=False)
            fh.flush()
            os.fsync(fh.fileno())


def load_npy(path: str | Path, *, mmap: bool = True, field: str | None = None) -> np.ndarray:
    """Load a ``.npy`` file memory-mapped, never unpickling; errors name the file and field."""
    path = Path(path)
    if not path.is_file():
        raise InputError("file is missing", file=path, field=field)
    try:
        return np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except ValueError as exc:  # object arrays, or pickled content
        msg = str(exc)
        if "pickle" in msg.lower() or "object" in msg.lower():
            raise InputError("holds an object/pickled array, which is refused (never unpickled)",
                             file=path, field=field) from None
        raise InputError(f"corrupt or truncated .npy file ({msg})", file=path, field=field) from None
    except (OSError, EOFError) as exc:
        raise InputError(f"corrupt or truncated .npy file ({exc})", file=path, field=field) from None


def read_json(path: str | Path) -> Any:
    path = Path(path)
    if not path.is_file():
        raise InputError("file is missing", file=path)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"not valid JSON ({exc})", file=path) from None
