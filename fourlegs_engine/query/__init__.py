"""Query engine: when and where a text query happens in a scene with a distilled 4D language field.

``relevancy`` (LERF form, stable), ``temporal`` (paper §3.2 / supplementary A.2), ``spatial`` (centre of
mass, 3D lift, best component box), ``viewpoint`` (best view), ``codebook`` (k-means fast path),
``multiscene`` (§6.2), and :class:`~.engine.QueryEngine` tying them to a scene and its field.
Submodules import torch lazily where they can; ``QueryEngine`` is imported on first attribute access.
"""
from __future__ import annotations

from typing import Any

__all__ = ["QueryEngine", "TemporalResult", "Localization", "ViewResult", "CentreResult", "relevancy"]


def __getattr__(name: str) -> Any:
    if name == "QueryEngine":
        from .engine import QueryEngine
        return QueryEngine
    if name in ("TemporalResult", "Localization", "ViewResult", "CentreResult"):
        from . import results
        return getattr(results, name)
    if name == "relevancy":
        from .relevancy import relevancy
        return relevancy
    raise AttributeError(name)
