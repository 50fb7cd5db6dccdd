"""Presets and planning for the add-on (no bpy): the engine's planner behind a small cached API."""
from __future__ import annotations

from types import SimpleNamespace
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
    without recomputing. A need the cached result does not cover falls through to the engine, as does
    the per-Gaussian relevancy the planner frames the action with (so the panel plans exactly as the
    main job, which hands the planner the engine itself). ``engine`` may be a callable opening it
    on first use (a localization restored from the .blend needs no engine until then).
    """

    def __init__(self, engine: Any, query: str, localization: Any = None, need: Iterable[str] = ()):
        self._engine, self.query, self.localization, self.need = engine, query, localization, set(need)

    @property
    def engine(self) -> Any:
        if callable(self._engine) and not hasattr(self._engine, "localize"):
            self._engine = self._engine()
        return self._engine

    def localize(self, query: str, need: set[str]) -> Any:
        if self.localization is not None and query == self.query and set(need) <= self.need:
            return self.localization
        loc = self.engine.localize(query, set(need))
        self.query, self.localization, self.need = query, loc, set(need)
        return loc

    def gaussian_relevancy(self, query: str, t: int) -> Any:
        return self.engine.gaussian_relevancy(query, t)


class PickedSegmentLocalizer:
    """A localization with the segment the user picked in the panel's list instead of the longest one:
    its peak is the picked segment's centre (as the engine defines a peak) and the best view and action
    centre are localized again there."""

    def __init__(self, localizer: Any, segment: Sequence[int]):
        self.inner, self.segment = localizer, (int(segment[0]), int(segment[1]))

    def localize(self, query: str, need: set[str]) -> Any:
        loc = self.inner.localize(query, need)
        temporal = getattr(loc, "temporal", None)
        if temporal is None or not temporal.found or tuple(temporal.segment) == self.segment:
            return loc
        peak = (self.segment[0] + self.segment[1]) // 2
        spatial = set(need) & {"best_view", "action_centre"}
        there = self.inner.engine.localize(query, spatial, t=peak) if spatial else None
        moved = SimpleNamespace(**vars(loc))
        moved.temporal = SimpleNamespace(**vars(temporal))
        moved.temporal.segment, moved.temporal.peak = self.segment, peak
        moved.t = peak
        if there is not None:
            for name in ("best_view", "view_scores", "action_centre", "centre_px", "bbox"):
                setattr(moved, name, getattr(there, name))
        return moved

    def gaussian_relevancy(self, query: str, t: int) -> Any:
        return self.inner.gaussian_relevancy(query, t)


def localization_from_dict(data: dict[str, Any]) -> Any:
    """A localization (what the planner reads of one) from ``Localization.to_dict()``: restored from the
    .blend, so Generate after reopening plans without localizing again."""
    import numpy as np

    temporal = data.get("temporal")
    if temporal is not None:
        temporal = SimpleNamespace(**{**temporal, "scores": np.asarray(temporal.get("scores") or [], np.float64),
                                      "positive": np.asarray(temporal.get("positive") or [], bool),
                                      "segment": None if temporal.get("segment") is None else tuple(temporal["segment"]),
                                      "segments": [tuple(s) for s in temporal.get("segments") or []]})
    centre = data.get("action_centre")
    return SimpleNamespace(query=data.get("query", ""), scene=data.get("scene", ""), temporal=temporal,
                           best_view=data.get("best_view"), view_scores=dict(data.get("view_scores") or {}),
                           action_centre=None if centre is None else np.asarray(centre, np.float64),
                           centre_px=data.get("centre_px"), bbox=data.get("bbox"), t=data.get("t"),
                           timings=dict(data.get("timings") or {}), messages=list(data.get("messages") or []),
                           to_dict=lambda: dict(data))


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
