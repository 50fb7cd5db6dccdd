"""Highlight plan (JSON dict, ``docs/CONTRACTS.md``) -> Blender animation data.

Creates one camera ("4-LEGS Highlight Camera") keyed on location, rotation and lens, keys the scene
timestep (``scene.fourlegs.timestep``; held values are bullet-time), and sets the timeline range, fps
and resolution. Everything it creates is tagged ``fourlegs_generated`` so running it again replaces
exactly that and never touches the user's own objects or keys.

Keys are written straight into F-curves (``keyframe_points.add`` + ``foreach_set``), one per plan key.
Dense camera keys of a shot that is not an orbit (one per frame, as the planner writes them) are then
thinned: eased Bezier keys (auto-clamped handles) are kept only where the curve would otherwise leave
the planned path by more than :data:`THIN_TOLERANCE`, so an editor gets a few keys to move. Orbits keep
LINEAR keys along the arc (sparse ones densified around the action centre, so interpolation cannot cut
a chord; planner orbits also get a rig, ``rig.py``); sparse keys elsewhere use Bezier (ease in/out).
The last key of a shot is CONSTANT: shots are joined by cuts, never by a one-frame swoop.
"""
from __future__ import annotations

import math
from typing import Any, Iterable, Sequence

import bpy
import numpy as np
from mathutils import Matrix

from . import convert

GENERATED_KEY = "fourlegs_generated"
CAMERA_NAME = "4-LEGS Highlight Camera"
CAMERA_ACTION_NAME = "4-LEGS Highlight Camera"
LENS_ACTION_NAME = "4-LEGS Highlight Lens"
SCENE_ACTION_NAME = "4-LEGS Scene Time"
TIMESTEP_PATH = "fourlegs.timestep"
MARKERS_KEY = "fourlegs_markers"  # scene property: names of the timeline markers Generate made
SHOT_FRAMES_KEY = "fourlegs_shot_frames"  # scene property: marker name -> the frame its shot starts at
ORBIT_EFFECTS = ("bullet_time",)
#: largest deviation from the planned path that thinning dense keys may introduce, per channel
THIN_TOLERANCE = {"location": 1e-3, "rotation_euler": 1e-3, "lens": 1e-2}  # planner effects whose camera circles the action centre


class PlanError(ValueError):
    """The plan dict does not follow the contract (message names the field)."""


# ----------------------------------------------------------------------------- plan checks
def check_plan(plan: dict[str, Any]) -> dict[str, Any]:
    """Minimal structural validation of a plan dict; raises :class:`PlanError` naming the field."""
    if not isinstance(plan, dict) or plan.get("format") != "fourlegs-highlight-plan":
        raise PlanError("plan: format: expected 'fourlegs-highlight-plan'")
    if int(plan.get("version", 0)) != 1:
        raise PlanError(f"plan: version: unsupported version {plan.get('version')!r} (expected 1)")
    for key in ("frame_start", "frame_end", "fps", "resolution", "shots"):
        if key not in plan:
            raise PlanError(f"plan: {key}: missing")
    if int(plan["frame_end"]) < int(plan["frame_start"]):
        raise PlanError("plan: frame_end: before frame_start")
    for i, shot in enumerate(plan["shots"]):
        for key in ("frame_start", "frame_end", "camera_keys"):
            if key not in shot:
                raise PlanError(f"plan: shots[{i}].{key}: missing")
        for j, k in enumerate(shot["camera_keys"]):
            c2w = np.asarray(k.get("c2w"), dtype=np.float64)
            if c2w.shape != (4, 4) or not np.all(np.isfinite(c2w)):
                raise PlanError(f"plan: shots[{i}].camera_keys[{j}].c2w: expected a finite 4x4 matrix")
    return plan


