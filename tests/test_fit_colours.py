"""The fit's colours expressed in the average training camera's response (``average_camera_colours``)."""
from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from fourlegs_engine.fit.model import average_camera_colours


def _opaque_weights(rng: np.random.Generator, pixels: int, gaussians: int) -> np.ndarray:
    """(P, N) blending weights of pixels whose accumulated opacity is 1."""
    w = rng.random((pixels, gaussians)) ** 3
    return w / w.sum(1, keepdims=True)


def test_training_cameras_see_the_same_corrected_render_and_the_average_camera_sees_the_colours():
    rng = np.random.default_rng(0)
    colors = rng.uniform(0.05, 0.9, (40, 3))
    cam_m = rng.normal(-0.05, 0.08, (27, 3))
    cam_c = rng.normal(0.004, 0.015, (27, 3))
    new_colors, new_m, new_c = average_camera_colours(colors, cam_m, cam_c)
    assert new_colors.dtype == new_m.dtype == new_c.dtype == np.float32
    np.testing.assert_allclose(new_m.mean(0), 0.0, atol=1e-6)
    weights = _opaque_weights(rng, 500, 40)
    for c in range(27):
        before = np.exp(cam_m[c]) * (weights @ colors) + cam_c[c]
        after = np.exp(new_m[c].astype(np.float64)) * (weights @ new_colors.astype(np.float64)) + new_c[c]
        np.testing.assert_allclose(after, before, atol=2e-6)
    # a camera with the average correction renders the new colours as they are
    average = np.exp(cam_m.mean(0)) * (weights @ colors) + cam_c.mean(0)
    np.testing.assert_allclose(weights @ new_colors.astype(np.float64), average, atol=2e-6)


def test_identity_corrections_change_nothing_and_no_cameras_pass_through():
    colors = np.array([[0.2, 0.5, 0.9], [1.0, 0.0, 0.3]])
    zeros = np.zeros((5, 3))
    new_colors, new_m, new_c = average_camera_colours(colors, zeros, zeros)
    np.testing.assert_array_equal(new_colors, colors.astype(np.float32))
    np.testing.assert_array_equal(new_m, zeros)
    np.testing.assert_array_equal(new_c, zeros)
    same, m0, c0 = average_camera_colours(colors, np.zeros((0, 3)), np.zeros((0, 3)))
    np.testing.assert_array_equal(same, colors.astype(np.float32))
    assert m0.shape == c0.shape == (0, 3)


@settings(max_examples=60, deadline=None)
@given(colors=arrays(np.float64, (7, 3), elements=st.floats(0.0, 1.0)),
       cam_m=arrays(np.float64, (4, 3), elements=st.floats(-8.0, 8.0)),
       cam_c=arrays(np.float64, (4, 3), elements=st.floats(-2.0, 2.0)))
def test_extreme_corrections_keep_colours_in_range_and_finite(colors, cam_m, cam_c):
    new_colors, new_m, new_c = average_camera_colours(colors, cam_m, cam_c)
    assert np.isfinite(new_colors).all() and np.isfinite(new_m).all() and np.isfinite(new_c).all()
    assert new_colors.min() >= 0.0 and new_colors.max() <= 1.0
    np.testing.assert_allclose(new_m.mean(0), 0.0, atol=1e-5)


def test_per_timestep_colours_are_corrected_timestep_by_timestep_alike():
    rng = np.random.default_rng(3)
    colors = rng.random((4, 50, 3)).astype(np.float32)
    cam_m, cam_c = rng.normal(0, 0.3, (6, 3)), rng.normal(0, 0.05, (6, 3))
    whole, m, c = average_camera_colours(colors, cam_m, cam_c)
    assert whole.shape == colors.shape and whole.dtype == np.float32
    for t in range(4):
        one, m_t, c_t = average_camera_colours(colors[t], cam_m, cam_c)
        np.testing.assert_array_equal(whole[t], one)
        np.testing.assert_array_equal(m, m_t)
        np.testing.assert_array_equal(c, c_t)
