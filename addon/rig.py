"""The bullet-time orbit as a rig an editor can change: a pivot empty at the action centre, a camera
parented to it, and two custom properties on the pivot that drive them.

- ``radius`` (scene units): the camera's horizontal distance from the pivot (a driver scales its offset);
- ``speed`` (1 = as planned): how fast the pivot sweeps the planned arc ``arc_deg``; the eased turn
  ``arc * (0.5 - 0.5 cos(pi * clamp(speed * (frame - f0) / (f1 - f0))))`` is the planner's
  ``ease_in_out_sine`` orbit exactly at speed 1, and holds at the end of the arc when it is done early.

The shot's timeline marker is bound to the rig camera (Blender switches the active camera at bound
markers), the other shots' markers to the highlight camera. The planner's orbit is rigid (the camera's
framing, roll and elevation are kept), which parenting to a turning pivot reproduces.
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


def can_rig(shot: dict[str, Any], centre: Optional[Any]) -> bool:
    """Whether the shot is a planner orbit the rig reproduces: sine-eased, constant radius and height."""
    p = shot.get("params") or {}
    return (centre is not None and str(shot.get("effect")) == "bullet_time" and "arc_deg" in p
            and p.get("easing", "ease_in_out_sine") == "ease_in_out_sine"
            and float(p.get("radius_scale", 1.0)) == 1.0 and float(p.get("height_scale", 1.0)) == 1.0 and p.get("rigid", True)
            and int(shot["frame_end"]) > int(shot["frame_start"]) and len(shot["camera_keys"]) >= 1)


def _driver(target: bpy.types.ID, data_path: str, index: int, expression: str, pivot: bpy.types.Object,
            props: tuple[str, ...]) -> None:
    fc = target.driver_add(data_path, index)
    drv = fc.driver
    drv.type = "SCRIPTED"
    for name in props:
        var = drv.variables.new()
        var.name, var.type = name, "SINGLE_PROP"
        var.targets[0].id = pivot
        var.targets[0].data_path = f'["{name}"]'
    drv.expression = expression


def build_orbit_rig(scene: bpy.types.Scene, shot: dict[str, Any], centre, lens_mm: float, sensor_width_mm: float,
                    tag: str) -> bpy.types.Object:
    """Create the pivot + camera of an orbit shot; returns the camera (tagged ``tag`` like the pivot)."""
    centre = np.asarray(centre, np.float64)
    keys = sorted(shot["camera_keys"], key=lambda k: int(k["frame"]))
    start = convert.opencv_to_blender_c2w(np.asarray(keys[0]["c2w"], np.float64))
    f0, f1 = int(shot["frame_start"]), int(shot["frame_end"])
    offset = start[:3, 3] - centre
    radius = float(math.hypot(offset[0], offset[1]))

    pivot = bpy.data.objects.new(PIVOT_NAME, None)
    pivot.empty_display_type = "SPHERE"
    pivot.empty_display_size = max(radius * 0.05, 0.05)
    pivot.location = centre.tolist()
    pivot[tag] = True
    pivot["radius"] = radius
    pivot["speed"] = 1.0
    pivot["arc_deg"] = float(shot["params"]["arc_deg"])
    ui = pivot.id_properties_ui("radius")
    ui.update(min=0.0, soft_max=max(radius * 4, 1.0), description="Orbit radius (scene units)")
    pivot.id_properties_ui("speed").update(min=0.0, soft_max=4.0, description="1 = as planned; 2 = the arc "
                                                                              "in half the time, then hold")
    pivot.id_properties_ui("arc_deg").update(description="Degrees the orbit turns (counter-clockwise from above)")
    scene.collection.objects.link(pivot)

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

    span = float(f1 - f0)
    progress = f"min(max(speed * (frame - {f0}) / {span}, 0.0), 1.0)"
    _driver(pivot, "rotation_euler", 2, f"arc_deg * pi / 180.0 * (0.5 - 0.5 * cos(pi * {progress}))", pivot,
            ("arc_deg", "speed"))
    if radius > 1e-9:
        for axis in (0, 1):
            _driver(cam, "location", axis, f"radius * {float(offset[axis] / radius)!r}", pivot, ("radius",))
    return cam


def bind_markers(scene: bpy.types.Scene, marker_names: list[str], cameras: list[bpy.types.Object]) -> None:
    """Bind each shot marker to the camera that films the shot (Blender switches cameras there)."""
    for name, cam in zip(marker_names, cameras):
        marker = scene.timeline_markers.get(name)
        if marker is not None:
            marker.camera = cam
