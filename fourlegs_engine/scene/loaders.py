"""``load_scene(path)``: open any supported scene by looking at what ``path`` is.

=================================  ==========================================================
``path``                           format
=================================  ==========================================================
directory with ``scene.json``      native bundle (:mod:`.bundle`)
directory with ``params.npz``      Dynamic 3D Gaussians (:mod:`.dynamic3dgs`)
``params.npz``-like ``.npz`` file  Dynamic 3D Gaussians (meta files looked up beside it)
``.ply`` file                      3DGS PLY, static (T=1) (:mod:`.ply`)
directory of ``.ply`` files        3DGS PLY sequence, one file per timestep (natural sort order)
Inria model directory              ``point_cloud/iteration_<highest>/point_cloud.ply``
=================================  ==========================================================
"""
from __future__ import annotations

import re
from pathlib import Path

from ..errors import InputError
from .bundle import is_bundle, load_bundle
from .dynamic3dgs import is_dynamic3dgs, load_dynamic3dgs
from .ply import load_ply_scene, load_ply_sequence
from .scene import Scene

SUPPORTED = ("a bundle directory (scene.json), a Dynamic 3D Gaussians directory (params.npz), "
             "a 3DGS .ply file, or a directory of per-frame .ply files")


def load_scene(path: str | Path) -> Scene:
    """Load a scene from any supported format (see the module table)."""
    path = Path(path).expanduser()
    if not path.exists():
        raise InputError(f"does not exist; expected {SUPPORTED}", file=path)
    if path.is_file():
        suffix = path.suffix.lower()
        if suffix == ".ply":
            return load_ply_scene(path)
        if suffix == ".npz":
            return load_dynamic3dgs(path.parent, params_file=path)
        if path.name == "scene.json":
            return load_bundle(path.parent)
        raise InputError(f"unsupported file type {suffix or '(none)'}; expected {SUPPORTED}", file=path)
    if is_bundle(path):
        return load_bundle(path)
    if is_dynamic3dgs(path):
        return load_dynamic3dgs(path)
    if any(p.suffix.lower() == ".ply" and p.is_file() for p in path.iterdir()):
        return load_ply_sequence(path)
    inria = _inria_point_cloud(path)
    if inria is not None:
        return load_ply_scene(inria)
    raise InputError(f"is not a recognised scene; expected {SUPPORTED}", file=path)


def _inria_point_cloud(model_dir: Path) -> Path | None:
    """The PLY of the highest training iteration in an Inria 3DGS model directory, if any."""
    root = model_dir / "point_cloud"
    if not root.is_dir():
        return None
    best = None
    for d in root.iterdir():
        m = re.fullmatch(r"iteration_(\d+)", d.name)
        if m and (d / "point_cloud.ply").is_file() and (best is None or int(m.group(1)) > best[0]):
            best = (int(m.group(1)), d / "point_cloud.ply")
    return best[1] if best else None
