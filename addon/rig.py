"""The bullet-time orbit as a rig an editor can change: a pivot empty at the action centre, a camera
parented to it, and custom properties on the pivot that drive them.

- ``speed`` (1 = as planned): how fast the pivot sweeps the planned arc ``arc_deg``; the eased turn
  ``arc * (0.5 - 0.5 cos(pi * clamp(speed * (frame - f0) / (f1 - f0))))`` is the planner's
  ``ease_in_out_sine`` orbit exactly at speed 1, and holds at the end of the arc when it is done early;
- a rigid orbit (the planner's without an action region): ``radius`` (scene units), the camera's
  horizontal distance from the pivot; the camera's framing, roll and elevation are kept, which
  parenting to a turning pivot reproduces;
- a framed orbit (the planner's with an action region, as the main job plans): the camera moves from
  the start's distance and elevation to ``distance`` and ``elevation_deg`` over the first sixth of the
  arc (smoothstep), always aimed level at the pivot (a Track To constraint), its lens scaled by
  ``lens_scale`` over the same ramp.

``start_frame``/``end_frame`` on the pivot are the shot's frames (moving the shot's marker retimes
them, see ``retime``). The shot's timeline marker is bound to the rig camera (Blender switches the
active camera at bound markers), the other shots' markers to the highlight camera.
"""
from __future__ import annotations

import math
from typing import Any, Optional

import bpy
import numpy as np
from mathutils import Matrix

from . import convert

PIVOT_NAME = "4-LEGS Orbit Pivot"
CAMERA_NAME = "4-LEGS Orbit Camera"


UP = np.array([0.0, 0.0, 1.0])


def _is_orbit(shot: dict[str, Any], centre: Optional[Any]) -> bool:
    p = shot.get("params") or {}
    return (centre is not None and str(shot.get("effect")) == "bullet_time" and "arc_deg" in p
            and p.get("easing", "ease_in_out_sine") == "ease_in_out_sine"
            and int(shot["frame_end"]) > int(shot["frame_start"]) and len(shot["camera_keys"]) >= 1)


def can_rig(shot: dict[str, Any], centre: Optional[Any]) -> bool:
    """Whether the shot is a rigid planner orbit the rig reproduces: sine-eased, constant radius and height."""
    p = shot.get("params") or {}
    return (_is_orbit(shot, centre) and float(p.get("radius_scale", 1.0)) == 1.0
            and float(p.get("height_scale", 1.0)) == 1.0 and p.get("rigid", True))


def can_rig_framed(shot: dict[str, Any], up: Optional[Any] = None) -> bool:
    """Whether the shot is a framed planner orbit (about +z) the framed rig reproduces."""
    p = shot.get("params") or {}
    return (_is_orbit(shot, p.get("centre")) and p.get("rigid") is False
            and all(k in p for k in ("arc_deg_used", "elevation_deg", "lens_scale", "radius", "height"))
            and (up is None or np.allclose(np.asarray(up, np.float64), UP)))


def _driver(target: bpy.types.ID, data_path: str, index: int, expression: str, pivot: bpy.types.Object,
            props: dict[str, str]) -> None:
    """A scripted driver on ``target`` reading the pivot's custom properties ``props`` (variable -> property);
    Blender keeps 256 characters of an expression, hence the terse ones.

    Every driver computes the shot's progress itself (no driver reads another driver's result, whose
    evaluation order Blender does not promise); ``clamp`` and ``smoothstep`` keep it a simple expression,
    evaluated without Python (files opened with scripts disabled still move)."""
    if len(expression) > 255:
        raise ValueError(f"driver expression of {len(expression)} characters (Blender keeps 255): {expression}")
    fc = target.driver_add(data_path, index) if index >= 0 else target.driver_add(data_path)
    drv = fc.driver
    drv.type = "SCRIPTED"
    for var_name, prop in props.items():
        var = drv.variables.new()
        var.name, var.type = var_name, "SINGLE_PROP"
        var.targets[0].id = pivot
        var.targets[0].data_path = f'["{prop}"]'
    drv.expression = expression


#: eased progress through the shot (the planner's ease_in_out_sine at speed 1) and the framed orbit's ramp
EASED = "(.5-.5*cos(pi*clamp(s*(frame-a)/max(b-a,1),0,1)))"
RAMP = f"smoothstep(0,1,6*{EASED})"
TIMING = {"s": "speed", "a": "start_frame", "b": "end_frame"}


def _g(value: float) -> str:
    """A float for a driver expression (Blender keeps 256 characters of one)."""
    return f"{float(value):.7g}"


def _pivot(scene: bpy.types.Scene, centre: np.ndarray, shot: dict[str, Any], arc_deg: float, size: float,
           tag: str) -> bpy.types.Object:
    """The pivot empty at ``centre`` with the timing properties (speed, arc, the shot's frames)."""
    pivot = bpy.data.objects.new(PIVOT_NAME, None)
    pivot.empty_display_type = "SPHERE"
    pivot.empty_display_size = max(size * 0.05, 0.05)
    pivot.location = centre.tolist()
    pivot[tag] = True
    pivot["speed"] = 1.0
    pivot["arc_deg"] = float(arc_deg)
    pivot["start_frame"], pivot["end_frame"] = float(shot["frame_start"]), float(shot["frame_end"])
    pivot.id_properties_ui("speed").update(min=0.0, soft_max=4.0, description="1 = as planned; 2 = the arc "
                                                                              "in half the time, then hold")
    pivot.id_properties_ui("arc_deg").update(description="Degrees the orbit turns (counter-clockwise from above)")
    for name in ("start_frame", "end_frame"):
        pivot.id_properties_ui(name).update(description="The shot's frames (moving its marker retimes them)")
    scene.collection.objects.link(pivot)
    return pivot


