"""Open a query engine on an imported scene (no bpy): language field + text encoder + QueryEngine.

The text encoder is the one the field was distilled from (``scene.json["language"]["encoder"]``).
ViCLIP needs its weights, which are never downloaded: the add-on reads their paths from the
environment variables ``FOURLEGS_VICLIP_CHECKPOINT`` and ``FOURLEGS_VICLIP_VOCAB``.
"""
from __future__ import annotations

import os
from typing import Any

from ._engine import engine_module

_ENGINES: dict[int, Any] = {}


def text_encoder_for(scene: Any) -> Any:
    encoders = engine_module("language.encoders")
    name = str((scene.language or {}).get("encoder", "viclip"))
    if name == "simulated":
        return encoders.get_encoder(name, scene=scene)
    if name.startswith("viclip"):
        return encoders.get_encoder(name, checkpoint=os.environ.get("FOURLEGS_VICLIP_CHECKPOINT"),
                                    vocab=os.environ.get("FOURLEGS_VICLIP_VOCAB"))
    return encoders.get_encoder(name)


def open_query_engine(scene: Any, **options: Any) -> Any:
    """A ``QueryEngine`` for ``scene`` (cached per scene object); InputError if it has no language field."""
    key = id(scene)
    if key in _ENGINES and not options:
        return _ENGINES[key]
    errors = engine_module("errors")
    if scene.root is None or not scene.language:
        raise errors.InputError("the scene has no distilled language field: run `fourlegs highlight` on it "
                                "once (or the language stages: extract, train-ae, distill)", file=scene.root,
                                field="language")
    field = engine_module("language.field").LanguageField.open(scene.root)
    engine = engine_module("query.engine").QueryEngine(scene, field, text_encoder_for(scene), **options)
    if not options:
        _ENGINES[key] = engine
    return engine


def forget(scene: Any) -> None:
    _ENGINES.pop(id(scene), None)
