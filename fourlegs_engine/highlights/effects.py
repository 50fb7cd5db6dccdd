"""The four highlight effects: what each needs, and the shot each builds.

Every effect declares its needs up front (:meth:`Effect.needs`) so the planner computes only those
parts of the localization, and lists only the render passes the chosen effects use:

========================  =========================================  ====================================
effect                    localization                               render passes (beyond rgb)
========================  =========================================  ====================================
play                      temporal if its time refers to the         depth if ``depth_of_field``
                          segment/peak; best view if it films from
                          it
zoom_in                   temporal, best view, 3D action centre      depth if ``depth_of_field``
bullet_time               temporal (peak), best view, action centre  depth if ``depth_of_field``
desaturate_background     temporal (segment), best view if filmed    relevancy, only on the frames whose
                          from it                                    scene time is in the segment, plus
                                                                     the fade-in/out margins
blur_background           as desaturate_background                   as desaturate_background
========================  =========================================  ====================================

``zoom_in`` and ``bullet_time`` take ``target_height``: the subject's height as a fraction of the frame
height at the end of the zoom and during the orbit (0 leaves the zoom to ``factor``).

Shots start exactly where the previous shot's camera ended (position, orientation and focal length),
so the camera never jumps at a shot boundary.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np

from ..errors import InputError
from . import timing
from .camera_paths import Pose, aim, dolly_path, hold_path, interpolate_poses, orbit_path, slerp_rotations
from .framed_moves import follow_subject, framed_orbit, framed_zoom, upright
from .framing import MAX_PULL_BACK
from .shot_context import ShotContext, ShotPath

TIME_ANCHORS = ("start", "end", "segment_start", "segment_end", "peak")
LOCALIZED_ANCHORS = ("segment_start", "segment_end", "peak")

NEED_TEMPORAL = "temporal"
NEED_BEST_VIEW = "best_view"
NEED_ACTION_CENTRE = "action_centre"
LOCALIZATION_NEEDS = (NEED_TEMPORAL, NEED_BEST_VIEW, NEED_ACTION_CENTRE)


# ----------------------------------------------------------------------------------- parameters
@dataclass(frozen=True)
class Param:
    """One effect parameter as written in a preset (TOML value)."""

    kind: str  # "float" | "int" | "str" | "bool"
    default: Any
    doc: str
    choices: Optional[tuple] = None
    minimum: Optional[float] = None
    maximum: Optional[float] = None

    def check(self, value: Any, where: str, file: Any = None) -> Any:
        def bad(problem: str) -> InputError:
            return InputError(problem, file=file, field=where)

        if self.kind == "bool":
            if not isinstance(value, bool):
                raise bad(f"must be true or false, got {value!r}")
            return value
        if self.kind == "str":
            if not isinstance(value, str):
                raise bad(f"must be a string, got {value!r}")
            if self.choices is not None and value not in self.choices:
                raise bad(f"must be one of {', '.join(map(str, self.choices))}; got {value!r}")
            return value
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise bad(f"must be a number, got {value!r}")
        if self.kind == "int" and not float(value).is_integer():
            raise bad(f"must be a whole number, got {value!r}")
        v = int(value) if self.kind == "int" else float(value)
        if not math.isfinite(v):
            raise bad(f"must be finite, got {value!r}")
        if self.minimum is not None and v < self.minimum:
            raise bad(f"must be >= {self.minimum}, got {value!r}")
        if self.maximum is not None and v > self.maximum:
            raise bad(f"must be <= {self.maximum}, got {value!r}")
        return v


_EASING = Param("str", "ease_in_out_cubic", "easing curve of the camera move", tuple(timing.EASINGS))
_TIME_PARAMS = {
    "from": Param("str", "segment_start", "scene time at the first frame", TIME_ANCHORS),
    "from_offset_s": Param("float", 0.0, "seconds (scene clock) added to 'from'", None, -3600, 3600),
    "to": Param("str", "segment_end", "scene time at the last frame", TIME_ANCHORS),
    "to_offset_s": Param("float", 0.0, "seconds (scene clock) added to 'to'", None, -3600, 3600),
    "speed": Param("float", 1.0, "playback speed (1 real time, 0.5 slow motion)", None, 0.01, 100.0),
    "min_duration_s": Param("float", 1.0, "shortest shot; short time spans hold their first moment",
                            None, 0.0, 3600),
    "duration_s": Param("float", 0.0, "fixed shot length; 0 = derived from the time span and speed "
                                      "(a fixed length stretches the span to fit)", None, 0.0, 3600),
}
_CAMERA_PARAMS = {
    "camera": Param("str", "previous", "'previous' (continue), 'best_view', or a scene camera name"),
    "transition_s": Param("float", 0.75, "seconds to swing from the previous camera to this shot's",
                          None, 0.0, 60.0),
    "follow": Param("bool", True, "turn the camera (level) to keep the framed subject mid-frame as it moves "
                                  "(only where the subject is framed)"),
}
_TARGET_HEIGHT = Param("float", 0.0, "the framed subject's height as a fraction of the frame height at the end "
                       "of the move (0 = off: the zoom magnifies by 'factor', the orbit keeps the zoom's distance)",
                       None, 0.0, 1.0)
_DOF = {"depth_of_field": Param("bool", False, "focus on the action centre (renderer needs a depth pass)")}


class Effect:
    """Base class: parameters, needs and the shot builder of one effect."""

    name: str = ""
    params: dict[str, Param] = {}
    defaults: dict[str, Any] = {}

    def resolve(self, given: dict[str, Any], where: str = "shot", file: Any = None) -> dict[str, Any]:
        """Validate ``given`` against the parameter table and fill in defaults."""
        out = {k: (self.defaults[k] if k in self.defaults else p.default) for k, p in self.params.items()}
        for key, value in given.items():
            if key in ("effect", "name"):
                continue
            if key not in self.params:
                raise InputError(f"unknown parameter for effect {self.name!r} (known: "
                                 f"{', '.join(sorted(self.params))})", file=file, field=f"{where}.{key}")
            out[key] = self.params[key].check(value, f"{where}.{key}", file)
        return out

    def needs(self, p: dict[str, Any], *, first: bool) -> set[str]:
        """The parts of the localization this shot needs ({"temporal", "best_view", "action_centre"})."""
        out: set[str] = set()
        if "from" in p and (p["from"] in LOCALIZED_ANCHORS or p["to"] in LOCALIZED_ANCHORS):
            out.add(NEED_TEMPORAL)
        cam = p.get("camera")
        if cam == "best_view" or (cam == "previous" and first):
            out.add(NEED_BEST_VIEW)
        return out

    def passes(self, p: dict[str, Any]) -> set[str]:
        """Render passes (besides rgb) needed on all of this shot's frames."""
        return {"depth"} if p.get("depth_of_field") else set()

    def build(self, p: dict[str, Any], ctx: "ShotContext") -> "ShotPath":
        raise NotImplementedError