# ----------------------------------------------------------------------------- F-curve helpers
def _slot_channelbag(id_data: bpy.types.ID, action: bpy.types.Action):
    """The F-curve container of ``id_data`` in ``action`` (channelbag on 4.4+/5.x, the action on 4.2/4.3)."""
    ad = id_data.animation_data or id_data.animation_data_create()
    if ad.action is not action:
        ad.action = action
    if hasattr(action, "slots"):
        from bpy_extras import anim_utils

        slot = ad.action_slot
        if slot is None:
            slot = action.slots.new(id_type=id_data.id_type, name=id_data.name)
            ad.action_slot = slot
        if hasattr(anim_utils, "action_ensure_channelbag_for_slot"):  # Blender 5.0+
            return anim_utils.action_ensure_channelbag_for_slot(action, slot)
        # 4.4 / 4.5: slotted actions without the helper: layer -> keyframe strip -> channelbag
        layer = action.layers[0] if len(action.layers) else action.layers.new("Layer")
        strip = layer.strips[0] if len(layer.strips) else layer.strips.new(type="KEYFRAME")
        return strip.channelbag(slot, ensure=True)
    return action  # Blender < 4.4: Action.fcurves


def ensure_action(id_data: bpy.types.ID, name: str) -> bpy.types.Action:
    """The id's action, creating a tagged one if it has none."""
    ad = id_data.animation_data or id_data.animation_data_create()
    if ad.action is None:
        action = bpy.data.actions.new(name)
        action[GENERATED_KEY] = True
        ad.action = action
    return ad.action


def fcurves_of(id_data: bpy.types.ID):
    """The F-curve collection animating ``id_data`` (empty list when it has no action)."""
    ad = id_data.animation_data
    if ad is None or ad.action is None:
        return []
    if hasattr(ad.action, "slots"):
        from bpy_extras import anim_utils

        if ad.action_slot is None:
            return []
        bag = anim_utils.action_get_channelbag_for_slot(ad.action, ad.action_slot)
        return bag.fcurves if bag is not None else []
    return ad.action.fcurves


def find_fcurve(id_data: bpy.types.ID, data_path: str, index: int = 0):
    for fc in fcurves_of(id_data):
        if fc.data_path == data_path and fc.array_index == index:
            return fc
    return None


def write_fcurve(id_data: bpy.types.ID, action: bpy.types.Action, data_path: str, index: int,
                 frames: Sequence[float], values: Sequence[float], interpolation: Sequence[str]) -> bpy.types.FCurve:
    """Replace the F-curve ``data_path[index]`` of ``id_data`` with keys (frames, values, per-key interpolation)."""
    bag = _slot_channelbag(id_data, action)
    old = find_fcurve(id_data, data_path, index)
    if old is not None:
        bag.fcurves.remove(old)
    fc = bag.fcurves.new(data_path, index=index)
    n = len(frames)
    fc.keyframe_points.add(n)
    co = np.empty((n, 2), np.float32)
    co[:, 0] = frames
    co[:, 1] = values
    fc.keyframe_points.foreach_set("co", co.ravel())
    enum = {item.identifier: item.value for item in
            bpy.types.Keyframe.bl_rna.properties["interpolation"].enum_items}
    fc.keyframe_points.foreach_set("interpolation", [enum[i] for i in interpolation])
    for kp in fc.keyframe_points:
        kp.handle_left_type = kp.handle_right_type = "AUTO_CLAMPED"
    fc.update()
    return fc


def thin_fcurve(fc: bpy.types.FCurve, removable: set[int], tolerance: float) -> int:
    """Remove the keys at ``removable`` frames that the remaining eased curve does not need: a key goes
    when, without it, the curve stays within ``tolerance`` of every original key value nearby. Returns
    how many keys were removed."""
    target = {int(round(kp.co[0])): float(kp.co[1]) for kp in fc.keyframe_points}
    removed = 0
    for frame in sorted(removable):
        points = fc.keyframe_points
        keyed = [int(round(kp.co[0])) for kp in points]
        if frame not in keyed:
            continue
        i = keyed.index(frame)
        kp = points[i]
        if kp.interpolation == "CONSTANT":
            continue
        value = float(kp.co[1])
        points.remove(kp, fast=True)
        fc.update()
        lo = keyed[max(i - 2, 0)]
        hi = keyed[min(i + 2, len(keyed) - 1)]
        error = max(abs(fc.evaluate(f) - target[f]) for f in target if lo <= f <= hi)
        if error > tolerance:
            back = points.insert(frame, value, options={"FAST"})
            back.interpolation = "BEZIER"
            back.handle_left_type = back.handle_right_type = "AUTO_CLAMPED"
            fc.update()
        else:
            removed += 1
    return removed


