"""Demand-driven planning: preset + localization -> :class:`HighlightPlan`.

The planner first asks every shot of the preset what it needs, then asks the localizer for exactly
that (``localize(query, need)`` with ``need`` a subset of {"temporal", "best_view", "action_centre"};
nothing at all when no shot needs a localization), builds the shots one after the other (each starts
where the previous camera ended), and lists per render pass the frames that need it: ``rgb`` on every
frame, ``relevancy`` only where the background is desaturated, ``depth`` only for shots that ask for
depth of field.

Following the paper (§6.1): the best view is the camera with the most relevancy at the peak (by default
the mass above 0.5, which follows a small subject; the paper's mean with ``view_score="mean"``);
the action centre is the relevancy centre of mass lifted with rendered depth; with ``recentre`` the
best view is turned so the action centre sits mid-frame; the segment is the longest positive run and
the peak its centre.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Optional, Protocol, Sequence

import numpy as np

from ..errors import InputError
from .camera_paths import Pose, aim, look_at_rotation
from .effects import LOCALIZATION_NEEDS, NEED_ACTION_CENTRE, NEED_BEST_VIEW, NEED_TEMPORAL, get_effect
from .framing import MAX_PULL_BACK, Framing, scene_up
from .plan import CameraKey, HighlightPlan, Shot, TimeKey, merge_ranges
from .presets import MAX_FPS, MAX_SIDE, MIN_SIDE, Preset, ShotSpec
from .rig_volume import RigVolume
from .shot_context import ShotContext
from .shot_list import PlannedShot, expand_shots, highlighted_segments

#: the anchor (context) shot shows the subject at most at this share of the first sized zoom's target
#: height, so that zoom has something to grow; the best view's lens is widened to it, but at most to
#: ``MAX_PULL_BACK`` of its focal length
ZOOM_ROOM = 0.6


class Localizer(Protocol):
    """What the planner needs from a query engine (``fourlegs_engine.query.QueryEngine`` fits).

    ``localize`` must compute only the parts named in ``need`` and return an object with the
    attributes of ``query.results.Localization``: ``temporal`` (``found``, ``message``, ``segment``,
    ``segments``, ``peak``, ``scores``), ``best_view`` (camera name), ``action_centre`` ((3,) or None),
    ``t`` (timestep of the view/centre, optional) and ``messages`` (optional).
    """

    def localize(self, query: str, need: set[str]) -> Any: ...


def shot_needs(preset: Preset) -> list[set[str]]:
    """The localization needs of each shot of ``preset``."""
    return [get_effect(s.effect).needs(s.params, first=(i == 0)) for i, s in enumerate(preset.shots)]


def plan_needs(preset: Preset) -> set[str]:
    """Union of what the preset's shots need from the localizer."""
    out: set[str] = set()
    for n in shot_needs(preset):
        out |= n
    return out


def _focal_for_output(camera, resolution: tuple[int, int], fov_fit: str) -> float:
    """Focal length (output px) keeping the camera's vertical or horizontal field of view."""
    if fov_fit == "horizontal":
        return camera.fx * resolution[0] / camera.width
    return camera.fy * resolution[1] / camera.height


def _find_camera(scene, name: str, t: int):
    """A scene camera by name at timestep t; unnamed cameras answer to "cameraNN" (their index in the
    query engine's list of all cameras)."""
    t = min(max(int(t), 0), max(scene.cameras.num_timesteps - 1, 0))
    cams = scene.cameras.cameras(t, "all")
    for i, cam in enumerate(cams):
        if (cam.name or f"camera{i:02d}") == name:
            return cam
    names = ", ".join(c.name or f"camera{i:02d}" for i, c in enumerate(cams))
    raise InputError(f"no camera named {name!r} in scene {scene.name!r} (cameras: {names})", field="camera")


