"""Per-timestep foreground colours (``FitOptions.lr_colors_later``): a foreground that darkens over time is
followed by the colours, the background and the first timestep are left alone, and a killed fit resumes
to the same bundle."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

import _fit_helpers as fh
from fourlegs_engine.errors import InputError
from fourlegs_engine.fit import FitOptions, fit_capture
from fourlegs_engine.fit.losses import psnr
from fourlegs_engine.render import RasterOptions, rasterize
from fourlegs_engine.scene.bundle import load_bundle

#: the synthetic scene's options (as tests/test_fit.py) with the foreground darkening 20 % per timestep
OPTIONS = FitOptions(resolution_scale=1.0, first_iterations=80, iterations=16, max_iterations=0,
                     init_background=1500, background_stride=4, voxel=0.04, max_gaussians=4000,
                     lr_means_later=0.0016, **fh.FEW_STEP_RATES)
DARKENING = 0.2


@pytest.fixture(scope="module")
def darkening_capture(tmp_path_factory) -> Path:
    return fh.write_capture(tmp_path_factory.mktemp("dark"), num_timesteps=3, fg_darkening=DARKENING)


@pytest.fixture(scope="module")
def fits(darkening_capture, tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("fits")
    out = {}
    for name, lr in (("static", 0.0), ("later", 0.02)):
        out[name] = root / name
        fit_capture(darkening_capture, out[name], replace(OPTIONS, lr_colors_later=lr), progress=False)
    return out


def _train_psnr(capture: Path, bundle: Path, t: int) -> float:
    """Mean PSNR of the colour-corrected renders of timestep ``t`` against the training images."""
    scene = load_bundle(bundle)
    g = scene.gaussians
    cc = scene.metadata["color_correction"]
    colors = np.array(g.colors[t] if g.colors.ndim == 3 else g.colors, np.float32)
    images = fh.load_images(capture, "train", t)
    scores = []
    for cam in scene.cameras.cameras(t, "train"):
        with torch.no_grad():
            rgb = rasterize(torch.from_numpy(np.array(g.means[t])), torch.from_numpy(np.array(g.rotations[t])),
                            torch.from_numpy(np.array(g.log_scales)), torch.from_numpy(np.array(g.opacity_logits)),
                            cam, colors=torch.from_numpy(colors), options=RasterOptions())["rgb"].double()
        k = int(cam.name) - 1
        img = torch.exp(torch.tensor(cc["cam_m"][k], dtype=torch.float64)) * rgb + torch.tensor(cc["cam_c"][k],
                                                                                                 dtype=torch.float64)
        scores.append(psnr(img, torch.from_numpy(images[cam.name])))
    return float(np.mean(scores))


@pytest.mark.slow
def test_colours_follow_a_darkening_foreground_and_leave_the_rest(darkening_capture, fits):
    static, later = load_bundle(fits["static"]).gaussians, load_bundle(fits["later"]).gaussians
    assert static.colors.shape == (static.num_gaussians, 3)
    assert later.colors.shape == (3, later.num_gaussians, 3)
    assert np.isfinite(later.colors).all() and later.colors.min() >= 0.0 and later.colors.max() <= 1.0
    fg = np.asarray(later.foreground, bool)
    # the first timestep is fitted alike (same seed, the knob acts only later); background colours never move
    np.testing.assert_array_equal(later.colors[0], static.colors)
    for t in (1, 2):
        np.testing.assert_array_equal(later.colors[t][~fg], later.colors[0][~fg])
    # the foreground's brightness follows the capture: 20 % darker per timestep, within what 16 steps reach
    brightness = [float(later.colors[t][fg].mean()) for t in range(3)]
    assert brightness[2] < brightness[1] < brightness[0], brightness
    assert brightness[2] < 0.85 * brightness[0], brightness
    # and the renders agree better with the darkened frames than static colours can
    for t in (1, 2):
        gain = _train_psnr(darkening_capture, fits["later"], t) - _train_psnr(darkening_capture, fits["static"], t)
        assert gain > 1.0, (t, gain)


def test_killed_fit_with_later_colours_resumes_to_the_identical_bundle(darkening_capture, tmp_path):
    opts = FitOptions(resolution_scale=0.5, first_iterations=20, iterations=4, init_background=400,
                      background_stride=4, voxel=0.05, lr_colors_later=0.02)
    straight, resumed = fh.fit_straight_and_resumed(darkening_capture, tmp_path, opts, kill_after=1)
    a, b = np.load(straight / "colors.npy"), np.load(resumed / "colors.npy")
    assert a.ndim == 3 and np.array_equal(a, b)


def test_the_colour_rate_is_in_the_fingerprint_only_when_on():
    from fourlegs_engine.fit.options import preset_options

    assert "lr_colors_later" not in FitOptions(lr_colors_later=0.0).fingerprint()
    assert FitOptions().fingerprint()["lr_colors_later"] == 0.0025
    assert preset_options("accurate").lr_colors_later == 0.0025


@pytest.mark.parametrize("value", [-0.01, float("nan"), float("inf")])
def test_a_bad_colour_rate_is_refused_naming_the_field(value):
    with pytest.raises(InputError, match="lr_colors_later"):
        FitOptions(lr_colors_later=value).check()


def test_the_bench_and_the_cli_take_the_colour_rate():
    import argparse

    from fourlegs_bench.fit import parse_runs
    from fourlegs_engine.commands.fit import options_from_args, register

    assert parse_runs("c:lr_colors_later=0.0025,device=cpu") == [("c", {"lr_colors_later": 0.0025, "device": "cpu"})]
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["fit", "capture", "-o", "out", "--lr-colors-later", "0.001"])
    assert options_from_args(args).lr_colors_later == 0.001
    assert options_from_args(parser.parse_args(["fit", "capture", "-o", "out"])).lr_colors_later == 0.0025
