"""Open a query engine on an imported scene (no bpy), through the engine's pipeline.

The text encoder is chosen as the ``fourlegs`` commands choose it (:class:`fourlegs_engine.api.EncoderOptions`,
``name="auto"``: the encoder the field was distilled with); ViCLIP weights come from the scene's
``encoder_checkpoint`` / ``encoder_vocab`` properties, the add-on's ``--checkpoint`` / ``--vocab``.
"""
from __future__ import annotations

from typing import Any, Callable, Optional

_ENGINES: dict[int, Any] = {}


def encoder_config(props: Any = None) -> Any:
    """The :class:`EncoderOptions` of the add-on's properties (``scene.fourlegs``; None: the defaults)."""
    from fourlegs_engine import api

    def path(value: str) -> Optional[str]:
        if not value:
            return None
        import bpy

        return bpy.path.abspath(value)

    if props is None:
        return api.EncoderOptions()
    return api.EncoderOptions(checkpoint=path(props.encoder_checkpoint), vocab=path(props.encoder_vocab))


def default_options() -> Any:
    """The query options of the panel: the engine's defaults (those of ``fourlegs query`` and ``fourlegs
    highlight``: the sketch path with exact scoring where it cannot decide, fast maps, the best view
    confirmed)."""
    from fourlegs_engine import api

    return api.QueryOptions()


def open_query_engine(scene: Any, options: Optional[Any] = None, encoder: Optional[Any] = None,
                      progress: Optional[Callable[[float, str], None]] = None) -> Any:
    """A ``QueryEngine`` for ``scene`` with ``options`` (QueryOptions; None: :func:`default_options`) and the
    text encoder ``encoder`` (EncoderOptions) names; cached per scene object when ``options`` is None.
    InputError if the scene has no language field. ``progress(fraction, stage)`` is called between the
    steps of opening (see :func:`fourlegs_engine.api.open_query_engine`); an exception it raises (the
    user cancelled) stops the opening there, and nothing is cached."""
    from fourlegs_engine import api

    key = id(scene)
    if options is None and key in _ENGINES:
        return _ENGINES[key]
    engine = api.open_query_engine(scene, options=options if options is not None else default_options(),
                                   encoder_config=encoder or api.EncoderOptions(), progress=progress)
    if options is None:
        _ENGINES[key] = engine
    return engine
