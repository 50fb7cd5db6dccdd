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
from .gaussians import (GaussianSequence, normalize_quaternions_chunked, quaternions_need_normalizing,
                        release_mapped_pages)
from .scene import Scene

FORMAT_NAME = "fourlegs-bundle"
FORMAT_VERSION = 1
SCENE_FILE = "scene.json"
ARRAY_FIELDS = ("means", "rotations", "log_scales", "opacity_logits", "colors", "sh", "foreground", "labels")
REQUIRED_FIELDS = ("means", "rotations", "log_scales", "opacity_logits")
LANGUAGE_FILE_KEYS = ("latents", "decoder", "codebook")  # language entries that name files in the bundle
MAX_TIMESTEPS = 1 << 20
MAX_GAUSSIANS = 1 << 34
MAX_FPS = 10_000.0


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
        if (isinstance(value, str) and key in ("decoder", "codebook") and is_inside(src_root.resolve(), value)
                and (src_root / value).is_file()):
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
    if not isinstance(version, int) or isinstance(version, bool) or version > FORMAT_VERSION or version < 1:
        raise InputError(f"unsupported bundle version {version!r} (this build reads 1..{FORMAT_VERSION})",
                         file=meta_file, field="version")
    for key in ("arrays", "cameras", "num_timesteps", "num_gaussians"):
        if key not in meta:
            raise InputError("missing key", file=meta_file, field=key)
    validate_bundle_meta(meta, meta_file)
    return meta


def _integer(meta: dict[str, Any], key: str, low: int, high: int, file: Path) -> int:
    value = meta[key]
    if isinstance(value, bool) or not isinstance(value, int):
        raise InputError(f"must be an integer, got {value!r}", file=file, field=key)
    if not low <= value <= high:
        raise InputError(f"must be in {low}..{high}, got {value}", file=file, field=key)
    return value


#: scene.json ``language`` fields and the types they must have (others are free)
_LANGUAGE_TYPES = {"encoder": (str, "text"), "mode": (str, "text"), "config_hash": (str, "text"),
                   "decoder_fingerprint": (str, "text"), "latent_dim": (int, "a whole number 1..4096"),
                   "canonical_phrases": (list, "a list of text phrases")}


def _check_language_types(language: dict[str, Any], meta_file: Path) -> None:
    """InputError naming the ``language`` field of scene.json whose value has the wrong type."""
    for key, (kind, what) in _LANGUAGE_TYPES.items():
        if key not in language:
            continue
        value = language[key]
        ok = isinstance(value, kind) and not isinstance(value, bool)
        if ok and key == "latent_dim":
            ok = 1 <= value <= 4096
        if ok and key == "canonical_phrases":
            ok = all(isinstance(p, str) and p for p in value)
        if not ok:
            raise InputError(f"must be {what}, got {value!r}"[:200], file=meta_file, field=f"language.{key}")


def validate_bundle_meta(meta: dict[str, Any], meta_file: Path) -> None:
    """Check the types and bounds of every ``scene.json`` entry before anything is allocated.

    Raises :class:`InputError` naming the key: integer counts within bounds, a positive finite
    ``fps``, ``arrays`` a mapping of known fields to relative ``.npy`` paths inside the bundle,
    ``cameras`` an object whose ``num_timesteps`` matches the scene, ``language``/``metadata``
    objects (or null). Camera entries themselves are checked by :meth:`CameraRig.from_dict`.
    """
    T = _integer(meta, "num_timesteps", 1, MAX_TIMESTEPS, meta_file)
    _integer(meta, "num_gaussians", 1, MAX_GAUSSIANS, meta_file)
    fps = meta.get("fps", 30.0)
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not 0 < fps <= MAX_FPS:
        raise InputError(f"must be a number in (0, {MAX_FPS:g}], got {fps!r}", file=meta_file, field="fps")
    if "name" in meta and not isinstance(meta["name"], str):
        raise InputError(f"must be a string, got {meta['name']!r}", file=meta_file, field="name")
    for key in ("language", "metadata"):
        if meta.get(key) is not None and not isinstance(meta[key], dict):
            raise InputError(f"must be an object or null, got {type(meta[key]).__name__}", file=meta_file,
                             field=key)
    arrays = meta["arrays"]
    if not isinstance(arrays, dict):
        raise InputError(f"must be an object mapping array names to files, got {type(arrays).__name__}",
                         file=meta_file, field="arrays")
    root = meta_file.parent.resolve()
    for name, rel in arrays.items():
        if not isinstance(rel, str) or not rel:
            raise InputError(f"must be a file name, got {rel!r}", file=meta_file, field=f"arrays.{name}")
        if not is_inside(root, rel):
            raise InputError(f"{rel!r} points outside the bundle; array files must lie inside it",
                             file=meta_file, field=f"arrays.{name}")
    for key, rel in (meta.get("language") or {}).items():
        if key in LANGUAGE_FILE_KEYS and (not isinstance(rel, str) or not is_inside(root, rel)):
            raise InputError(f"{rel!r} is not a file inside the bundle", file=meta_file, field=f"language.{key}")
    _check_language_types(meta.get("language") or {}, meta_file)
    cameras = meta["cameras"]
    if not isinstance(cameras, dict):
        raise InputError(f"must be an object, got {type(cameras).__name__}", file=meta_file, field="cameras")
    for split in ("train", "test"):
        if not isinstance(cameras.get(split, []), list):
            raise InputError(f"must be a list, got {type(cameras[split]).__name__}", file=meta_file,
                             field=f"cameras.{split}")
    if cameras.get("static", False):
        cam_T = cameras.get("num_timesteps")
        if isinstance(cam_T, bool) or not isinstance(cam_T, int) or cam_T not in (0, T):
            raise InputError(f"must be an integer equal to the scene's {T} timesteps, got {cam_T!r}",
                             file=meta_file, field="cameras.num_timesteps")
    else:
        for split in ("train", "test"):
            lists = cameras.get(split, [])
            if len(lists) not in (0, T):
                raise InputError(f"has {len(lists)} timesteps but the scene has {T}", file=meta_file,
                                 field=f"cameras.{split}")
            if any(not isinstance(l, list) for l in lists):
                raise InputError("must be a list of per-timestep camera lists", file=meta_file,
                                 field=f"cameras.{split}")


def is_inside(root: Path, relative: str) -> bool:
    """Whether ``root / relative`` (symlinks resolved) stays inside ``root`` (``root`` resolved)."""
    if Path(relative).is_absolute():
        return False
    target = (root / relative).resolve()
    return target == root or root in target.parents


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
    for arr in loaded.values():  # validation read every timestep; keep only what is used later resident
        release_mapped_pages(arr)
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