# ----------------------------------------------------------------------------- pose maths
def _slerp(q0: np.ndarray, q1: np.ndarray, w: float) -> np.ndarray:
    if np.dot(q0, q1) < 0:
        q1 = -q1
    d = float(np.clip(np.dot(q0, q1), -1.0, 1.0))
    if d > 0.9995:
        q = q0 + w * (q1 - q0)
    else:
        th = math.acos(d)
        q = (math.sin((1 - w) * th) * q0 + math.sin(w * th) * q1) / math.sin(th)
    return q / np.linalg.norm(q)


def densify_orbit(keys: list[dict[str, Any]], centre: Sequence[float]) -> list[dict[str, Any]]:
    """Fill frame gaps between camera keys along the arc around ``centre`` (no chord cutting).

    Position: radius, azimuth and height about the vertical axis through ``centre`` are interpolated
    linearly (the shortest way round); orientation: quaternion slerp; focal: linear.
    """
    from mathutils import Quaternion

    centre = np.asarray(centre, dtype=np.float64)
    out: list[dict[str, Any]] = []
    for a, b in zip(keys[:-1], keys[1:]):
        out.append(a)
        gap = int(b["frame"]) - int(a["frame"])
        if gap <= 1:
            continue
        ca, cb = np.asarray(a["c2w"], np.float64), np.asarray(b["c2w"], np.float64)
        pa, pb = ca[:3, 3] - centre, cb[:3, 3] - centre
        ra, rb = math.hypot(pa[0], pa[1]), math.hypot(pb[0], pb[1])
        aa, ab = math.atan2(pa[1], pa[0]), math.atan2(pb[1], pb[0])
        dang = (ab - aa + math.pi) % (2 * math.pi) - math.pi
        qa = np.array(Matrix(ca[:3, :3].tolist()).to_quaternion())
        qb = np.array(Matrix(cb[:3, :3].tolist()).to_quaternion())
        for s in range(1, gap):
            w = s / gap
            r, ang, h = ra + w * (rb - ra), aa + w * dang, pa[2] + w * (pb[2] - pa[2])
            c2w = np.eye(4)
            c2w[:3, :3] = np.array(Quaternion(_slerp(qa, qb, w)).to_matrix())
            c2w[:3, 3] = centre + [r * math.cos(ang), r * math.sin(ang), h]
            key = {"frame": int(a["frame"]) + s, "c2w": c2w.tolist(),
                   "focal_px": float(a.get("focal_px", 0) + w * (b.get("focal_px", 0) - a.get("focal_px", 0)))}
            if "lens_mm" in a and "lens_mm" in b:
                key["lens_mm"] = a["lens_mm"] + w * (b["lens_mm"] - a["lens_mm"])
            key["sensor_width_mm"] = a.get("sensor_width_mm", convert.DEFAULT_SENSOR_WIDTH_MM)
            out.append(key)
    out.append(keys[-1])
    return out


def key_lens_mm(key: dict[str, Any], width: int) -> float:
    if key.get("lens_mm"):
        return float(key["lens_mm"])
    sensor = float(key.get("sensor_width_mm", convert.DEFAULT_SENSOR_WIDTH_MM))
    return float(key["focal_px"]) * sensor / width


# ----------------------------------------------------------------------------- generation
def remove_generated(scene: bpy.types.Scene) -> None:
    """Delete what a previous Generate Highlight created (tagged datablocks, shot markers and the
    timestep F-curve)."""
    made = set(scene.get(MARKERS_KEY, []))
    for marker in [m for m in scene.timeline_markers if m.name in made]:
        scene.timeline_markers.remove(marker)
    for key in (MARKERS_KEY, SHOT_FRAMES_KEY):
        if key in scene:
            del scene[key]
    for obj in [o for o in bpy.data.objects if o.get(GENERATED_KEY)]:
        bpy.data.objects.remove(obj, do_unlink=True)
    for cam in [c for c in bpy.data.cameras if c.get(GENERATED_KEY) and c.users == 0]:
        bpy.data.cameras.remove(cam)
    fc = find_fcurve(scene, TIMESTEP_PATH, 0)
    if fc is not None:
        bag = _slot_channelbag(scene, scene.animation_data.action)
        bag.fcurves.remove(fc)
    ad = scene.animation_data
    if ad is not None and ad.action is not None and ad.action.get(GENERATED_KEY) and not list(fcurves_of(scene)):
        action = ad.action
        ad.action = None
        bpy.data.actions.remove(action)
    for action in [a for a in bpy.data.actions if a.get(GENERATED_KEY) and a.users == 0]:
        bpy.data.actions.remove(action)


