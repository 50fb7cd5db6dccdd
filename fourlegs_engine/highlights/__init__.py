"""Highlight planning: a localized text query -> shots with camera and scene-time keys (pure engine, no bpy).

- :mod:`.plan` — :class:`HighlightPlan` (versioned JSON, docs/CONTRACTS.md "highlights").
- :mod:`.effects` — ``play``, ``zoom_in``, ``bullet_time``, ``desaturate_background``: parameters,
  needs, shot builders.
- :mod:`.planner` — :func:`plan_highlight`: computes only what the chosen effects need.
- :mod:`.presets` — TOML presets (repository ``presets/``, a packaged copy, user directories).
- :mod:`.camera_paths`, :mod:`.timing` — poses, orbits, dollies, easing, time remapping.
- :mod:`.preview` — contact sheet rendered by the engine's rasterizer.
"""
from ..lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "PLAN_FORMAT": "plan", "PLAN_VERSION": "plan", "CameraKey": "plan", "HighlightPlan": "plan", "Shot": "plan",
    "TimeKey": "plan", "Localizer": "planner", "plan_highlight": "planner", "plan_needs": "planner",
    "Preset": "presets", "available_presets": "presets", "load_preset": "presets", "parse_preset": "presets"
})
