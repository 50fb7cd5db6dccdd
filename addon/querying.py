"""Open a query engine on an imported scene (no bpy), through the engine's pipeline.

The text encoder is chosen as ``fourlegs highlight`` chooses it (:class:`fourlegs_engine.api.EncoderConfig`
with ``name="auto"``: the encoder the field was distilled with).
"""
from __future__ import annotations

from typing import Any, Optional

_ENGINES: dict[int, Any] = {}


def open_query_engine(scene: Any, options: Optional[Any] = None) -> Any:
    """A ``QueryEngine`` for ``scene`` (cached per scene object when ``options`` is None: the engine's
    defaults); InputError if the scene has no language field."""
    from fourlegs_engine import api

    key = id(scene)
    if options is None and key in _ENGINES:
        return _ENGINES[key]
    engine = api.open_query_engine(scene, options=options)
    if options is None:
        _ENGINES[key] = engine
    return engine