# ----------------------------------------------------------------------------------- time
def shot_progress(easing: str, n: int, *, continuing: bool) -> np.ndarray:
    """(n,) eased progress of a camera move. A continuing shot starts at 0 (the previous shot's last
    pose) even when it has a single frame; a first shot of one frame shows the end state."""
    if n == 1:
        return np.zeros(1) if continuing else np.ones(1)
    return timing.ease(easing, timing.progress(n))


def shot_times(p: dict[str, Any], ctx: ShotContext) -> tuple[np.ndarray, dict[str, Any]]:
    """(n,) fractional timesteps of a shot from its time parameters, and facts for its params."""
    t0 = ctx.timestep(p["from"], p["from_offset_s"])
    t1 = ctx.timestep(p["to"], p["to_offset_s"])
    if p["duration_s"] > 0:
        n = timing.frames_for_duration(p["duration_s"], ctx.output_fps)
        times = timing.remap_time(t0, t1, n)
    else:
        natural = timing.play_frame_count(t0, t1, scene_fps=ctx.scene_fps, output_fps=ctx.output_fps,
                                          speed=p["speed"])
        n = max(natural, timing.frames_for_duration(p["min_duration_s"], ctx.output_fps))
        times = timing.remap_time(t0, t1, n, hold_frames=n - natural)
    facts = {"t_from": t0, "t_to": t1, "num_frames": int(n),
             "effective_speed": timing.effective_speed(t0, t1, int(np.count_nonzero(np.diff(times)) + 1),
                                                       scene_fps=ctx.scene_fps, output_fps=ctx.output_fps)}
    return times, facts


