"""Multi-channel EXR maps (relevancy, depth, alpha) with the OpenEXR package, written atomically."""
from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np

from ..errors import InputError
from ..fileio import atomic_path, incomplete_write_error, writing


def write_exr(path: str | Path, channels: Mapping[str, np.ndarray], *, overwrite: bool = False) -> Path:
    """Write float32 (H,W) channels (e.g. {"relevancy": .., "depth": .., "alpha": ..}) as one EXR file.

    Non-finite values are written as 0. Raises :class:`InputError` for mismatched or non-2D channels.
    """
    import OpenEXR

    if not channels:
        raise InputError("no channels to write", file=path)
    shapes = {k: np.asarray(v).shape for k, v in channels.items()}
    first = next(iter(shapes.values()))
    if len(first) != 2 or any(s != first for s in shapes.values()):
        raise InputError(f"channels must share one (H,W) shape, got {shapes}", file=path)
    data = {k: np.ascontiguousarray(np.nan_to_num(np.asarray(v, dtype=np.float32), nan=0.0, posinf=0.0,
                                                  neginf=0.0)) for k, v in channels.items()}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    path = Path(path)
    with atomic_path(path, overwrite=overwrite) as tmp, writing(path):
        with OpenEXR.File(header, data) as f:
            f.write(str(tmp))
        try:  # OpenEXR may not report a write the full disk cut short: read it back
            with OpenEXR.File(str(tmp)) as check:
                complete = set(check.channels()) == set(data)
        except Exception:  # noqa: BLE001 (any failure to read back is an incomplete file)
            complete = False
        if not complete:
            raise incomplete_write_error(path, "the EXR file does not read back")
    return path


def read_exr(path: str | Path) -> dict[str, np.ndarray]:
    """{channel name: (H,W) float32} of an EXR file written by :func:`write_exr`."""
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise InputError("file is missing", file=path)
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            return {name: np.array(ch.pixels, dtype=np.float32) for name, ch in f.channels().items()}
    except Exception as exc:  # OpenEXR raises plain exceptions for corrupt files
        raise InputError(f"not a readable EXR file ({exc})", file=path) from None
