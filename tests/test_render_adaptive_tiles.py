"""tile_size="auto": the tile side follows the projected footprints, and the image stays the oracle's."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from _render_helpers import as_numpy, random_scene, view_cameras
from _render_oracle import render as oracle_render
from fourlegs_engine.errors import InputError
from fourlegs_engine.render import RasterOptions, rasterize
from fourlegs_engine.render.binning import bin_gaussians, choose_tile_size, estimated_pairs
from fourlegs_engine.render.projection import project_gaussians


def _project(scene, cam):
    return project_gaussians(scene["means"], scene["rotations"], scene["log_scales"], scene["opacity_logits"], cam,
                             RasterOptions(), torch.float64)


def test_small_splats_keep_small_tiles_and_large_splats_get_large_ones():
    cam = view_cameras(96, 72)[0]
    small = random_scene(400, 0, log_scale=-4.5)  # footprints of a pixel or two
    large = random_scene(400, 0, log_scale=-1.2)  # footprints of tens of pixels, heavily overlapping
    # 128 latent channels: the per-pixel blend dominates, small splats stay on the smallest tiles
    assert choose_tile_size(_project(small, cam), channels=128) == 4
    proj = _project(large, cam)
    chosen = choose_tile_size(proj, channels=3)
    assert chosen >= 8 and choose_tile_size(proj, channels=128) >= 8
    # the estimate tracks the real pair count, and the chosen side cuts the pairs several-fold
    for ts in (4, chosen):
        actual = bin_gaussians(proj, cam.width, cam.height, ts).num_pairs
        assert estimated_pairs(proj, ts) == pytest.approx(actual, rel=0.25)
    assert bin_gaussians(proj, cam.width, cam.height, 4).num_pairs > 3 * bin_gaussians(
        proj, cam.width, cam.height, "auto").num_pairs


def test_auto_tiles_on_large_splats_match_the_float64_oracle():
    scene = random_scene(150, 7, log_scale=-1.2)
    s = as_numpy(scene)
    for cam in view_cameras()[:2]:
        assert choose_tile_size(_project(scene, cam)) > 4
        ref = oracle_render(s["means"], s["rotations"], s["log_scales"], s["opacity_logits"], cam, s["colors"],
                            background=[0.0, 0.0, 0.0])
        for kernel in (True, False):
            with torch.no_grad():
                out = rasterize(scene["means"], scene["rotations"], scene["log_scales"], scene["opacity_logits"], cam,
                                colors=scene["colors"], outputs=("rgb", "alpha"),
                                options=RasterOptions(tile_size="auto", cpu_kernel=kernel))
            assert np.abs(out["rgb"].numpy() - ref["color"]).max() <= 1e-9
            assert np.abs(out["alpha"][..., 0].numpy() - ref["alpha"]).max() <= 1e-9
            assert ref["alpha"].mean() > 0.3


def test_tile_size_rejects_other_strings():
    scene = random_scene(10, 0)
    with pytest.raises(InputError, match="tile_size"):
        rasterize(scene["means"], scene["rotations"], scene["log_scales"], scene["opacity_logits"], view_cameras()[0],
                  colors=scene["colors"], options=RasterOptions(tile_size="big"))