def _lens_fitting_subject(ctx: ShotContext, label: str) -> float:
    """The anchor's focal length (output px), widened (to at most ``MAX_PULL_BACK`` of it) until this shot's
    subject fits the frame: a replay of another segment frames the subject found there, which may stand
    nearer the anchor than the one the anchor was chosen for."""
    focal = float(ctx.anchor_focal)
    if ctx.framing is None:
        return focal
    distance = float(np.linalg.norm(ctx.anchor.position - ctx.framing.centre))
    fit = ctx.framing.fitting_focal(distance, ctx.resolution)
    if fit >= focal:
        return focal
    wider = max(fit, MAX_PULL_BACK * focal)
    ctx.messages.append(f"{label}: the subject of this shot stands {distance:.2f} m from the view; its lens is "
                        f"widened x{wider / focal:.2f}" + ("" if wider == fit else " (the most allowed)")
                        + " to show it")
    return wider


def _camera_move(p: dict[str, Any], ctx: ShotContext, n: int) -> tuple[list[Pose], np.ndarray]:
    """Poses/focals of a shot that films from a chosen camera, swinging there from the previous one."""
    cam = p["camera"]
    if cam == "previous":
        pose, focal = ctx.start_camera()
        return hold_path(pose, n), np.full(n, focal)
    if cam == "best_view":
        if ctx.anchor is None:
            raise InputError("camera 'best_view' needs the best view", field="camera")
        target, target_focal = ctx.anchor, _lens_fitting_subject(ctx, p["camera"])
    else:
        if ctx.camera_pose is None:
            raise InputError(f"no scene cameras to resolve {cam!r}", field="camera")
        target, target_focal = ctx.camera_pose(cam)
    if ctx.previous is None:
        return hold_path(target, n), np.full(n, target_focal)
    m = min(n, max(2, timing.frames_for_duration(p["transition_s"], ctx.output_fps)))
    w = np.concatenate([shot_progress(p.get("easing", "ease_in_out_cubic"), m, continuing=True), np.ones(n - m)])
    if n == 1:
        ctx.messages.append(f"{p['camera']}: a one-frame shot cannot swing to its camera; it holds the previous one")
    poses = interpolate_poses(ctx.previous, target, w, pivot=ctx.action_centre, up=ctx.up)
    focals = float(ctx.previous_focal) * (target_focal / float(ctx.previous_focal)) ** w
    if ctx.framing is not None and m > 1:
        # keep looking at the action while swinging round it (a slerp between two views from opposite
        # sides would look away half-way), level about the scene's up; the previous pose's roll is
        # carried along and levelled over the swing
        c = ctx.framing.centre
        if ctx.framing.rig is not None and ctx.framing.rig.contains(c[None])[0]:   # the swing stays in the rig
            inside = ctx.framing.rig.pull_inside(np.array([q.position for q in poses]), c)
            poses = [Pose(x, q.rotation) for x, q in zip(inside, poses)]
        level = [upright(q.position, c, ctx.up) for q in poses]
        offset = level[0].T @ ctx.previous.rotation
        if np.allclose(offset, np.eye(3), atol=1e-6):   # a level previous camera stays exactly level
            offset = np.eye(3)
        poses = [Pose(q.position, slerp_rotations(R @ offset, R, [wi])[0]) for q, R, wi in zip(poses, level, w)]
        poses[0] = ctx.previous
        eyes = np.array([q.position for q in poses[:m]])
        if not ctx.framing.path_is_clear(eyes):
            direct = interpolate_poses(ctx.previous, target, w)
            direct_eyes = np.array([q.position for q in direct[:m]])
            if ctx.framing.path_is_clear(direct_eyes):
                poses = direct   # a straight move past the action only when nothing is in its way
                ctx.messages.append(f"{p['camera']}: the swing round the action passes close to or behind scene "
                                    "Gaussians; the camera moves straight to its view")
            elif not ctx.framing.path_enters_gaussians(eyes):   # the action hidden for a moment: keep the swing
                ctx.messages.append(f"{p['camera']}: the swing to the camera passes behind scene Gaussians (no "
                                    "clear path found)")
            elif not ctx.framing.path_enters_gaussians(direct_eyes):
                poses = direct
                ctx.messages.append(f"{p['camera']}: the swing round the action would pass through scene "
                                    "Gaussians; the camera moves straight to its view")
            else:  # flying through splats fills frames with their blur: cut to the camera instead
                poses, focals = hold_path(target, n), np.full(n, target_focal)
                ctx.messages.append(f"{p['camera']}: every move to the camera passes through scene Gaussians; "
                                    "the shot cuts to it")
    return poses, focals


