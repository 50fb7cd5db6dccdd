"""Clean plates: the background an occluder hides at the first timestep is recovered once it moves away."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

import _fit_helpers as fh
from fourlegs_engine.errors import InputError
from fourlegs_engine.fit import Capture, FitOptions, fit_capture
from fourlegs_engine.fit.clean_plate import clean_plates, median_background, sample_timesteps
from fourlegs_engine.render import RasterOptions, rasterize
from fourlegs_engine.scene.bundle import load_bundle

#: the box jumps 0.7 m a timestep: what it hides at t = 0 is in the open at t = 1 and 2
JUMP = np.array([0.7, 0.0, 0.0])
OPTIONS = FitOptions(resolution_scale=1.0, first_iterations=60, iterations=1, init_background=1500,
                     background_stride=3, voxel=0.04, max_gaussians=4000, densify=False, **fh.FEW_STEP_RATES)


@pytest.fixture(scope="module")
def moving_occluder(tmp_path_factory) -> Path:
    mp = pytest.MonkeyPatch()
    mp.setattr(fh, "STEP_TRANSLATION", JUMP)
    try:
        return fh.write_capture(tmp_path_factory.mktemp("occluder"), num_timesteps=3)
    finally:
        mp.undo()


def _hidden_at_t0(capture: Capture, c: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of training camera c that the box covers at t = 0 and leaves fully open at t = 1 and 2,
    and the float64 ground-truth background-only image of that camera."""
    g = fh.scene_gaussians()
    cam = fh.cameras()[0][c]
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(fh, "STEP_TRANSLATION", JUMP)
        _, a0 = fh.render(g, 0, cam, subset=g["fg"])
        _, a1 = fh.render(g, 1, cam, subset=g["fg"])
        _, a2 = fh.render(g, 2, cam, subset=g["fg"])
        wall, _ = fh.render(g, 0, cam, subset=~g["fg"])
    return (a0 > 0.9) & (a1 < 0.01) & (a2 < 0.01), wall


def test_median_background_ignores_the_masked_samples():
    images = np.array([[[[0.9, 0.1, 0.1]]], [[[0.2, 0.4, 0.6]]], [[[0.2, 0.4, 0.6]]], [[[0.3, 0.5, 0.7]]]],
                      np.float32)
    masks = np.array([[[1.0]], [[0.0]], [[0.2]], [[0.4]]], np.float32)
    plate, known = median_background(images, masks)
    np.testing.assert_allclose(plate[0, 0], [0.2, 0.4, 0.6], atol=1e-7)
    assert known[0, 0]
    plate, known = median_background(images, np.ones_like(masks))
    assert not known[0, 0] and np.all(plate == 0.0) and np.isfinite(plate).all()


def test_sample_timesteps_spreads_over_the_range_and_keeps_the_first():
    assert sample_timesteps(range(0, 150), 8) == [0, 21, 43, 64, 85, 106, 128, 149]
    assert sample_timesteps(range(5, 8), 8) == [5, 6, 7]
    assert sample_timesteps(range(3, 9), 1) == [3]
    with pytest.raises(InputError, match="clean_plate_samples"):
        FitOptions(clean_plate_samples=-1).check()


def test_clean_plate_shows_the_wall_the_occluder_hid_at_t0(moving_occluder):
    capture = Capture(moving_occluder)
    cams = [1, 2, 3, 4]  # camera 0 looks along the box's path: the box never leaves its view of the wall
    plates = clean_plates(capture, cams, [0, 1, 2], (fh.WIDTH, fh.HEIGHT))
    for i, c in enumerate(cams):
        hidden, wall = _hidden_at_t0(capture, c)
        t0 = capture.load_image("train", 0, c, (fh.WIDTH, fh.HEIGHT))
        assert hidden.sum() > 20 and plates.known[i][hidden].all()
        # within PNG quantisation of the float64 wall, far from what the t0 frame shows there
        np.testing.assert_allclose(plates.images[i][hidden], wall[hidden], atol=1.0 / 255 + 1e-6)
        assert np.abs(t0[hidden] - wall[hidden]).mean() > 0.05


def _background_errors(bundle: Path, capture: Capture) -> tuple[float, float]:
    """Mean |background-only render − float64 wall| over the training views: (where the box stood at
    t = 0 and then left, everywhere the box never covers)."""
    scene = load_bundle(bundle)
    g = scene.gaussians
    fg = torch.from_numpy(np.array(g.foreground))
    opac = torch.from_numpy(np.array(g.opacity_logits)).clone()
    opac[fg] = -30.0
    errors, open_errors = [], []
    g_true = fh.scene_gaussians()
    for c, cam in enumerate(fh.cameras()[0]):
        hidden, wall = _hidden_at_t0(capture, c)
        with torch.no_grad():
            rgb = rasterize(torch.from_numpy(np.array(g.means[0])), torch.from_numpy(np.array(g.rotations[0])),
                            torch.from_numpy(np.array(g.log_scales)), opac, cam,
                            colors=torch.from_numpy(np.array(g.rgb(0))), options=RasterOptions())["rgb"].numpy()
        errors.append(np.abs(rgb[hidden] - wall[hidden]).mean(-1))
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(fh, "STEP_TRANSLATION", JUMP)
            never = np.all([fh.render(g_true, t, cam, subset=g_true["fg"])[1] < 0.01 for t in range(3)], axis=0)
        open_errors.append(np.abs(rgb[never] - wall[never]).mean(-1))
    return float(np.concatenate(errors).mean()), float(np.concatenate(open_errors).mean())


@pytest.mark.slow
def test_fitted_background_has_the_wall_colour_where_the_occluder_stood(moving_occluder, tmp_path):
    capture = Capture(moving_occluder)
    errors = {}
    for samples in (0, 3):
        out = tmp_path / f"plates{samples}"
        opts = replace(OPTIONS, timesteps=(0, 3), clean_plate_samples=samples)
        fit_capture(capture, out, opts, progress=False)
        errors[samples] = _background_errors(out, capture)
    (hidden_without, open_without), (hidden_with, open_with) = errors[0], errors[3]
    # without plates the wall behind the box at t = 0 is fitted worse than the wall nothing hides;
    # with them it is as good as anywhere
    assert hidden_without > 1.1 * open_without, errors
    assert hidden_with < 1.05 * open_with, errors
    assert hidden_with < 0.9 * hidden_without, errors


def test_cli_flag_sets_the_clean_plate_samples():
    from fourlegs_engine.commands.main import build_parser
    from fourlegs_engine.commands.fit import options_from_args

    args = build_parser().parse_args(["fit", "ds", "-o", "out", "--clean-plate-samples", "5"])
    assert options_from_args(args).clean_plate_samples == 5
    assert options_from_args(build_parser().parse_args(["fit", "ds", "-o", "out"])).clean_plate_samples == 8
    args = build_parser().parse_args(["fit", "ds", "-o", "out", "--clean-plate-samples", "0"])
    assert options_from_args(args).clean_plate_samples == 0   # off
