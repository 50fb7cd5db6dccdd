"""What an Inria 3DGS PLY file holds beyond the Gaussians, and which files form a sequence (no bpy)."""
from __future__ import annotations

import re
from pathlib import Path
from typing import Optional

import numpy as np

GAUSSIAN_PROPERTY = re.compile(r"^(x|y|z|nx|ny|nz|opacity|f_dc_\d+|f_rest_\d+|scale_\d+|rot_\d+)$")
_NUMBER = re.compile(r"^(.*?)(\d+)$")


def extra_properties(path: Path) -> dict[str, np.ndarray]:
    """The vertex properties of ``path`` that are not part of a Gaussian (e.g. a per-splat label), as (N,)
    float32 arrays."""
    import plyfile

    vertex = plyfile.PlyData.read(str(path))["vertex"]
    return {p.name: np.asarray(vertex[p.name], np.float32) for p in vertex.properties
            if not GAUSSIAN_PROPERTY.match(p.name) and np.issubdtype(vertex[p.name].dtype, np.number)}


def natural_key(path: Path) -> list:
    """Sort key that orders embedded numbers numerically (``f2`` < ``f10``)."""
    return [int(tok) if tok.isdigit() else tok.lower() for tok in re.split(r"(\d+)", path.name)]


def sequence_of(path: Path) -> Optional[Path]:
    """The folder of ``path`` when the file is one frame of a numbered sequence (``frame_0001.ply``,
    ``frame_0002.ply``, ... with the same prefix), else None."""
    match = _NUMBER.match(path.stem)
    if match is None:
        return None
    prefix = match.group(1)
    frames = [p for p in path.parent.glob("*.ply")
              if (m := _NUMBER.match(p.stem)) is not None and m.group(1) == prefix]
    return path.parent if len(frames) > 1 else None
