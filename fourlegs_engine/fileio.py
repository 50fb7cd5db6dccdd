"""Atomic file writes and safe array loading (no pickle is ever executed)."""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
import tokenize
import zipfile
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

import numpy as np

from .errors import InputError, OutputExistsError


#: what a damaged ``.npy`` header raises inside numpy: its literal parser (SyntaxError, TokenError),
#: its shape and dtype checks, or the file read itself
NPY_HEADER_ERRORS = (OSError, EOFError, SyntaxError, TypeError, OverflowError, tokenize.TokenError)
#: what ``torch.load(weights_only=True)`` raises for files that are not torch files at all (garbage
#: reaches the restricted unpickler as unknown opcodes or memo keys)
TORCH_LOAD_ERRORS = (RuntimeError, OSError, EOFError, ValueError, KeyError, IndexError, TypeError,
                     AttributeError, UnicodeDecodeError, zipfile.BadZipFile)


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
        with writing(path):
            with open(tmp, "wb") as fh:
                np.save(fh, array, allow_pickle=False)
                fh.flush()
                os.fsync(fh.fileno())


#: how libraries word a write that failed (torch's zip writer, OpenEXR) in a RuntimeError
_WRITE_FAILURES = ("unexpected pos", "PytorchStreamWriter", "file write failed", "No space left", "Cannot write",
                   "Error writing", "Unable to write")


@contextlib.contextmanager
def writing(path: str | Path) -> Iterator[None]:
    """Errors of a library's write (numpy, torch, zipfile) named after ``path``: numpy's ``N requested and M
    written`` and torch's ``unexpected pos`` carry no path and no errno; they become :func:`incomplete_write_error`
    (ENOSPC when the disk is full), an OSError without a path gets ``path``."""
    try:
        yield
    except OSError as exc:
        _release_writers(exc)
        if exc.filename is not None:
            raise
        if exc.errno is not None:
            raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from None
        raise incomplete_write_error(path, str(exc)[:200]) from None
    except RuntimeError as exc:
        text = str(exc)
        if any(k in text for k in _WRITE_FAILURES):
            raise incomplete_write_error(path, text.splitlines()[0][:200] if text else "write failed") from None
        raise


def _release_writers(exc: BaseException) -> None:
    """Close what the failed write left open now, quietly: a ``zipfile.ZipFile`` that numpy's ``savez`` kept
    in its frame would otherwise try to flush to the full disk again when collected, printing
    ``Exception ignored in ZipFile.__del__`` after the command's own error line."""
    import gc
    import sys
    import traceback

    tb = exc.__traceback__
    while tb is not None:
        for value in list(tb.tb_frame.f_locals.values()):
            if isinstance(value, zipfile.ZipFile):
                value.fp = None  # its file is ours (closed by our ``with``); close() and __del__ become no-ops
        tb = tb.tb_next
    traceback.clear_frames(exc.__traceback__)
    previous = sys.unraisablehook
    sys.unraisablehook = lambda unraisable: None
    try:
        gc.collect()
    finally:
        sys.unraisablehook = previous


def save_npz_atomic(path: str | Path, **arrays: np.ndarray) -> None:
    """``np.savez`` atomically, a full disk reported naming ``path`` (and nothing printed after it)."""
    with atomic_path(path) as tmp:
        with writing(path):
            with open(tmp, "wb") as fh:
                np.savez(fh, **arrays)


def save_torch_atomic(path: str | Path, obj: Any) -> None:
    """``torch.save`` of a state dict or checkpoint, atomically, a full disk reported naming ``path``."""
    import torch

    with atomic_path(path) as tmp:
        with writing(path):
            torch.save(obj, tmp)


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
    except MemoryError:
        raise InputError("its header claims an array larger than memory (damaged)", file=path, field=field) from None
    except NPY_HEADER_ERRORS as exc:
        # a damaged header reaches numpy's literal parser (SyntaxError/TokenError) or its shape checks
        raise InputError(f"corrupt or truncated .npy file ({type(exc).__name__}: {str(exc)[:120]})", file=path,
                         field=field) from None


def read_json(path: str | Path) -> Any:
    path = Path(path)
    if not path.is_file():
        raise InputError("file is missing", file=path)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"not valid JSON ({exc})", file=path) from None
    except RecursionError:
        raise InputError("nested too deeply to be a file of this program (damaged or hostile)", file=path) from None


def unpickling_detail(exc: BaseException) -> str:
    """The informative part of a refused ``torch.load(weights_only=True)``, without torch's advice.

    torch's message suggests re-running with ``weights_only=False`` ("will likely succeed"), which
    would execute the file's code; that advice is dropped, the reason kept (e.g. 'Unsupported
    global: GLOBAL builtins.print').
    """
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    for index, line in enumerate(lines):
        if "WeightsUnpickler error:" in line:
            rest = line.split("WeightsUnpickler error:", 1)[1].strip()
            lines = [rest] if rest else lines[index + 1:index + 2]
            break
    keep = [line for line in lines if "weights_only" not in line and "likely succeed" not in line
            and "trusted source" not in line]
    text = (keep[0] if keep else "unsupported content").split(" Please use", 1)[0].strip()
    return text.replace("was not an allowed global by default.", "is not allowed").rstrip(".")[:200]


