"""Moving a shot's timeline marker retimes the shot, and every shot after it (a ripple edit).

Generate Highlight records the frame each shot's marker was made at (``scene["fourlegs_shot_frames"]``).
When a marker is found elsewhere (checked on every depsgraph update and frame change, and before a
render) the generated keys from the shot's old start on move by the same number of frames: the
highlight camera's location, rotation and lens, the scene time (so bullet-time and slow motion follow),
the desaturation weight, the orbit rig's ``start_frame``/``end_frame``, the later markers, the stored
plan (its passes, so relevancy is computed where the shot now is) and the end of the timeline. Moving
a marker earlier drops the previous shot's keys it now covers; moving it later holds the previous
shot's last key until the cut.
"""
from __future__ import annotations

import json
from typing import Any

import bpy
from bpy.app.handlers import persistent

from . import compositor, keyframes

TEXT_KEYS = ("frame", "frame_start", "frame_end")


def moved_marker(scene: bpy.types.Scene) -> tuple[str, int, int] | None:
    """(marker name, recorded frame, frame now) of the earliest shot marker that moved, or None."""
    recorded = scene.get(keyframes.SHOT_FRAMES_KEY)
    if not recorded:
        return None
    for name, frame in sorted(recorded.items(), key=lambda kv: kv[1]):
        marker = scene.timeline_markers.get(name)
        if marker is not None and marker.frame != int(frame):
            return name, int(frame), int(marker.frame)
    return None


def _animated(scene: bpy.types.Scene) -> list[tuple[Any, list]]:
    """(datablock, its F-curves) of everything Generate keyed: cameras and their lenses, scene time,
    desaturation weight."""
    out = []
    for obj in bpy.data.objects:
        if obj.get(keyframes.GENERATED_KEY) and obj.animation_data is not None:
            out.append(list(keyframes.fcurves_of(obj)))
            if obj.type == "CAMERA":
                out.append(list(keyframes.fcurves_of(obj.data)))
    fc = keyframes.find_fcurve(scene, keyframes.TIMESTEP_PATH)
    if fc is not None:
        out.append([fc])
    tree = compositor.compositor_tree(scene)
    if tree is not None and tree.get(keyframes.GENERATED_KEY):
        out.append(list(keyframes.fcurves_of(tree)))
    return [fc for curves in out for fc in curves]


def _shift_fcurve(fc, start: int, delta: int) -> None:
    points = fc.keyframe_points
    if delta < 0:  # the moved shot now starts inside the previous one: those keys of it go
        for kp in [kp for kp in points if start + delta <= kp.co[0] < start][::-1]:
            points.remove(kp)
    else:  # the previous shot's last key holds until the cut
        before = [kp for kp in points if kp.co[0] < start]
        if before:
            before[-1].interpolation = "CONSTANT"
    for kp in points:
        if kp.co[0] >= start:
            kp.co[0] += delta
            kp.handle_left[0] += delta
            kp.handle_right[0] += delta
    fc.update()


def _shift_plan(plan: dict[str, Any], start: int, delta: int) -> dict[str, Any]:
    def shift(frame):
        return int(frame) + delta if int(frame) >= start else int(frame)

    def walk(value):
        if isinstance(value, dict):
            return {k: shift(v) if k in TEXT_KEYS and isinstance(v, (int, float)) else walk(v) for k, v in value.items()}
        if isinstance(value, list):
            return [walk(v) for v in value]
        return value

    out = walk(plan)
    out["passes"] = {name: [[shift(a), shift(b)] for a, b in ranges] for name, ranges in (plan.get("passes") or {}).items()}
    for effect in ("desaturate", "blur"):
        block = plan.get(effect)
        if block:
            out[effect] = dict(block, ranges=[[shift(a), shift(b)] for a, b in block.get("ranges", [])],
                               weights={str(shift(f)): w for f, w in (block.get("weights") or {}).items()})
    return out


def ripple(scene: bpy.types.Scene, start: int, delta: int, moved: str) -> None:
    """Move everything Generate made from frame ``start`` on by ``delta`` frames (``moved`` is the marker
    already at its new frame)."""
    from .render_engine import PLAN_TEXT_NAME

    for fc in _animated(scene):
        _shift_fcurve(fc, start, delta)
    for obj in bpy.data.objects:
        if obj.get(keyframes.GENERATED_KEY) and "start_frame" in obj and obj["start_frame"] >= start:
            obj["start_frame"] += delta
            obj["end_frame"] += delta
            obj.update_tag()  # its drivers read these: evaluate them again
    recorded = dict(scene[keyframes.SHOT_FRAMES_KEY])
    for name, frame in recorded.items():
        if int(frame) >= start:
            recorded[name] = int(frame) + delta
            marker = scene.timeline_markers.get(name)
            if marker is not None and name != moved:
                marker.frame = int(frame) + delta
    scene[keyframes.SHOT_FRAMES_KEY] = recorded
    text = bpy.data.texts.get(PLAN_TEXT_NAME)
    if text is not None:
        plan = _shift_plan(json.loads(text.as_string()), start, delta)
        text.clear()
        text.write(json.dumps(plan, indent=1))
    scene.frame_end = max(scene.frame_start, scene.frame_end + delta)


def sync(scene: bpy.types.Scene) -> int:
    """Apply every marker move found; returns how many shots were retimed."""
    count = 0
    while (found := moved_marker(scene)) is not None and count < 64:
        name, old, new = found
        ripple(scene, old, new - old, name)
        count += 1
    return count


@persistent
def on_change(scene: bpy.types.Scene, depsgraph=None) -> None:
    if scene.get(keyframes.SHOT_FRAMES_KEY):
        sync(scene)


def register() -> None:
    for handlers in (bpy.app.handlers.depsgraph_update_post, bpy.app.handlers.frame_change_pre):
        if on_change not in handlers:
            handlers.append(on_change)


def unregister() -> None:
    for handlers in (bpy.app.handlers.depsgraph_update_post, bpy.app.handlers.frame_change_pre):
        if on_change in handlers:
            handlers.remove(on_change)
