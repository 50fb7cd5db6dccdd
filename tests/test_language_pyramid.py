"""Crop pyramid geometry and per-pixel interpolation against float64 references."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from fourlegs_engine.errors import InputError
from fourlegs_engine.language.frames import crop_means
from fourlegs_engine.language.pyramid import (CLIP_MEAN, crop_layout, interpolate_points,
                                              pixel_features, pyramid_ratios, resize_crops, scale_crops,
                                              tube_indices, upsample_to_pixels)


def test_crop_count_matches_the_paper_setup():
    layout = crop_layout(640, 360, pyramid_ratios(0.15, 0.6, 5))
    assert [s.kernel for s in layout.scales] == [54, 94, 135, 175, 216]
    assert [s.stride for s in layout.scales] == [27, 47, 67, 87, 108]
    assert [s.num_crops for s in layout.scales] == [336, 112, 60, 40, 24]
    assert layout.num_crops == 572
    assert pyramid_ratios(0.15, 0.6, 5)[1] == pytest.approx(0.2625)


def test_animal_ratios_and_bad_ratios():
    layout = crop_layout(640, 360, pyramid_ratios(0.4, 0.95, 5))
    assert layout.scales[-1].kernel == int(0.95 * 360)
    with pytest.raises(InputError):
        pyramid_ratios(0.6, 0.15, 5)
    with pytest.raises(InputError):
        crop_layout(64, 4, [0.15])  # 0 px crops


def test_tube_repeats_edge_frames():
    assert tube_indices(0, 10) == [0, 0, 0, 0, 0, 1, 2, 3]
    assert tube_indices(5, 10) == [1, 2, 3, 4, 5, 6, 7, 8]
    assert tube_indices(9, 10) == [5, 6, 7, 8, 9, 9, 9, 9]
    assert tube_indices(0, 1) == [0] * 8


def test_crops_are_zero_padded_windows_of_the_frames():
    rng = np.random.default_rng(0)
    frames = rng.uniform(size=(2, 3, 20, 37))
    layout = crop_layout(37, 20, [0.3, 0.55])
    for g in layout.scales:
        crops = scale_crops(torch.from_numpy(frames), g).numpy()
        padded = np.pad(frames, ((0, 0), (0, 0), (g.padding,) * 2, (g.padding,) * 2))
        for iy in range(g.ny):
            for ix in range(g.nx):
                y0, x0 = iy * g.stride, ix * g.stride
                ref = padded[:, :, y0:y0 + g.kernel, x0:x0 + g.kernel]
                np.testing.assert_array_equal(crops[iy * g.nx + ix], ref)
                # the crop's centre in pixel-index coordinates
                assert g.centers_x()[ix] == pytest.approx(x0 - g.padding + (g.kernel - 1) / 2)
        means = crop_means(torch.from_numpy(frames), g).numpy()
        np.testing.assert_allclose(means, crops.mean(axis=(3, 4)), atol=1e-12)


def test_resize_and_clip_normalization():
    crops = torch.full((2, 8, 3, 9, 9), 0.5)
    out = resize_crops(crops, 224, clip_normalize=True)
    assert out.shape == (2, 8, 3, 224, 224)
    expected = (0.5 - CLIP_MEAN[0]) / 0.26862954
    assert float(out[0, 0, 0].mean()) == pytest.approx(expected, abs=1e-5)


def _reference_pixel_feature(layout, feats: np.ndarray, x: float, y: float) -> np.ndarray:
    """float64, written independently: for each scale find the 4 surrounding crop centres by search."""
    total = np.zeros(feats.shape[1])
    for g in layout.scales:
        cx, cy = g.centers_x(), g.centers_y()

        def bracket(c: np.ndarray, v: float) -> tuple[int, int, float]:
            if len(c) == 1:
                return 0, 0, 0.0
            if v <= c[0]:
                return 0, 1, 0.0
            if v >= c[-1]:
                return len(c) - 2, len(c) - 1, 1.0
            i = int(np.searchsorted(c, v, side="right") - 1)
            i = min(i, len(c) - 2)
            return i, i + 1, (v - c[i]) / (c[i + 1] - c[i])

        x0, x1, wx = bracket(cx, x)
        y0, y1, wy = bracket(cy, y)
        f = feats[g.offset:g.offset + g.num_crops].reshape(g.ny, g.nx, -1)
        total += ((1 - wy) * ((1 - wx) * f[y0, x0] + wx * f[y0, x1]) + wy * ((1 - wx) * f[y1, x0] + wx * f[y1, x1]))
    return total / len(layout.scales)


def test_interpolation_matches_float64_reference_on_random_features():
    rng = np.random.default_rng(1)
    layout = crop_layout(41, 23, pyramid_ratios(0.15, 0.6, 5))
    feats = rng.normal(size=(layout.num_crops, 5))
    grid = pixel_features(layout, torch.from_numpy(feats)).numpy()
    assert grid.shape == (23, 41, 5)
    for y, x in [(0, 0), (22, 40), (11, 7), (3, 39), (17, 2)]:
        np.testing.assert_allclose(grid[y, x], _reference_pixel_feature(layout, feats, x, y), atol=1e-12)
    xs, ys = rng.uniform(0, 40, 50), rng.uniform(0, 22, 50)
    pts = interpolate_points(layout, torch.from_numpy(feats), torch.from_numpy(xs), torch.from_numpy(ys)).numpy()
    for i in range(50):
        np.testing.assert_allclose(pts[i], _reference_pixel_feature(layout, feats, xs[i], ys[i]), atol=1e-12)


def test_interpolation_reproduces_a_linear_gradient_inside_the_crop_grid():
    """Crop features sampled from a linear function of the crop centre interpolate exactly to it."""
    layout = crop_layout(96, 54, pyramid_ratios(0.15, 0.6, 5))
    feats = np.zeros((layout.num_crops, 2))
    for g in layout.scales:
        cy, cx = np.meshgrid(g.centers_y(), g.centers_x(), indexing="ij")
        feats[g.offset:g.offset + g.num_crops, 0] = (0.3 * cx + 2.0).ravel()
        feats[g.offset:g.offset + g.num_crops, 1] = (-0.7 * cy + 0.1 * cx).ravel()
    grid = pixel_features(layout, torch.from_numpy(feats)).numpy()
    # pixels inside every scale's outermost crop centres
    inner_x = max(g.centers_x()[0] for g in layout.scales), min(g.centers_x()[-1] for g in layout.scales)
    inner_y = max(g.centers_y()[0] for g in layout.scales), min(g.centers_y()[-1] for g in layout.scales)
    ys, xs = np.mgrid[0:54, 0:96]
    inside = (xs >= inner_x[0]) & (xs <= inner_x[1]) & (ys >= inner_y[0]) & (ys <= inner_y[1])
    assert inside.sum() > 1000
    np.testing.assert_allclose(grid[..., 0][inside], (0.3 * xs + 2.0)[inside], atol=1e-12)
    np.testing.assert_allclose(grid[..., 1][inside], (-0.7 * ys + 0.1 * xs)[inside], atol=1e-12)


def test_features_are_the_mean_over_scales_not_renormalized():
    layout = crop_layout(30, 20, [0.3, 0.6])
    feats = torch.zeros(layout.num_crops, 3, dtype=torch.float64)
    feats[:layout.scales[0].num_crops, 0] = 1.0   # scale 0: unit x
    feats[layout.scales[0].num_crops:, 1] = 1.0   # scale 1: unit y
    grid = pixel_features(layout, feats)
    np.testing.assert_allclose(grid.numpy(), np.broadcast_to([0.5, 0.5, 0.0], (20, 30, 3)))


@given(st.integers(1, 5), st.integers(5, 40), st.integers(5, 40))
def test_strided_sampling_upsamples_back_to_full_resolution(stride, width, height):
    layout = crop_layout(width, height, [0.5])
    feats = torch.randn(layout.num_crops, 2, dtype=torch.float64)
    coarse = pixel_features(layout, feats, stride)
    assert coarse.shape[:2] == (math.ceil(height / stride), math.ceil(width / stride))
    full = upsample_to_pixels(coarse, width, height, stride)
    assert full.shape == (height, width, 2)
    assert torch.isfinite(full).all()
    # a linear interpolant of a linear interpolant: bounded by the crop features
    assert float(full.abs().max()) <= float(feats.abs().max()) + 1e-9


def test_wrong_feature_count_is_an_input_error():
    layout = crop_layout(30, 20, [0.3])
    with pytest.raises(InputError, match="crop features"):
        pixel_features(layout, torch.zeros(layout.num_crops + 1, 4))
