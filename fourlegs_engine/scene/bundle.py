"""Native scene bundle: ``scene.json`` (format + version) and one ``.npy`` per array, memory-mapped.

Layout::

    bundle/
      scene.json          {"format": "fourlegs-bundle", "version": 1, "arrays": {field: file}, ...}
      means.npy rotations.npy log_scales.npy opacity_logits.npy [colors.npy] [sh.npy]
      [foreground.npy] [labels.npy] [language/latents.npy] ...

Writing is atomic: everything goes into a temporary sibling directory that is renamed into place,
and an existing bundle is only replaced when ``overwrite=True``. Stages (extraction, distillation)
add their own sub-directories inside an existing bundle with their own atomic per-file writes.
"""
from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..fileio import atomic_directory, load_npy, read_json, save_npy_atomic, write_json_atomic
from .camera import CameraRig
from .gaussians import GaussianSequence, normalize_quaternions_chunked, quaternions_need_normalizing
from .scene import Scene

FORMAT_NAME = "fourlegs-bundle"
FORMAT_VERSION = 1
SCENE_FILE = "scene.json"
ARRAY_FIELDS = ("means", "rotations", "log_scales", "opacity_logits", "colors", "sh", "foreground", "labels")
REQUIRED_FIELDS = ("means", "rotations", "log_scales", "opacity_logits")


def is_bundle(path: str | Path) -> bool:
    return (Path(path) / SCENE_FILE).is_file()


def write_bundle(scene: Scene, path: str | Path, *, overwrite: bool = False) -> Path:
    """Write ``scene`` as a bundle at ``path`` atomically; returns the path.

    Latents (if any) are copied chunk by chunk (never loaded whole) to ``language/latents.npy``.
    """
    path = Path(path)
    with atomic_directory(path, overwrite=overwrite) as tmp:
        g = scene.gaussians
        arrays: dict[str, str] = {}
        for name in ARRAY_FIELDS:
            arr = getattr(g, name)
            if arr is not None:
                save_npy_atomic(tmp / f"{name}.npy", np.asarray(arr))
                arrays[name] = f"{name}.npy"
        language = dict(scene.language) if scene.language else None
        if g.latents is not None:
            (tmp / "language").mkdir()
            out = np.lib.format.open_memmap(tmp / "language" / "latents.npy", mode="w+",
                                            dtype=g.latents.dtype, shape=tuple(g.latents.shape))
            for t in range(g.num_timesteps):
                out[t] = g.latents[t]
            out.flush()
            del out
            arrays["latents"] = "language/latents.npy"
            language = language or {}
            language.setdefault("latent_dim", int(g.latents.shape[-1]))
        if scene.root is not None and language:
            _copy_language_files(Path(scene.root), tmp, language)
        meta = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "name": scene.name,
            "fps": scene.fps,
            "num_timesteps": g.num_timesteps,
            "num_gaussians": g.num_gaussians,
            "arrays": arrays,
            "cameras": scene.cameras.to_dict(),
            "language": language,
            "metadata": scene.metadata,
        }
        write_json_atomic(tmp / SCENE_FILE, meta)
    scene.root = path
    return path


def _copy_language_files(src_root: Path, dst_root: Path, language: dict[str, Any]) -> None:
    """Copy files the language description points to (e.g. the decoder) along with the bundle."""
    for key, value in language.items():
        if isinstance(value, str) and key in ("decoder", "codebook") and (src_root / value).is_file():
            (dst_root / value).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src_root / value, dst_root / value)


def read_bundle_meta(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    meta_file = path / SCENE_FILE
    meta = read_json(meta_file)
    if not isinstance(meta, dict):
        raise InputError("top level must be a JSON object", file=meta_file)
    if meta.get("format") != FORMAT_NAME:
        raise InputError(f"format is {meta.get('format')!r}, expected {FORMAT_NAME!r}", file=meta_file,
                         field="format")
    version = meta.get("version")
    if not isinstance(version, int) or version > FORMAT_VERSION or version < 1:
        raise InputError(f"unsupported bundle version {version!r} (this build reads 1..{FORMAT_VERSION})",
                         file=meta_file, field="version")
    for key in ("arrays", "cameras", "num_timesteps", "num_gaussians"):
        if key not in meta:
            raise InputError("missing key", file=meta_file, field=key)
    return meta


def load_bundle(path: str | Path) -> Scene:
    """Read a bundle; arrays are memory-mapped (latents are never loaded whole)."""
    path = Path(path)
    meta = read_bundle_meta(path)
    meta_file = path / SCENE_FILE
    arrays = meta["arrays"]
    for name in REQUIRED_FIELDS:
        if name not in arrays:
            raise InputError("missing array entry", file=meta_file, field=f"arrays.{name}")
    loaded: dict[str, Any] = {}
    for name, rel in arrays.items():
        if name not in ARRAY_FIELDS + ("latents",):
            continue
        loaded[name] = load_npy(path / rel, mmap=True, field=name)
    T, N = int(meta["num_timesteps"]), int(meta["num_gaussians"])
    for name, arr in loaded.items():
        lead = arr.shape[:2] if name in ("means", "rotations", "labels", "latents") else None
        if lead is not None and tuple(lead) != (T, N):
            raise InputError(f"has leading shape {tuple(lead)}, but scene.json says T={T}, N={N}",
                             file=path / arrays[name], field=name)
    rot = loaded["rotations"]
    if rot.ndim == 3 and rot.shape[-1] == 4 and quaternions_need_normalizing(rot):
        loaded["rotations"] = normalize_quaternions_chunked(rot, file=str(path / arrays["rotations"]),
                                                            field="rotations")
    g = GaussianSequence(source=str(path), **{k: v for k, v in loaded.items()})
    rig = CameraRig.from_dict(meta["cameras"], file=str(meta_file))
    if rig.num_timesteps not in (0, T):
        raise InputError(f"cameras cover {rig.num_timesteps} timesteps but the scene has {T}",
                         file=meta_file, field="cameras")
    return Scene(gaussians=g, cameras=rig, name=str(meta.get("name", path.name)), fps=float(meta.get("fps", 30.0)),
                 root=path, language=meta.get("language"), metadata=meta.get("metadata") or {})


def update_bundle_meta(path: str | Path, **changes: Any) -> dict[str, Any]:
    """Atomically update top-level keys of ``scene.json`` (e.g. ``language=...``, ``arrays=...``)."""
    path = Path(path)
    meta = read_bundle_meta(path)
    meta.update(changes)
    write_json_atomic(path / SCENE_FILE, meta)
    return meta
