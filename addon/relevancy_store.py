"""Per-Gaussian relevancy of a query, stored beside the scene's language field.

Blender without PyTorch (any 5.1+ until the add-on installs it, and the 5.3 test job) cannot evaluate
the language field, yet EEVEE and Cycles need the relevancy of every frame they render. So whenever a
highlight is generated where the field can be evaluated (the panel with PyTorch, the main job), the
relevancy of every timestep the highlight desaturates is written here, one file per timestep:

    <bundle>/query/blender-relevancy/<key>/<t:06d>.npy    (N,) float16 in [0, 1]

``key`` hashes the query and the field's ``config_hash``, so a re-distilled field never reads an old
answer. Files are written atomically and read without unpickling. Relevancy for a timestep comes from
the first of: the object's live provider (a query engine), these files, a query engine opened now.
"""
from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any, Callable, Iterable, Optional

import numpy as np

SUBDIR = ("query", "blender-relevancy")


def store_dir(scene: Any, query: str) -> Optional[Path]:
    """Where ``query``'s relevancy of ``scene`` (an engine Scene) is stored; None for an in-memory scene."""
    if getattr(scene, "root", None) is None:
        return None
    field = (scene.language or {}) if isinstance(getattr(scene, "language", None), dict) else {}
    digest = hashlib.sha1(f"{query}\n{field.get('config_hash', '')}\n{field.get('latents', '')}".encode()).hexdigest()
    return Path(scene.root).joinpath(*SUBDIR, digest[:16])


def save(scene: Any, query: str, t: int, values: np.ndarray) -> Optional[Path]:
    """Store the (N,) relevancy of timestep ``t`` (clipped to [0, 1], NaN as 0)."""
    from fourlegs_engine import api

    folder = store_dir(scene, query)
    if folder is None:
        return None
    path = folder / f"{int(t):06d}.npy"
    values = np.clip(np.nan_to_num(np.asarray(values, np.float32).reshape(-1)), 0.0, 1.0).astype(np.float16)
    with api.atomic_path(path) as tmp:
        np.save(tmp, values)
    return path


def load(scene: Any, query: str, t: int) -> Optional[np.ndarray]:
    """The stored (N,) float32 relevancy of timestep ``t``, or None when it is not stored (or damaged)."""
    folder = store_dir(scene, query)
    path = None if folder is None else folder / f"{int(t):06d}.npy"
    if path is None or not path.is_file():
        return None
    try:
        values = np.load(path, allow_pickle=False)
    except (OSError, ValueError):
        return None
    if values.shape != (scene.num_gaussians,):
        return None
    return values.astype(np.float32)


def store_timesteps(scene: Any, query: str, provider: Callable[[int], np.ndarray], timesteps: Iterable[int]) -> int:
    """Compute and store the relevancy of ``timesteps`` not stored yet; returns how many were written."""
    written = 0
    for t in sorted(set(int(t) for t in timesteps)):
        if load(scene, query, t) is None and save(scene, query, t, provider(t)) is not None:
            written += 1
    return written


def stored_provider(scene: Any, query: str) -> Optional[Callable[[int], np.ndarray]]:
    """A provider reading the stored files (None when nothing is stored for ``query``); a timestep without
    a file gives zeros (nothing relevant), never an error during a render."""
    folder = store_dir(scene, query)
    if folder is None or not folder.is_dir() or not any(folder.glob("*.npy")):
        return None

    def provider(t: int) -> np.ndarray:
        values = load(scene, query, t)
        return np.zeros(scene.num_gaussians, np.float32) if values is None else values

    return provider


def relevancy_for(bl_scene: Any, obj: Any, scene: Any, t: int, query: Optional[str]) -> Optional[np.ndarray]:
    """(N,) relevancy of timestep ``t`` for the splat object ``obj`` showing ``scene``: its provider, else the
    stored files of ``query``, else a query engine opened now; None without a query, or with nothing
    stored and no PyTorch."""
    from . import importer, querying
    from .messages import missing_for

    rel = importer.gaussian_relevancy(obj, t)
    if rel is not None or not query:
        return rel
    provider = stored_provider(scene, query)
    if provider is None:
        if missing_for(("torch",)) is not None:
            return None  # nothing stored and no PyTorch to evaluate the field: no relevancy here
        engine = querying.open_query_engine(scene, encoder=querying.encoder_config(bl_scene.fourlegs))
        provider = lambda t, e=engine, q=query: e.gaussian_relevancy(q, t).numpy()  # noqa: E731
    importer.set_relevancy_provider(obj, provider)
    return importer.gaussian_relevancy(obj, t)
