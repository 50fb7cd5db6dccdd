"""OpenCV <-> Blender camera conversion: known points projected both ways agree (numpy and real bpy)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from _blender_helpers import bl, bpy_addon  # noqa: F401  (fixtures; also makes fourlegs_addon importable)
from fourlegs_addon import convert
from fourlegs_engine.scene import Camera


def _camera(yaw: float, pitch: float, dist: float, focal: float, cx_off: float, cy_off: float,
            width: int = 64, height: int = 48) -> Camera:
    eye = dist * np.array([math.cos(yaw) * math.cos(pitch), math.sin(yaw) * math.cos(pitch), math.sin(pitch)])
    cam = Camera.look_at(eye + [0.3, -0.2, 0.1], (0.3, -0.2, 0.1), width=width, height=height, focal=focal)
    K = cam.K.copy()
    K[0, 2] += cx_off
    K[1, 2] += cy_off
    return Camera(K=K, w2c=cam.w2c, width=width, height=height)


def test_axis_flip_is_an_involution_and_rigid():
    c2w = _camera(0.4, 0.3, 5.0, 50.0, 0.0, 0.0).c2w
    blender = convert.opencv_to_blender_c2w(c2w)
    np.testing.assert_allclose(convert.blender_to_opencv_c2w(blender), c2w, atol=1e-12)
    R = blender[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    # Blender cameras look down their local -z; OpenCV cameras down +z: same world direction.
    np.testing.assert_allclose(-blender[:3, 2], c2w[:3, 2], atol=1e-12)
    # Blender's local +y is image-up, OpenCV's +y is image-down.
    np.testing.assert_allclose(blender[:3, 1], -c2w[:3, 1], atol=1e-12)


def test_scaled_blender_matrix_loses_its_scale():
    c2w = _camera(1.0, 0.2, 3.0, 40.0, 0.0, 0.0).c2w
    scaled = convert.opencv_to_blender_c2w(c2w) @ np.diag([2.0, 2.0, 2.0, 1.0])
    np.testing.assert_allclose(convert.blender_to_opencv_c2w(scaled), c2w, atol=1e-12)


@given(yaw=st.floats(-math.pi, math.pi), pitch=st.floats(-1.2, 1.2), dist=st.floats(0.5, 50.0),
       focal=st.floats(10.0, 400.0), cx_off=st.floats(-10.0, 10.0), cy_off=st.floats(-10.0, 10.0))
def test_projection_agrees_both_ways(yaw, pitch, dist, focal, cx_off, cy_off):
    """Engine (OpenCV) projection == projection through the converted Blender camera and lens."""
    cam = _camera(yaw, pitch, dist, focal, cx_off, cy_off)
    rng = np.random.default_rng(0)
    uv_target = rng.uniform([0, 0], [cam.width, cam.height], (16, 2))
    depth = rng.uniform(0.2, 3.0 * dist, 16)
    points = cam.unproject(uv_target, depth)  # known world points at known pixels
    lens = convert.intrinsics_to_blender(cam.K, cam.width, cam.height)
    K_back = convert.camera_intrinsics(lens.lens_mm, lens.sensor_width_mm, 24.0, "HORIZONTAL", cam.width,
                                       cam.height, shift_x=lens.shift_x, shift_y=lens.shift_y)
    np.testing.assert_allclose(K_back, cam.K, rtol=1e-10, atol=1e-9)
    uv_b, depth_b = convert.project_blender(points, convert.opencv_to_blender_c2w(cam.c2w), K_back)
    np.testing.assert_allclose(uv_b, uv_target, atol=1e-6 * max(1.0, dist))
    np.testing.assert_allclose(depth_b, depth, rtol=1e-9)
    uv_e, z_e = cam.project(points)
    np.testing.assert_allclose(uv_e, uv_target, atol=1e-6 * max(1.0, dist))


@pytest.mark.parametrize("fit,width,height", [("AUTO", 64, 48), ("AUTO", 48, 64), ("VERTICAL", 64, 48)])
def test_sensor_fit_rules(fit, width, height):
    K = convert.camera_intrinsics(50.0, 36.0, 24.0, fit, width, height)
    if fit == "AUTO":
        assert K[0, 0] == pytest.approx(50.0 * max(width, height) / 36.0)
    else:
        assert K[1, 1] == pytest.approx(50.0 * height / 24.0)
    assert K[0, 0] == pytest.approx(K[1, 1])
    assert (K[0, 2], K[1, 2]) == (width / 2, height / 2)


@pytest.mark.blender
def test_matches_blenders_own_projection(bl):
    """Points projected by Blender (world_to_camera_view) land where the engine camera puts them."""
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    from fourlegs_addon import importer

    cam = _camera(0.7, 0.35, 6.0, 55.0, 3.0, -2.0)
    scene = bl.context.scene
    scene.render.resolution_x, scene.render.resolution_y = cam.width, cam.height
    scene.render.resolution_percentage = 100
    obj = bl.data.objects.new("cam", bl.data.cameras.new("cam"))
    scene.collection.objects.link(obj)
    importer.apply_camera(obj, cam.c2w, cam.K, cam.width, cam.height)
    bl.context.view_layer.update()
    rng = np.random.default_rng(1)
    uv = rng.uniform([2, 2], [cam.width - 2, cam.height - 2], (10, 2))
    depth = rng.uniform(1.0, 12.0, 10)
    points = cam.unproject(uv, depth)
    for p, (u, v), d in zip(points, uv, depth):
        ndc = world_to_camera_view(scene, obj, Vector(p))
        assert ndc.x * cam.width == pytest.approx(u, abs=1e-3)
        assert (1.0 - ndc.y) * cam.height == pytest.approx(v, abs=1e-3)
        assert ndc.z == pytest.approx(d, rel=1e-5)


def test_srgb_to_linear_known_values_and_edges():
    c = np.array([0.0, 0.04045, 0.5, 1.0, -0.2, 1.5, np.nan, np.inf], np.float64)
    lin = convert.srgb_to_linear(c)
    np.testing.assert_allclose(lin[:4], [0.0, 0.04045 / 12.92, 0.21404114, 1.0], rtol=1e-5)
    np.testing.assert_allclose(lin[4:], [0.0, 1.0, 0.0, 1.0])  # clamped, NaN -> 0, never NaN/Inf out
    x = np.linspace(0, 1, 1001)
    assert np.all(np.diff(convert.srgb_to_linear(x)) >= 0)
    # continuous at the breakpoint (float64 reference of both branches)
    lo, hi = 0.04045 / 12.92, ((0.04045 + 0.055) / 1.055) ** 2.4
    assert abs(lo - hi) < 1e-7
