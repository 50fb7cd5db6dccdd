"""Quaternion and camera conversions against float64 hand computations (+ hypothesis properties)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from fourlegs_engine.errors import InputError
from fourlegs_engine.scene import Camera, CameraRig, normalize_quaternions, quaternion_to_matrix
from fourlegs_engine.scene.gaussians import normalize_quaternions_chunked

finite = st.floats(-10, 10, allow_nan=False, allow_infinity=False)
vec3 = st.tuples(finite, finite, finite)


def _rodrigues(axis: np.ndarray, angle: float) -> np.ndarray:
    """float64 rotation matrix from axis-angle, R = I + sin(a) [k]x + (1 - cos(a)) [k]x^2."""
    k = axis / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * kx + (1 - math.cos(angle)) * kx @ kx


def test_quaternion_hand_cases():
    s = math.sqrt(0.5)
    q = torch.tensor([[1, 0, 0, 0], [s, 0, 0, s], [0, 1, 0, 0], [s, s, 0, 0]], dtype=torch.float64)
    expected = np.array([np.eye(3),
                         [[0, -1, 0], [1, 0, 0], [0, 0, 1]],     # +90 deg about z
                         [[1, 0, 0], [0, -1, 0], [0, 0, -1]],    # 180 deg about x
                         [[1, 0, 0], [0, 0, -1], [0, 1, 0]]])    # +90 deg about x
    np.testing.assert_allclose(quaternion_to_matrix(q).numpy(), expected, atol=1e-15)
    # unnormalized input (any norm > 0) gives the same rotation
    np.testing.assert_allclose(quaternion_to_matrix(7.5 * q).numpy(), expected, atol=1e-14)


@given(axis=vec3.filter(lambda v: np.linalg.norm(v) > 1e-3), angle=st.floats(-math.pi, math.pi),
       scale=st.floats(1e-3, 1e3), sign=st.sampled_from([1.0, -1.0]))
def test_quaternion_matches_rodrigues(axis, angle, scale, sign):
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    q = sign * scale * np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * k])  # q and -q: same R
    R = quaternion_to_matrix(torch.tensor(q, dtype=torch.float64)).numpy()
    np.testing.assert_allclose(R, _rodrigues(k, angle), atol=1e-12)
    R32 = quaternion_to_matrix(torch.tensor(q, dtype=torch.float32)).numpy()
    np.testing.assert_allclose(R32, _rodrigues(k, angle), atol=2e-6)


def test_chunked_normalization_matches_and_names_index():
    rng = np.random.default_rng(1)
    q = rng.normal(size=(3, 5, 4)) * 4
    with pytest.warns(UserWarning):
        a = normalize_quaternions_chunked(q, chunk=4)  # chunk boundaries inside a timestep
    with pytest.warns(UserWarning):
        b = normalize_quaternions(q)
    np.testing.assert_array_equal(a, b)
    q[2, 1] = 0
    with pytest.raises(InputError, match=r"rot: zero-length quaternion at index \[2, 1\]"):
        normalize_quaternions_chunked(q, file="f.npz", field="rot", chunk=4)


def test_look_at_hand_computed():
    cam = Camera.look_at((0, -5, 0), (0, 0, 0), (0, 0, 1), width=64, height=48, focal=40.0)
    R = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], float)  # rows: right, down, forward
    np.testing.assert_allclose(cam.w2c[:3, :3], R, atol=1e-15)
    np.testing.assert_allclose(cam.w2c[:3, 3], [0, 0, 5], atol=1e-15)
    np.testing.assert_allclose(cam.center, [0, -5, 0], atol=1e-15)
    np.testing.assert_allclose(cam.forward, [0, 1, 0], atol=1e-15)
    # world point (1, 0, 2): camera coords (1, -2, 5) -> uv = (40*1/5 + 32, 40*(-2)/5 + 24)
    uv, z = cam.project(np.array([[1.0, 0.0, 2.0]]))
    np.testing.assert_allclose(uv, [[40.0, 8.0]], atol=1e-12)
    np.testing.assert_allclose(z, [5.0])
    np.testing.assert_allclose(cam.unproject(uv, z), [[1.0, 0.0, 2.0]], atol=1e-12)
    assert cam.fov_x == pytest.approx(2 * math.atan(32 / 40)) and cam.fov_y == pytest.approx(2 * math.atan(24 / 40))
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = R.T, [0, -5, 0]
    np.testing.assert_allclose(cam.c2w, c2w, atol=1e-15)


def test_look_at_fov():
    cam = Camera.look_at((1, 2, 3), (0, 0, 0), width=320, height=180, fov_y=math.radians(60))
    assert cam.fov_y == pytest.approx(math.radians(60), abs=1e-12)
    assert cam.fy == pytest.approx(90 / math.tan(math.radians(30)))


@pytest.mark.parametrize("eye", [(0, 0, 5), (0, 0, -5), (0, 0, 1e-7)])
def test_look_at_up_parallel_to_view_is_a_valid_rotation(eye):
    cam = Camera.look_at(eye, (0, 0, 0), (0, 0, 1), width=32, height=32).validate()
    R = cam.w2c[:3, :3]
    assert np.isfinite(cam.w2c).all()
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(cam.forward, -np.sign(eye[2]) * np.array([0, 0, 1.0]), atol=1e-12)
    uv, _ = cam.project(np.zeros((1, 3)))
    np.testing.assert_allclose(uv, [[16, 16]], atol=1e-9)


def test_look_at_coincident_eye_target():
    with pytest.raises(InputError, match="eye and target coincide"):
        Camera.look_at((1, 1, 1), (1, 1, 1), width=8, height=8)


@given(eye=vec3, target=vec3, up=vec3, f=st.floats(5, 2000), u=st.floats(0, 64), v=st.floats(0, 48),
       depth=st.floats(0.05, 50))
def test_camera_properties(eye, target, up, f, u, v, depth):
    if np.linalg.norm(np.subtract(target, eye)) < 1e-3 or np.linalg.norm(up) < 1e-6:
        return
    cam = Camera.look_at(eye, target, up, width=64, height=48, focal=f).validate()
    np.testing.assert_allclose(cam.c2w @ cam.w2c, np.eye(4), atol=1e-9)
    world = cam.unproject(np.array([[u, v]]), np.array([depth]))
    uv, z = cam.project(world)
    np.testing.assert_allclose(uv, [[u, v]], atol=1e-6 * max(1.0, f))
    np.testing.assert_allclose(z, [depth], rtol=1e-9, atol=1e-9)
    # the target projects to the image centre, in front of the camera
    uv_t, z_t = cam.project(np.array([target]))
    np.testing.assert_allclose(uv_t, [[32, 24]], atol=1e-6 * max(1.0, f))
    assert z_t[0] > 0
    # world up never points down in the image (unless parallel to the view direction)
    fwd = cam.forward
    up_n = np.asarray(up) / np.linalg.norm(up)
    if abs(np.dot(fwd, up_n)) < 0.99:
        assert np.dot(cam.w2c[1, :3], up_n) <= 1e-9


@pytest.mark.parametrize("factor", [0.5, 2.0, 0.25])
def test_scaled_camera(factor):
    cam = Camera.look_at((3, 1, 2), (0, 0, 0), width=64, height=48, focal=50.0)
    small = cam.scaled(factor)
    assert (small.width, small.height) == (64 * factor, 48 * factor)
    pts = np.array([[0.1, 0.2, 0.3], [-0.5, 0.4, 0.0]])
    np.testing.assert_allclose(small.project(pts)[0], factor * cam.project(pts)[0], atol=1e-12)
    assert small.fov_x == pytest.approx(cam.fov_x) and small.fov_y == pytest.approx(cam.fov_y)
    np.testing.assert_array_equal(small.w2c, cam.w2c)
    with pytest.raises(InputError, match="resolution scale must be positive"):
        cam.scaled(0)


def test_validate_bad_cameras():
    good = Camera.look_at((3, 0, 0), (0, 0, 0), width=8, height=8, name="c7")
    K = good.K.copy()
    K[0, 0] = 0
    with pytest.raises(InputError, match=r"f\.json: camera\[c7\]\.K: focal length must be positive"):
        Camera(K, good.w2c, 8, 8, name="c7").validate("f.json")
    w2c = good.w2c.copy()
    w2c[:3, :3] *= 2
    with pytest.raises(InputError, match=r"camera\[c7\]\.w2c: is not a rigid transform"):
        Camera(good.K, w2c, 8, 8, name="c7").validate()
    with pytest.raises(InputError, match="near < far"):
        Camera(good.K, good.w2c, 8, 8, near=0.0).validate()


def test_camera_dict_and_rig_round_trip():
    cams = [Camera.look_at((3, i, 1), (0, 0, 0), width=16, height=12, name=f"c{i}") for i in range(3)]
    rig = CameraRig.static(cams[:2], cams[2:], 4)
    back = CameraRig.from_dict(rig.to_dict())
    assert back.num_timesteps == 4 and back.num_cameras("train") == 2 and back.num_cameras("test") == 1
    np.testing.assert_array_equal(back.find("c2", 3).w2c, cams[2].w2c)
    with pytest.raises(InputError, match="no camera named 'x'"):
        back.find("x")