def subject_framing(scene, localizer, query: str, t: int, up: np.ndarray, messages: list[str], *,
                instance: int = 0) -> Optional[Framing]:
    """The framed subject (instance number ``instance`` of the relevant Gaussians, 0: the largest
    relevancy mass) and obstacles at timestep ``t`` from the localizer's per-Gaussian relevancy, its
    cameras kept inside the rig volume (None, with a message, when the localizer cannot give it or
    nothing is relevant there)."""
    relevancy_of = getattr(localizer, "gaussian_relevancy", None)
    g = getattr(scene, "gaussians", None)
    if relevancy_of is None or g is None:
        return None
    t = min(max(int(t), 0), int(g.num_timesteps) - 1)
    rel = relevancy_of(query, t)
    rel = np.asarray(rel.detach().cpu().numpy() if hasattr(rel, "detach") else rel, dtype=np.float64).reshape(-1)
    log_scales = np.asarray(g.log_scales[t] if np.ndim(g.log_scales) == 3 else g.log_scales, dtype=np.float64)
    opacities = 1.0 / (1.0 + np.exp(-np.asarray(g.opacity_logits, dtype=np.float64)))
    means = np.asarray(g.means[t])
    framing = Framing.build(means, np.asarray(g.rotations[t]), np.exp(log_scales), opacities, rel, up,
                            foreground=getattr(g, "foreground", None), instance=instance)
    if framing is not None:
        framing.within_rig(rig_volume(scene, up, t))
        framing.with_track(np.asarray(g.means[:, np.flatnonzero(framing.region.members)]))
    if framing is None and instance == 0:
        messages.append(f"no Gaussian is relevant to {query!r} at timestep {t}: the shots follow the best "
                        "view without framing the action region")
    return framing


def rig_volume(scene, up: np.ndarray, t: int = 0) -> Optional[RigVolume]:
    """The volume the scene's training cameras observed at timestep ``t`` (:mod:`.rig_volume`), the floor
    taken from the Gaussians at ``t``; None without cameras spanning a volume."""
    if not scene.cameras.num_timesteps:
        return None
    t_cam = min(max(int(t), 0), scene.cameras.num_timesteps - 1)
    cams = scene.cameras.cameras(t_cam, "train") or scene.cameras.cameras(t_cam, "all")
    g = getattr(scene, "gaussians", None)
    means = None if g is None else np.asarray(g.means[min(max(int(t), 0), int(g.num_timesteps) - 1)])
    return RigVolume.build(np.array([c.center for c in cams]), up, gaussian_means=means)


def plan_highlight(scene, localizer: Optional[Localizer], query: str, preset: Preset, *,
                   resolution: Optional[Sequence[int]] = None, fps: Optional[float] = None) -> HighlightPlan:
    """Plan a highlight of ``query`` in ``scene`` with ``preset``: localize what the shots need, place the
    anchor camera, build the shots one after the other, merge their render passes.

    Args:
        scene: a :class:`fourlegs_engine.scene.Scene` (cameras, fps, timesteps, name, root).
        localizer: see :class:`Localizer`; may be None when the preset needs no localization.
        query: the text query.
        preset: a validated :class:`Preset`.
        resolution, fps: override the preset's output resolution / frame rate.
    Returns:
        The plan. A query that is not found gives a plan without the localized shots (a full-length
        context shot instead) and a message saying so.
    """
    resolution = tuple(int(v) for v in (resolution or preset.resolution))
    if len(resolution) != 2 or not all(MIN_SIDE <= v <= MAX_SIDE for v in resolution):
        raise InputError(f"must be [width, height] of {MIN_SIDE}..{MAX_SIDE} pixels, got {list(resolution)}",
                         field="resolution")
    out_fps = float(fps if fps is not None else preset.fps)
    if not (0 < out_fps <= MAX_FPS and np.isfinite(out_fps)):
        raise InputError(f"must be a frame rate in (0, {MAX_FPS}], got {out_fps:g}", field="fps")
    messages: list[str] = []
    per_shot = shot_needs(preset)
    found = _localize(scene, localizer, query, preset, per_shot, messages)
    specs = _shots_with_what_was_found(scene, query, preset, per_shot, found, messages)
    up = scene_up(scene.cameras.cameras(0, "all") if scene.cameras.num_timesteps else [])
    framing = None
    if found.centre is not None and specs and any(NEED_ACTION_CENTRE in needs for _, needs in specs):
        framing = subject_framing(scene, localizer, query, found.view_t, up, messages)
        if framing is not None:
            found.centre = framing.centre
    anchor, anchor_focal = _anchor_camera(scene, found, framing, resolution, preset, up, messages)
    if not specs:  # nothing localized survived: show the whole sequence from a sensible camera
        specs, anchor, anchor_focal = _context_shot(scene, anchor, anchor_focal, resolution, preset, messages)

    def camera_pose(name: str) -> tuple[Pose, float]:
        cam = _find_camera(scene, name, found.view_t)
        return Pose.from_camera(cam), _focal_for_output(cam, resolution, preset.fov_fit)

    context = ShotContext(num_timesteps=int(scene.num_timesteps), scene_fps=float(scene.fps), output_fps=out_fps,
                          segment=found.segment, peak=found.peak, action_centre=found.centre, anchor=anchor,
                          anchor_focal=anchor_focal, previous=None, previous_focal=None, camera_pose=camera_pose,
                          up=up, framing=framing, resolution=resolution)
    subjects = [framing] + [subject_framing(scene, localizer, query, found.view_t, up, messages, instance=k)
                            for k in range(1, min(preset.subjects, len(framing.region.instances)))] \
        if framing is not None else [None]
    segments = highlighted_segments(found, preset)
    planned = expand_shots([spec for spec, _ in specs], subjects, segments, subject_t=found.view_t,
                           segment_framing=None if framing is None else
                           (lambda t: subject_framing(scene, localizer, query, t, up, [])))
    shots = _build_shots(planned, context, preset, messages)
    passes, desaturate, blur = _merge_passes(shots)
    plan = HighlightPlan(
        scene={"name": scene.name, "path": None if scene.root is None else str(scene.root),
               "num_timesteps": int(scene.num_timesteps), "fps": float(scene.fps)},
        query=query, localization=_localization_record(found, up, framing, subjects, segments, preset),
        fps=out_fps, resolution=resolution,
        frame_start=int(preset.frame_start), frame_end=shots[-1].frame_end, shots=shots, passes=passes,
        desaturate=desaturate, blur=blur, messages=messages, preset=preset.name)
    return plan.validate()