OUTPUTS_MARKER = ".fourlegs-outputs.json"


def check_outputs(paths: Iterable[str | Path | None], *, overwrite: bool) -> None:
    """Check every output of a command before any is written: existing ones are refused, all named
    in one :class:`OutputExistsError`, unless ``overwrite``. ``None`` entries are skipped."""
    existing = [str(p) for p in paths if p is not None and Path(p).exists()]
    if existing and not overwrite:
        raise OutputExistsError(", ".join(existing))


def claim_outputs(directory: str | Path, paths: Iterable[str | Path], *, overwrite: bool) -> Callable[[], None]:
    """Check a command's outputs in ``directory`` up front; returns ``record()`` to call just before
    the first of them is written, which marks them as the command's own.

    A file already there is the user's unless an earlier, interrupted run recorded it in
    ``directory/.fourlegs-outputs.json``; the user's files are refused (all named in one line)
    unless ``overwrite``. Recorded files may be replaced by a resumed run, and only those.
    """
    directory = Path(directory)
    paths = [Path(p) for p in paths]
    marker = directory / OUTPUTS_MARKER
    owned: set[str] = set()
    if marker.is_file():
        try:
            recorded = json.loads(marker.read_text(encoding="utf-8"))
            owned = {str(n) for n in recorded.get("outputs", [])} if isinstance(recorded, dict) else set()
        except (ValueError, UnicodeDecodeError):
            owned = set()
    foreign = [p for p in paths if p.exists() and p.name not in owned]
    if foreign and not overwrite:
        raise OutputExistsError(", ".join(map(str, foreign)))

    def record() -> None:
        write_json_atomic(marker, {"outputs": sorted(owned | {p.name for p in paths})})

    return record


@contextlib.contextmanager
def output_group() -> Iterator[list[Path]]:
    """All of a command's outputs or none: yields a list the command appends each written path to;
    if the block fails, the ones already written are removed, so a re-run is not refused by a
    partial result (each file itself is written atomically)."""
    written: list[Path] = []
    try:
        yield written
    except BaseException:
        for path in reversed(written):
            path = Path(path)
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path, ignore_errors=True)
            else:
                with contextlib.suppress(FileNotFoundError):
                    path.unlink()
        raise


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
EXR_MAGIC = b"\x76\x2f\x31\x01"
_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}  # colour type -> samples per pixel


def image_file_problem(path: str | Path, size: tuple[int, int] | None = None) -> str | None:
    """Why the PNG or EXR at ``path`` is not a complete image (None when it is).

    PNG: signature, every chunk's length and CRC, IHDR size (== ``size`` (width, height) if given),
    the image data inflated to exactly the rows IHDR announces, and a final IEND. EXR: its magic
    number and a non-trivial length. A frame written to a full disk (0 bytes, or cut short) fails.
    """
    import struct
    import zlib

    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        return f"unreadable ({exc.strerror or exc})"
    if not data:
        return "empty (0 bytes)"
    if path.suffix.lower() == ".exr":
        return None if data[:4] == EXR_MAGIC and len(data) > 64 else "not a complete OpenEXR file"
    if not data.startswith(PNG_SIGNATURE):
        return "not a PNG file"
    pos, header, idat, ended = len(PNG_SIGNATURE), None, [], False
    while pos + 12 <= len(data):
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        body = data[pos + 8:pos + 8 + length]
        crc = data[pos + 8 + length:pos + 12 + length]
        if len(body) != length or len(crc) != 4 or zlib.crc32(kind + body) != struct.unpack(">I", crc)[0]:
            return f"cut short or damaged in its {kind.decode('latin-1')!r} chunk"
        if kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", body[:13])
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"IEND":
            ended = True
            break
        pos += 12 + length
    if header is None or not ended:
        return "cut short (no IHDR or IEND chunk)"
    width, height, depth, colour, _, _, interlace = header
    if size is not None and (width, height) != tuple(size):
        return f"is {width}x{height}, expected {size[0]}x{size[1]}"
    try:
        pixels = zlib.decompress(b"".join(idat))
    except zlib.error as exc:
        return f"image data damaged ({exc})"
    if not interlace and colour in _PNG_CHANNELS:
        row = 1 + (width * _PNG_CHANNELS[colour] * depth + 7) // 8
        if len(pixels) != row * height:
            return f"image data has {len(pixels)} bytes, expected {row * height}"
    return None


def incomplete_write_error(path: str | Path, problem: str, needed_bytes: int = 1 << 20) -> OSError:
    """The error for a file a writer we do not control (Blender) left incomplete: ENOSPC when the
    disk has less than ``needed_bytes`` free (it filled up), else EIO naming the problem."""
    import errno

    path = Path(path)
    probe = path.parent
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    try:
        free = shutil.disk_usage(probe).free
    except OSError:
        free = None
    if free is not None and free < needed_bytes:
        return OSError(errno.ENOSPC, "No space left on device", str(path))
    return OSError(errno.EIO, f"written incomplete: {problem}", str(path))