# ----------------------------------------------------------------------------------- effects
class Play(Effect):
    """Real-time (or slowed) playback of scene time, filmed from a chosen camera (context shot)."""

    name = "play"
    params = {**_TIME_PARAMS, **_CAMERA_PARAMS, "easing": _EASING, **_DOF}
    defaults = {"from": "segment_start", "from_offset_s": -1.5, "to": "segment_start"}

    def build(self, p: dict[str, Any], ctx: ShotContext) -> ShotPath:
        times, facts = shot_times(p, ctx)
        poses, focals = _camera_move(p, ctx, len(times))
        if p["follow"]:
            poses = follow_subject(poses, times, ctx, p["transition_s"])
        return ShotPath(poses, focals, times, {**p, **facts})


class ZoomIn(Effect):
    """Approach the action centre from the current view: dolly (camera moves) or focal-length zoom.

    The distance (dolly) or focal length (zoom) changes geometrically, so the apparent size grows
    at an even rate, shaped by the easing curve. The camera turns onto the action centre while it
    moves, so the action stays framed (it sits at the image centre once the turn is complete).
    """

    name = "zoom_in"
    params = {**_TIME_PARAMS, "easing": _EASING, **_DOF,
              "mode": Param("str", "dolly", "'dolly' moves the camera, 'focal' changes the focal length",
                            ("dolly", "focal")),
              "factor": Param("float", 2.0, "magnification of the action at the end (>= 1)", None, 1.0, 50.0),
              "min_distance_m": Param("float", 0.25, "closest approach to the action centre (dolly)",
                                      None, 0.0, 1e4),
              "target_height": _TARGET_HEIGHT}
    defaults = {"from": "segment_start", "to": "peak", "min_duration_s": 1.5}

    def needs(self, p, *, first):
        return super().needs(p, first=first) | {NEED_TEMPORAL, NEED_BEST_VIEW, NEED_ACTION_CENTRE}

    def build(self, p: dict[str, Any], ctx: ShotContext) -> ShotPath:
        times, facts = shot_times(p, ctx)
        n = len(times)
        centre = ctx.require_centre(self.name)
        start, f0 = ctx.start_camera()
        e = shot_progress(p["easing"], n, continuing=ctx.previous is not None)
        magnification = p["factor"] ** e
        if start.depth_of(centre) <= 0:
            ctx.messages.append("zoom_in: the action centre is behind the starting camera; the zoom turns "
                                "the camera round onto it")
        if ctx.framing is not None:
            return framed_zoom(p, ctx, times, facts, start, f0, e)
        if p["mode"] == "dolly":
            poses = dolly_path(start, centre, 1.0 / magnification, min_distance=p["min_distance_m"])
            focals = np.full(n, f0)
        else:
            aimed = aim(start, centre)
            poses = interpolate_poses(start, aimed, np.clip(e * 4.0, 0.0, 1.0))  # turn early, then zoom
            focals = f0 * magnification
        return ShotPath(poses, focals, times, {**p, **facts, "distance_start": float(np.linalg.norm(
            start.position - centre)), "distance_end": float(np.linalg.norm(poses[-1].position - centre))})