@dataclass
class _Found:
    """What the localizer found for the plan: the parts asked for (``need``), the temporal answer, the
    segment and peak (when found), the best view's name, the action centre (finite or None) and the
    timestep the view and centre belong to."""

    need: set[str]
    temporal: Any = None
    segment: Optional[tuple[int, int]] = None
    peak: Optional[int] = None
    best_view: Optional[str] = None
    centre: Optional[np.ndarray] = None
    view_t: int = 0

    @property
    def found(self) -> bool:
        return bool(self.temporal is not None and self.temporal.found)

    def available(self) -> set[str]:
        """The localization parts the shots can use."""
        return ({NEED_TEMPORAL} if self.found else set()) | ({NEED_BEST_VIEW} if self.best_view is not None else
                                                             set()) | \
            ({NEED_ACTION_CENTRE} if self.centre is not None else set())


def _localize(scene, localizer: Optional[Localizer], query: str, preset: Preset, per_shot: list[set[str]],
              messages: list[str]) -> _Found:
    """Ask the localizer for exactly what the shots need (nothing when they need nothing)."""
    need = set().union(*per_shot) if per_shot else set()
    if not need:
        return _Found(need)
    if localizer is None:
        raise InputError(f"preset {preset.name!r} needs a localization ({', '.join(sorted(need))}) but no "
                         "query engine was given", field="localizer")
    loc = localizer.localize(query, set(need))
    temporal = getattr(loc, "temporal", None)
    skip = {getattr(temporal, "message", None)} if temporal is not None else set()
    messages.extend(str(m) for m in (getattr(loc, "messages", None) or []) if m not in skip)
    found = _Found(need, temporal, best_view=getattr(loc, "best_view", None))
    if found.found:
        found.segment = tuple(int(v) for v in temporal.segment) if temporal.segment is not None else None
        found.peak = int(temporal.peak) if temporal.peak is not None else None
    centre = getattr(loc, "action_centre", None)
    centre = None if centre is None else np.asarray(centre, dtype=np.float64).reshape(3)
    if centre is not None and not np.all(np.isfinite(centre)):
        messages.append("the action centre was not finite and is ignored")
        centre = None
    found.centre = centre
    view_t = getattr(loc, "t", None)
    found.view_t = int(view_t) if view_t is not None else (found.peak if found.peak is not None else 0)
    return found


def _shots_with_what_was_found(scene, query: str, preset: Preset, per_shot: list[set[str]], found: _Found,
                               messages: list[str]) -> list[tuple[ShotSpec, set[str]]]:
    """The preset's shots whose needs were met; a message for the ones left out."""
    available = found.available()
    specs, dropped = [], []
    for spec, needs in zip(preset.shots, per_shot):
        (specs if needs <= available else dropped).append((spec, needs))
    if NEED_TEMPORAL in found.need and not found.found:
        temporal = found.temporal
        why = (temporal.message if temporal is not None and temporal.message else "no timestep is positive")
        messages.append(f"query {query!r} was not found in scene {scene.name!r} ({why}); the plan has no "
                        "localized effects" + (f" (left out: {', '.join(s.name for s, _ in dropped)})"
                                               if dropped else ""))
    else:
        for spec, needs in dropped:
            missing = sorted(needs - available)
            messages.append(f"shot {spec.name!r} ({spec.effect}) left out: {', '.join(missing)} could not be "
                            "determined")
    return specs


