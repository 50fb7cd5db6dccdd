"""The scene's cameras as Blender cameras, and a camera for a scene that has none."""
from __future__ import annotations

import math
from typing import Any

import bpy
import numpy as np

from . import convert

CAMERA_COLLECTION_SUFFIX = " Cameras"
VIEW_CAMERA_NAME = "4-LEGS View"
# Calibrated cameras have fx and fy a fraction of a percent apart; Blender cannot write a multilayer EXR with
# non-square pixels, so such cameras get square pixels and the geometric-mean focal length.
SQUARE_PIXEL_TOLERANCE = 0.01


def apply_camera(cam_obj: bpy.types.Object, c2w_opencv: np.ndarray, K: np.ndarray, width: int,
                 height: int, near: float = 0.01, far: float = 100.0) -> None:
    """Place a Blender camera object to match an OpenCV camera."""
    from mathutils import Matrix

    cam_obj.matrix_world = Matrix(convert.opencv_to_blender_c2w(c2w_opencv).tolist())
    lens = convert.intrinsics_to_blender(K, width, height)
    data = cam_obj.data
    data.sensor_fit = "HORIZONTAL"
    data.sensor_width = lens.sensor_width_mm
    data.lens = lens.lens_mm
    data.shift_x, data.shift_y = lens.shift_x, lens.shift_y
    data.clip_start, data.clip_end = near, far


def near_square_pixels(K: np.ndarray, tolerance: float = SQUARE_PIXEL_TOLERANCE) -> np.ndarray:
    """(3,3) ``K`` with fx = fy = sqrt(fx*fy) when they differ by at most ``tolerance`` (relative), else ``K``."""
    K = np.asarray(K, dtype=np.float64)
    fx, fy = K[0, 0], K[1, 1]
    if fx <= 0 or fy <= 0 or abs(fx / fy - 1.0) > tolerance:
        return K
    out = K.copy()
    out[0, 0] = out[1, 1] = math.sqrt(fx * fy)
    return out


def import_cameras(context_scene: bpy.types.Scene, scene: Any, collection: bpy.types.Collection) -> list:
    """The scene's cameras at timestep 0 (train, then test) as Blender cameras in a child collection.

    The render's pixel aspect is the first camera's (one value per Blender scene); nearly square pixels
    become square (:func:`near_square_pixels`)."""
    cams = scene.cameras.cameras(0, "all") if scene.cameras.num_timesteps else []
    if not cams:
        return []
    sub = bpy.data.collections.new(collection.name + CAMERA_COLLECTION_SUFFIX)
    collection.children.link(sub)
    out = []
    for i, cam in enumerate(cams):
        data = bpy.data.cameras.new(cam.name or f"cam{i:02d}")
        obj = bpy.data.objects.new(cam.name or f"cam{i:02d}", data)
        obj["fourlegs_camera"] = cam.name or f"cam{i:02d}"
        sub.objects.link(obj)
        apply_camera(obj, cam.c2w, near_square_pixels(cam.K), cam.width, cam.height, cam.near, min(cam.far, 1000.0))
        out.append(obj)
    render = context_scene.render
    render.resolution_x, render.resolution_y = cams[0].width, cams[0].height
    render.resolution_percentage = 100
    lens = convert.intrinsics_to_blender(near_square_pixels(cams[0].K), cams[0].width, cams[0].height)
    render.pixel_aspect_x, render.pixel_aspect_y = lens.pixel_aspect_x, lens.pixel_aspect_y
    if context_scene.camera is None:
        context_scene.camera = out[0]
    return out


def add_view_camera(context_scene: bpy.types.Scene, means: np.ndarray, collection: bpy.types.Collection,
                    width: int = 1280, height: int = 720) -> bpy.types.Object:
    """A camera that sees every point of ``means`` (N,3) from the front-left and above (a scene without
    cameras, e.g. one PLY file), made the scene's camera."""
    from fourlegs_engine import api

    pts = np.asarray(means, np.float64).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    lo, hi = (np.percentile(pts, 1, axis=0), np.percentile(pts, 99, axis=0)) if len(pts) else (-np.ones(3), np.ones(3))
    centre, radius = (lo + hi) / 2.0, max(float(np.linalg.norm(hi - lo)) / 2.0, 1e-3)
    fov_y = math.radians(40.0)
    distance = radius / math.sin(fov_y / 2.0)
    eye = centre + distance * np.array([0.6, -0.7, 0.4]) / np.linalg.norm([0.6, -0.7, 0.4])
    cam = api.Camera.look_at(tuple(eye), tuple(centre), width=width, height=height, fov_y=fov_y,
                             far=max(distance * 4.0, 100.0))
    data = bpy.data.cameras.new(VIEW_CAMERA_NAME)
    obj = bpy.data.objects.new(VIEW_CAMERA_NAME, data)
    collection.objects.link(obj)
    apply_camera(obj, cam.c2w, cam.K, width, height, cam.near, cam.far)
    render = context_scene.render
    render.resolution_x, render.resolution_y, render.resolution_percentage = width, height, 100
    context_scene.camera = obj
    return obj