def shot_marker_name(index: int, shot: dict[str, Any]) -> str:
    return f"{index + 1} {shot.get('name') or shot.get('effect') or 'shot'}"


def add_shot_markers(scene: bpy.types.Scene, plan: dict[str, Any]) -> list[bpy.types.TimelineMarker]:
    """One timeline marker at the first frame of each shot, named "<n> <shot name>"."""
    shots = sorted(plan["shots"], key=lambda s: int(s["frame_start"]))
    markers = [scene.timeline_markers.new(shot_marker_name(i, shot), frame=int(shot["frame_start"]))
               for i, shot in enumerate(shots)]
    scene[MARKERS_KEY] = [m.name for m in markers]
    scene[SHOT_FRAMES_KEY] = {m.name: m.frame for m in markers}
    return markers


def has_generated(scene: bpy.types.Scene) -> bool:
    """Whether a previous Generate Highlight left data here (which a new one would replace)."""
    return any(o.get(GENERATED_KEY) for o in bpy.data.objects) or bool(scene.get(MARKERS_KEY))


def apply_plan(scene: bpy.types.Scene, plan: dict[str, Any]) -> bpy.types.Object:
    """Create the highlight camera and keys from ``plan``; returns the camera object.

    Replaces anything a previous call created. The scene's active camera becomes the highlight camera.
    """
    check_plan(plan)
    remove_generated(scene)
    markers = add_shot_markers(scene, plan)
    width, height = (int(v) for v in plan["resolution"])
    render = scene.render
    render.resolution_x, render.resolution_y, render.resolution_percentage = width, height, 100
    render.fps = max(1, int(round(float(plan["fps"]))))
    render.fps_base = render.fps / float(plan["fps"])
    scene.frame_start, scene.frame_end = int(plan["frame_start"]), int(plan["frame_end"])

    cam_data = bpy.data.cameras.new(CAMERA_NAME)
    cam_data[GENERATED_KEY] = True
    cam_data.sensor_fit = "HORIZONTAL"
    cam = bpy.data.objects.new(CAMERA_NAME, cam_data)
    cam[GENERATED_KEY] = True
    cam.rotation_mode = "XYZ"
    scene.collection.objects.link(cam)
    scene.camera = cam

    centre = (plan.get("localization") or {}).get("action_centre")
    frames: list[int] = []
    locs: list[Sequence[float]] = []
    eulers: list[Sequence[float]] = []
    lenses: list[float] = []
    interp: list[str] = []
    thinnable: set[int] = set()  # interior frames of dense non-orbit shots
    sensor = convert.DEFAULT_SENSOR_WIDTH_MM
    prev_euler = None
    for shot in sorted(plan["shots"], key=lambda s: int(s["frame_start"])):
        keys = sorted(shot["camera_keys"], key=lambda k: int(k["frame"]))
        if not keys:
            continue
        sparse = any(int(b["frame"]) - int(a["frame"]) > 1 for a, b in zip(keys[:-1], keys[1:]))
        effect = str(shot.get("effect", ""))
        is_orbit = effect in ORBIT_EFFECTS or "orbit" in effect or "arc_deg" in (shot.get("params") or {})
        if sparse and is_orbit and centre is not None:
            keys = densify_orbit(keys, centre)
            sparse = False
        mode = "BEZIER" if sparse and str(shot.get("interpolation", "bezier")).lower() == "bezier" else "LINEAR"
        if not sparse and not is_orbit and len(keys) > 2:
            mode = "BEZIER"
            thinnable.update(int(k["frame"]) for k in keys[1:-1])
        for i, key in enumerate(keys):
            m = Matrix(convert.opencv_to_blender_c2w(np.asarray(key["c2w"], np.float64)).tolist())
            euler = m.to_euler("XYZ", prev_euler) if prev_euler is not None else m.to_euler("XYZ")
            prev_euler = euler
            frames.append(int(key["frame"]))
            locs.append(tuple(m.translation))
            eulers.append(tuple(euler))
            lenses.append(key_lens_mm(key, width))
            sensor = float(key.get("sensor_width_mm", sensor))
            interp.append("CONSTANT" if i == len(keys) - 1 else mode)
    if not frames:
        raise PlanError("plan: shots: no camera keys")
    cam_data.sensor_width = sensor
    action = bpy.data.actions.new(CAMERA_ACTION_NAME)
    action[GENERATED_KEY] = True
    for index in range(3):
        fc = write_fcurve(cam, action, "location", index, frames, [p[index] for p in locs], interp)
        thin_fcurve(fc, thinnable, THIN_TOLERANCE["location"])
        fc = write_fcurve(cam, action, "rotation_euler", index, frames, [e[index] for e in eulers], interp)
        thin_fcurve(fc, thinnable, THIN_TOLERANCE["rotation_euler"])
    lens_action = bpy.data.actions.new(LENS_ACTION_NAME)
    lens_action[GENERATED_KEY] = True
    fc = write_fcurve(cam_data, lens_action, "lens", 0, frames, lenses, interp)
    thin_fcurve(fc, thinnable, THIN_TOLERANCE["lens"])

    time_frames, time_values = [], []
    for shot in sorted(plan["shots"], key=lambda s: int(s["frame_start"])):
        for key in sorted(shot.get("time_keys", []), key=lambda k: int(k["frame"])):
            time_frames.append(int(key["frame"]))
            time_values.append(float(key["timestep"]))
    if time_frames:
        scene_action = ensure_action(scene, SCENE_ACTION_NAME)
        write_fcurve(scene, scene_action, TIMESTEP_PATH, 0, time_frames, time_values,
                     ["LINEAR"] * len(time_frames))
    _rig_orbits(scene, plan, cam, [m.name for m in markers], width, sensor)
    scene.frame_set(scene.frame_start)
    return cam


