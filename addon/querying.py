"""Open a query engine on an imported scene (no bpy): language field + text encoder + QueryEngine."""
from __future__ import annotations

from typing import Any

from ._engine import engine_module

_ENGINES: dict[int, Any] = {}


def open_query_engine(scene: Any, **options: Any) -> Any:
    """A ``QueryEngine`` for ``scene`` (cached per scene object); InputError if it has no language field."""
    key = id(scene)
    if key in _ENGINES and not options:
        return _ENGINES[key]
    errors = engine_module("errors")
    info = scene.language or {}
    if scene.root is None or not info:
        raise errors.InputError("the scene has no distilled language field: run `fourlegs distill` on it "
                                "(or `fourlegs highlight`, which does every step)", file=scene.root,
                                field="language")
    field_mod = engine_module("language.field")
    field = field_mod.LanguageField.open(scene) if hasattr(field_mod.LanguageField, "open") else \
        field_mod.LanguageField(scene)
    encoders = engine_module("language.encoders")
    text_encoder = encoders.get_encoder(str(info.get("encoder", "viclip")), **_encoder_kwargs(scene, info))
    query_mod = engine_module("query.engine")
    engine = query_mod.QueryEngine(scene, field, text_encoder, **options)
    if not options:
        _ENGINES[key] = engine
    return engine


def _encoder_kwargs(scene: Any, info: dict) -> dict:
    kwargs = info.get("encoder_kwargs") or {}
    return dict(kwargs)


def forget(scene: Any) -> None:
    _ENGINES.pop(id(scene), None)