def _anchor_camera(scene, found: _Found, framing: Optional[Framing], resolution: tuple[int, int], preset: Preset,
                   up: np.ndarray, messages: list[str]) -> tuple[Optional[Pose], Optional[float]]:
    """The best view, turned onto the action centre (§6.1) when it is known; with the action region known,
    moved to the nearest clear viewpoint, turned level (upright about the scene's up) onto the region's
    centre and widened until the region fits, and further (to at most ``MAX_PULL_BACK`` of the best view's
    focal length in all) until the subject spans at most ``ZOOM_ROOM`` of the first sized zoom's target
    height, so a best view already tighter than the zoom's target starts wide instead of holding. (None,
    None) without a best view."""
    if found.best_view is None:
        return None, None
    name, centre = found.best_view, found.centre
    cam = _find_camera(scene, str(name), found.view_t)
    anchor, anchor_focal = Pose.from_camera(cam), _focal_for_output(cam, resolution, preset.fov_fit)
    if centre is None or not preset.recentre:
        return anchor, anchor_focal
    if anchor.depth_of(centre) <= 0:
        messages.append(f"the action centre lies behind the best view {name!r}; that camera is turned round to "
                        "face it")
    if framing is None:
        return aim(anchor, centre), anchor_focal
    eye, clear = framing.nearest_clear_position(anchor.position)
    if not clear:
        messages.append(f"no viewpoint near the best view {name!r} sees the action without scene Gaussians in "
                        "the way")
    elif not np.allclose(eye, anchor.position):
        messages.append(f"the best view {name!r} sees the action through other scene Gaussians; the shots "
                        f"start from the nearest clear viewpoint ({np.linalg.norm(eye - anchor.position):.2f} m away)")
    anchor = Pose(eye, look_at_rotation(eye, centre, up, previous=anchor.rotation))
    distance = float(np.linalg.norm(eye - centre))
    best_view_focal = anchor_focal
    fit = framing.fitting_focal(distance, resolution)
    if fit < anchor_focal:
        messages.append(f"the action region does not fit the best view's lens; its lens is widened "
                        f"x{fit / anchor_focal:.2f} to show all of it")
        anchor_focal = fit
    room = _zoom_room_focal(preset, framing, distance, resolution)
    if room is not None and room < anchor_focal and best_view_focal * MAX_PULL_BACK < anchor_focal:
        wider = max(room, best_view_focal * MAX_PULL_BACK)
        messages.append(f"the best view {name!r} already shows the subject at "
                        f"{anchor_focal * framing.region.height / distance / resolution[1]:.2f} of the frame height, "
                        f"above what the zoom grows it to; its lens is widened x{wider / anchor_focal:.2f} so the "
                        "zoom starts wide")
        anchor_focal = wider
    return anchor, anchor_focal


def _zoom_room_focal(preset: Preset, framing: Framing, distance: float, resolution: tuple[int, int]) -> Optional[float]:
    """The widest-needed anchor lens (output px) at which the subject spans at most ``ZOOM_ROOM`` of the
    first sized zoom's ``target_height``, so that zoom grows it; None when no zoom_in shot has a target
    size."""
    for spec in preset.shots:
        target = float(spec.params.get("target_height", 0.0) or 0.0) if spec.effect == "zoom_in" else 0.0
        if target > 0:
            return ZOOM_ROOM * target * resolution[1] * distance / max(framing.region.height, 1e-9)
    return None


def _context_shot(scene, anchor: Optional[Pose], anchor_focal: Optional[float], resolution: tuple[int, int],
                  preset: Preset, messages: list[str]) -> tuple[list[tuple[ShotSpec, set[str]]], Pose, float]:
    """One "play" shot of the whole sequence, from the anchor or else the first training camera."""
    fallback = get_effect("play").resolve({"from": "start", "to": "end", "min_duration_s": 0.0})
    if anchor is None:
        cams = scene.cameras.cameras(0, "train") or scene.cameras.cameras(0, "all")
        if not cams:
            raise InputError("the scene has no cameras to film from", field="cameras")
        anchor, anchor_focal = Pose.from_camera(cams[0]), _focal_for_output(cams[0], resolution, preset.fov_fit)
        fallback["camera"] = "previous"
        messages.append(f"context shot of the whole sequence from camera {cams[0].name or 0!r}")
    return [(ShotSpec("context", "play", fallback), set())], anchor, anchor_focal