def _rig_orbits(scene: bpy.types.Scene, plan: dict[str, Any], cam: bpy.types.Object, marker_names: list[str],
                width: int, sensor: float) -> None:
    """Give each planner orbit its rig (``rig.py``) and bind the shot markers to their cameras."""
    from . import rig

    centre = (plan.get("localization") or {}).get("action_centre")
    up = (plan.get("localization") or {}).get("up")
    shots = sorted(plan["shots"], key=lambda s: int(s["frame_start"]))
    cameras = []
    for shot in shots:
        first = min(shot["camera_keys"], key=lambda k: int(k["frame"])) if shot["camera_keys"] else None
        if rig.can_rig(shot, centre):
            cameras.append(rig.build_orbit_rig(scene, shot, centre, key_lens_mm(first, width), sensor, GENERATED_KEY))
        elif rig.can_rig_framed(shot, up):
            cameras.append(rig.build_framed_orbit_rig(scene, shot, key_lens_mm(first, width), sensor, GENERATED_KEY))
        else:
            cameras.append(cam)
    if any(c is not cam for c in cameras):
        rig.bind_markers(scene, marker_names, cameras)


def camera_pose_at(cam: bpy.types.Object, scene: bpy.types.Scene, frame: int) -> tuple[np.ndarray, float]:
    """(OpenCV c2w (4,4), lens mm) of ``cam`` at ``frame`` (evaluates the animation)."""
    scene.frame_set(frame)
    return convert.blender_to_opencv_c2w(np.array(cam.matrix_world)), float(cam.data.lens)


def keyed_frames(id_data: bpy.types.ID, data_path: str, index: int = 0) -> list[float]:
    fc = find_fcurve(id_data, data_path, index)
    return [] if fc is None else [kp.co[0] for kp in fc.keyframe_points]


def frames_in_ranges(ranges: Iterable[Sequence[int]] | None, frame: int) -> bool:
    """True if ``frame`` lies in one of the inclusive ``[start, end]`` ranges."""
    return any(int(a) <= frame <= int(b) for a, b in (ranges or []))
