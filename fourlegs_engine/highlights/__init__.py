"""Highlight planning: a localized text query -> shots with camera and scene-time keys (pure engine, no bpy).

- :mod:`.plan` — :class:`HighlightPlan` (versioned JSON, docs/CONTRACTS.md "highlights").
- :mod:`.effects` — ``play``, ``zoom_in``, ``bullet_time``, ``desaturate_background``: parameters,
  needs, shot builders.
- :mod:`.planner` — :func:`plan_highlight`: computes only what the chosen effects need.
- :mod:`.presets` — TOML presets (repository ``presets/``, a packaged copy, user directories).
- :mod:`.camera_paths`, :mod:`.timing` — poses, orbits, dollies, easing, time remapping.
- :mod:`.preview` — contact sheet rendered by the engine's rasterizer.
"""
from .plan import PLAN_FORMAT, PLAN_VERSION, CameraKey, HighlightPlan, Shot, TimeKey
from .planner import Localizer, plan_highlight, plan_needs
from .presets import Preset, available_presets, load_preset, parse_preset

__all__ = ["PLAN_FORMAT", "PLAN_VERSION", "CameraKey", "HighlightPlan", "Localizer", "Preset", "Shot", "TimeKey",
           "available_presets", "load_preset", "parse_preset", "plan_highlight", "plan_needs"]