def _turn(pivot: bpy.types.Object) -> None:
    """The pivot turns ``arc_deg`` over the shot, eased."""
    _driver(pivot, "rotation_euler", 2, f"t * pi / 180.0 * {EASED}", pivot, {"t": "arc_deg", **TIMING})


def build_orbit_rig(scene: bpy.types.Scene, shot: dict[str, Any], centre, lens_mm: float, sensor_width_mm: float,
                    tag: str) -> bpy.types.Object:
    """Create the pivot + camera of an orbit shot; returns the camera (tagged ``tag`` like the pivot)."""
    centre = np.asarray(centre, np.float64)
    keys = sorted(shot["camera_keys"], key=lambda k: int(k["frame"]))
    start = convert.opencv_to_blender_c2w(np.asarray(keys[0]["c2w"], np.float64))
    f0, f1 = int(shot["frame_start"]), int(shot["frame_end"])
    offset = start[:3, 3] - centre
    radius = float(math.hypot(offset[0], offset[1]))

    pivot = _pivot(scene, centre, shot, float(shot["params"]["arc_deg"]), radius, tag)
    pivot["radius"] = radius
    pivot.id_properties_ui("radius").update(min=0.0, soft_max=max(radius * 4, 1.0),
                                            description="Orbit radius (scene units)")

    data = bpy.data.cameras.new(CAMERA_NAME)
    data[tag] = True
    data.sensor_fit = "HORIZONTAL"
    data.sensor_width = sensor_width_mm
    data.lens = lens_mm
    cam = bpy.data.objects.new(CAMERA_NAME, data)
    cam[tag] = True
    cam.parent = pivot
    local = start.copy()
    local[:3, 3] = offset
    cam.matrix_basis = Matrix(local.tolist())
    cam.rotation_mode = "XYZ"
    scene.collection.objects.link(cam)

    _turn(pivot)
    if radius > 1e-9:
        for axis in (0, 1):
            _driver(cam, "location", axis, f"radius * {float(offset[axis] / radius)!r}", pivot, {"radius": "radius"})
    return cam


def build_framed_orbit_rig(scene: bpy.types.Scene, shot: dict[str, Any], lens_mm: float, sensor_width_mm: float,
                           tag: str) -> bpy.types.Object:
    """Create the pivot + camera of a framed orbit shot (see the module notes); returns the camera."""
    p = shot["params"]
    centre = np.asarray(p["centre"], np.float64)
    keys = sorted(shot["camera_keys"], key=lambda k: int(k["frame"]))
    start = convert.opencv_to_blender_c2w(np.asarray(keys[0]["c2w"], np.float64))
    offset = start[:3, 3] - centre
    horizontal = float(math.hypot(offset[0], offset[1]))
    d0, el0 = float(np.linalg.norm(offset)), math.atan2(float(offset[2]), horizontal)
    ux, uy = (offset[0] / horizontal, offset[1] / horizontal) if horizontal > 1e-9 else (1.0, 0.0)
    distance = float(math.hypot(p["radius"], p["height"]))

    pivot = _pivot(scene, centre, shot, float(p["arc_deg_used"]), distance, tag)
    pivot["distance"], pivot["elevation_deg"] = distance, float(p["elevation_deg"])
    pivot["lens_scale"] = float(p["lens_scale"])
    pivot.id_properties_ui("distance").update(min=0.0, soft_max=max(distance * 4, 1.0),
                                              description="Distance from the action at the end of the first "
                                                          "sixth of the orbit (scene units)")
    pivot.id_properties_ui("elevation_deg").update(min=-89.0, max=89.0, description="Elevation above the action")
    _turn(pivot)

    data = bpy.data.cameras.new(CAMERA_NAME)
    data[tag] = True
    data.sensor_fit, data.sensor_width, data.lens = "HORIZONTAL", sensor_width_mm, lens_mm
    cam = bpy.data.objects.new(CAMERA_NAME, data)
    cam[tag] = True
    cam.parent = pivot
    scene.collection.objects.link(cam)
    dist = f"({_g(d0)}+(D-{_g(d0)})*{RAMP})"
    elevation = f"({_g(el0)}+(L*pi/180-{_g(el0)})*{RAMP})"
    props = {"D": "distance", "L": "elevation_deg", **TIMING}
    for axis, factor in ((0, ux), (1, uy)):
        _driver(cam, "location", axis, f"{dist}*cos({elevation})*{_g(factor)}", pivot, props)
    _driver(cam, "location", 2, f"{dist}*sin({elevation})", pivot, props)
    _driver(data, "lens", -1, f"{_g(lens_mm)}*k**{RAMP}", pivot, {"k": "lens_scale", **TIMING})
    aim = cam.constraints.new("TRACK_TO")
    aim.target, aim.track_axis, aim.up_axis = pivot, "TRACK_NEGATIVE_Z", "UP_Y"
    return cam


def bind_markers(scene: bpy.types.Scene, marker_names: list[str], cameras: list[bpy.types.Object]) -> None:
    """Bind each shot marker to the camera that films the shot (Blender switches cameras there)."""
    for name, cam in zip(marker_names, cameras):
        marker = scene.timeline_markers.get(name)
        if marker is not None:
            marker.camera = cam