class BulletTime(Effect):
    """Freeze scene time at the peak while the camera orbits the action centre.

    The orbit rotates the current camera rigidly about the vertical axis through the action centre,
    so radius, height and framing are those of the best view (after any zoom); ``radius_scale`` and
    ``height_scale`` can widen or lift the orbit along the way.
    """

    name = "bullet_time"
    params = {**{k: v for k, v in _TIME_PARAMS.items()}, "easing": _EASING, **_DOF,
              "arc_deg": Param("float", 180.0, "orbit angle in degrees (negative = clockwise)", None,
                               -1080.0, 1080.0),
              "radius_scale": Param("float", 1.0, "radius at the end of the orbit / start radius", None,
                                    0.05, 20.0),
              "height_scale": Param("float", 1.0, "height offset at the end / start height offset "
                                    "(>= 0: the orbit never passes through the action's level plane)",
                                    None, 0.0, 20.0),
              "target_height": _TARGET_HEIGHT}
    defaults = {"from": "peak", "to": "peak", "duration_s": 3.0, "easing": "ease_in_out_sine"}

    def needs(self, p, *, first):
        return super().needs(p, first=first) | {NEED_TEMPORAL, NEED_BEST_VIEW, NEED_ACTION_CENTRE}

    def build(self, p: dict[str, Any], ctx: ShotContext) -> ShotPath:
        times, facts = shot_times(p, ctx)
        n = len(times)
        centre = ctx.require_centre(self.name)
        start, f0 = ctx.start_camera()
        e = shot_progress(p["easing"], n, continuing=True)
        if ctx.framing is not None:
            return framed_orbit(p, ctx, times, facts, start, f0, e)
        angles = np.radians(p["arc_deg"]) * e
        poses = orbit_path(start, centre, angles, axis=ctx.up, radius_factors=1.0 + (p["radius_scale"] - 1.0) * e,
                           height_factors=1.0 + (p["height_scale"] - 1.0) * e)
        rel = start.position - centre
        return ShotPath(poses, np.full(n, f0), times, {
            **p, **facts, "centre": [float(v) for v in centre],
            "radius": float(math.hypot(rel[0], rel[1])), "height": float(rel[2]),
            "rigid": bool(np.allclose(ctx.up, [0.0, 0.0, 1.0]))})