def _build_shots(planned: list[PlannedShot], context: ShotContext, preset: Preset, messages: list[str]) -> list[Shot]:
    """The shots one after the other on the timeline, each starting where the previous camera ended."""
    shots: list[Shot] = []
    frame = int(preset.frame_start)
    width = context.resolution[0]
    for item in planned:
        spec = item.spec
        ctx = replace(context, messages=[], **item.overrides)
        effect = get_effect(spec.effect)
        path = effect.build(spec.params, ctx)
        messages.extend(f"{spec.name}: {m}" if not m.startswith(spec.name) else m for m in ctx.messages)
        n = len(path.poses)
        frames = range(frame, frame + n)
        keys = [CameraKey.make(f, pose, focal, width, preset.sensor_width_mm)
                for f, pose, focal in zip(frames, path.poses, path.focals)]
        times = [TimeKey(f, float(t)) for f, t in zip(frames, path.timesteps)]
        passes: dict[str, list[list[int]]] = {"rgb": [[frame, frame + n - 1]]}
        for extra in effect.passes(spec.params):
            passes[extra] = [[frame, frame + n - 1]]
        params = dict(path.params)
        for key, weights in (("desaturation_weights", path.desaturation), ("blur_weights", path.blur)):
            if weights is not None:
                on = [f for f, w in zip(frames, weights) if w > 0]
                passes["relevancy"] = merge_ranges(passes.get("relevancy", []) + [[f, f] for f in on])
                params[key] = [float(w) for w in weights]
        shots.append(Shot(spec.name, spec.effect, frame, frame + n - 1, keys, times, "linear", params, passes))
        context = replace(context, previous=path.poses[-1], previous_focal=float(path.focals[-1]))
        frame += n
    return shots


def _merge_passes(shots: list[Shot]) -> tuple[dict[str, list[list[int]]], Optional[dict[str, Any]],
                                               Optional[dict[str, Any]]]:
    """The plan's render passes (each shot's frame ranges merged per pass), its desaturation and its blur
    (the per-frame weights of every such shot, with the first one's fades and strength; the blur adds
    its radius)."""
    all_passes: dict[str, list[list[int]]] = {}
    for s in shots:
        for k, ranges in s.passes.items():
            all_passes.setdefault(k, []).extend(ranges)
    all_passes = {k: merge_ranges(v) for k, v in all_passes.items()}
    return all_passes, _mask_block(shots, "desaturation_weights"), _mask_block(shots, "blur_weights")


def _mask_block(shots: list[Shot], key: str) -> Optional[dict[str, Any]]:
    """The plan's ``desaturate`` or ``blur`` block from the shots' per-frame weights under ``key``."""
    weights, first = {}, None
    for s in shots:
        w = s.params.pop(key, None)
        if w is None:
            continue
        first = first or s
        weights.update({str(f): float(x) for f, x in zip(range(s.frame_start, s.frame_end + 1), w) if x > 0})
    if not weights:
        return None
    block = {"ranges": merge_ranges([[int(f), int(f)] for f in weights]),
             "fade_in": int(first.params["fade_in_frames"]), "fade_out": int(first.params["fade_out_frames"]),
             "strength": float(first.params["strength"]), "weights": weights}
    if "radius" in first.params:
        block["radius"] = float(first.params["radius"])
    return block


def _localization_record(found: _Found, up: np.ndarray, framing: Optional[Framing], subjects: list,
                         segments: list[tuple[int, int]], preset: Preset) -> dict[str, Any]:
    """The plan's ``localization`` block: what was found, the instances the query matches (``instances``,
    best first, the first ``subjects`` of them framed), and which segments the replays show."""
    temporal, centre = found.temporal, found.centre
    instances = [] if framing is None else [i.to_dict() for i in framing.region.instances]
    return {
        "found": found.found if temporal is not None else None,
        "message": (temporal.message if temporal is not None else "no localization was needed"),
        "segment": None if found.segment is None else list(found.segment),
        "peak": found.peak,
        "segments": [] if temporal is None else [[int(a), int(b)] for a, b in temporal.segments],
        "segment_mode": preset.segments,
        "highlighted_segments": [[int(a), int(b)] for a, b in segments],
        "scores": [] if temporal is None else [float(v) for v in np.asarray(temporal.scores).reshape(-1)],
        "action_centre": None if centre is None else [float(v) for v in centre],
        "best_view": None if found.best_view is None else str(found.best_view),
        "t": found.view_t if (found.best_view is not None or centre is not None) else None,
        "computed": sorted(found.need, key=LOCALIZATION_NEEDS.index),
        "up": [float(v) for v in up],
        "action_region": None if framing is None else {
            "centre": [float(v) for v in framing.centre], "radius": float(framing.region.radius),
            "height": float(framing.region.height), "gaussians": int(framing.region.members.sum())},
        "instances": instances,
        "framed_instances": len([f for f in subjects if f is not None]),
    }
