"""Presets and planning for the add-on (no bpy): the engine's planner behind a small cached API."""
from __future__ import annotations

from typing import Any, Iterable, Optional, Sequence


def preset_names() -> list[str]:
    from fourlegs_engine import api

    try:
        return sorted(api.available_presets())
    except Exception:  # the planner is not installed / presets unreadable: an empty menu, not a crash
        return []


def load_preset(name: str):
    from fourlegs_engine import api

    return api.load_preset(name)


class CachedLocalizer:
    """Answers the planner's ``localize(query, need)`` from one earlier, larger localization.

    Run Query localizes everything once (in a background thread); Generate Highlight then plans
    without recomputing. A need the cached result does not cover falls through to the engine.
    """

    def __init__(self, engine: Any, query: str, localization: Any = None, need: Iterable[str] = ()):
        self.engine, self.query, self.localization, self.need = engine, query, localization, set(need)

    def localize(self, query: str, need: set[str]) -> Any:
        if self.localization is not None and query == self.query and set(need) <= self.need:
            return self.localization
        loc = self.engine.localize(query, set(need))
        self.query, self.localization, self.need = query, loc, set(need)
        return loc


def make_plan(scene: Any, localizer: Any, query: str, preset_name: str, *,
              disabled_effects: Sequence[str] = (), resolution: Optional[Sequence[int]] = None,
              fps: Optional[float] = None) -> dict[str, Any]:
    """Plan a highlight and return the contract's plan dict."""
    from fourlegs_engine import api

    preset = load_preset(preset_name)
    if disabled_effects:
        preset = preset.with_shots([s.effect for s in preset.shots if s.effect not in set(disabled_effects)])
    plan = api.plan_highlight(scene, localizer, query, preset, resolution=resolution, fps=fps)
    return plan.to_dict() if hasattr(plan, "to_dict") else dict(plan)


def plan_needs(preset_name: str) -> set[str]:
    from fourlegs_engine import api

    return set(api.plan_needs(load_preset(preset_name)))