class DesaturateBackground(Effect):
    """Playback (by default a slow-motion replay) with everything but the action desaturated.

    Desaturation applies to the frames whose scene time lies inside the localized segment, fading in
    over ``fade_in_frames`` before and out over ``fade_out_frames`` after; only those frames need the
    renderer's relevancy pass.
    """

    name = "desaturate_background"
    params = {**_TIME_PARAMS, **_CAMERA_PARAMS, "easing": _EASING, **_DOF,
              "strength": Param("float", 1.0, "1 = fully grey background", None, 0.0, 1.0),
              "fade_in_frames": Param("int", 6, "frames to fade the desaturation in", None, 0, 10000),
              "fade_out_frames": Param("int", 6, "frames to fade it out", None, 0, 10000),
              "fade_easing": Param("str", "smoothstep", "shape of the fades", tuple(timing.EASINGS))}
    defaults = {"from_offset_s": -0.5, "to_offset_s": 0.5, "speed": 0.5}

    def needs(self, p, *, first):
        return super().needs(p, first=first) | {NEED_TEMPORAL}

    def passes(self, p):
        return super().passes(p)  # relevancy frames depend on the timing: see weights in build()

    def build(self, p: dict[str, Any], ctx: ShotContext) -> ShotPath:
        times, facts = shot_times(p, ctx)
        poses, focals = _camera_move(p, ctx, len(times))
        if p["follow"]:
            poses = follow_subject(poses, times, ctx, p["transition_s"])
        weights = desaturation_weights(times, ctx.segment, strength=p["strength"], fade_in=p["fade_in_frames"],
                                       fade_out=p["fade_out_frames"], easing=p["fade_easing"])
        if not np.any(weights > 0):
            ctx.messages.append(f"{self.name}: no frame of the shot shows the localized segment; nothing is "
                                "masked")
        return ShotPath(poses, focals, times, {**p, **facts}, desaturation=weights)


class BlurBackground(DesaturateBackground):
    """Playback (by default a slow-motion replay) with everything but the action blurred (the paper's
    "blurring the background during the detected temporal segment", §6.1).

    The blur's weight per frame follows the desaturation's rule (``strength`` inside the segment, fades
    before and after); at weight 1 the background is blurred with a Gaussian of ``radius`` times the
    frame height. Only the weighted frames need the relevancy pass.
    """

    name = "blur_background"
    params = {**DesaturateBackground.params,
              "strength": Param("float", 1.0, "1 = the full blur radius", None, 0.0, 1.0),
              "radius": Param("float", 0.02, "blur radius at full strength, as a fraction of the frame height",
                              None, 0.0, 0.2)}

    def build(self, p: dict[str, Any], ctx: ShotContext) -> ShotPath:
        path = super().build(p, ctx)
        return ShotPath(path.poses, path.focals, path.timesteps, path.params, blur=path.desaturation)


def desaturation_weights(times: np.ndarray, segment: Optional[tuple[int, int]], *, strength: float,
                         fade_in: int, fade_out: int, easing: str = "smoothstep") -> np.ndarray:
    """(n,) desaturation weight per frame: ``strength`` while scene time is inside ``segment``.

    Frames just before the first (after the last) in-segment frame fade in (out) over ``fade_in``
    (``fade_out``) frames; every frame in a fade has a weight > 0, all others exactly 0.
    """
    times = np.asarray(times, dtype=np.float64)
    w = np.zeros(len(times))
    if segment is None or strength <= 0:
        return w
    inside = (times >= segment[0] - 1e-9) & (times <= segment[1] + 1e-9)
    idx = np.flatnonzero(inside)
    if idx.size == 0:
        return w
    a, b = int(idx[0]), int(idx[-1])
    w[a:b + 1] = 1.0
    for k in range(1, fade_in + 1):
        if a - k >= 0:
            w[a - k] = float(timing.ease(easing, 1.0 - k / (fade_in + 1)))
    for k in range(1, fade_out + 1):
        if b + k < len(w):
            w[b + k] = float(timing.ease(easing, 1.0 - k / (fade_out + 1)))
    return np.clip(w * strength, 0.0, 1.0)


EFFECTS: dict[str, Effect] = {e.name: e for e in (Play(), ZoomIn(), BulletTime(), DesaturateBackground(),
                                                  BlurBackground())}
#: The effects that mask the picture by relevancy (they need the relevancy pass on their weighted frames).
MASKED_EFFECTS = ("desaturate_background", "blur_background")


def get_effect(name: str, *, file: Any = None, field: str = "effect") -> Effect:
    try:
        return EFFECTS[name]
    except KeyError:
        raise InputError(f"unknown effect {name!r} (one of {', '.join(EFFECTS)})", file=file, field=field) from None
