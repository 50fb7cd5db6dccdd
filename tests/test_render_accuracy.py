"""The tile rasterizer against the independent float64 brute-force oracle (tests/_render_oracle.py)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from _render_helpers import as_numpy, random_scene, view_cameras
from _render_oracle import render as oracle_render
from fourlegs_engine.render import RasterOptions, cpu_kernels, rasterize
from fourlegs_engine.render.reference import rasterize_reference

ALL = ("rgb", "features", "depth", "depth_median", "alpha", "weights")
TOL = {torch.float64: 1e-5, torch.float32: 1e-4}
BACKGROUND = [0.2, 0.4, 0.6]


def _oracle(scene, cam):
    s = as_numpy(scene)
    values = np.concatenate([s["colors"], s["features"]], axis=1)
    return oracle_render(s["means"], s["rotations"], s["log_scales"], s["opacity_logits"], cam, values,
                         background=BACKGROUND + [0.0] * s["features"].shape[1])


def _max_errors(out, ref, W, H, N):
    dense = np.zeros((H * W, N))
    wts = out["weights"]
    dense[wts.pixel.numpy(), wts.gaussian.numpy()] = wts.weight.double().numpy()
    return {
        "rgb": np.abs(out["rgb"].double().numpy() - ref["color"][..., :3]).max(),
        "features": np.abs(out["features"].double().numpy() - ref["color"][..., 3:]).max(),
        "alpha": np.abs(out["alpha"][..., 0].double().numpy() - ref["alpha"]).max(),
        "weights": np.abs(dense - ref["weights"]).max(),
        # depths are in metres (~3): compare relative to the scene depth
        "depth": np.abs(out["depth"][..., 0].double().numpy() - ref["depth"]).max() / 3.0,
        "depth_median": np.abs(out["depth_median"][..., 0].double().numpy() - ref["depth_median"]).max() / 3.0,
    }


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("seed", [0, 1])
def test_matches_oracle_on_random_scenes(dtype, seed):
    scene64 = random_scene(250, seed)
    scene = {k: v.to(dtype) for k, v in scene64.items()}
    drawn = 0.0
    for cam in view_cameras():
        ref = _oracle(scene64, cam)
        out = rasterize(scene["means"], scene["rotations"], scene["log_scales"], scene["opacity_logits"], cam,
                        colors=scene["colors"], features=scene["features"], background=BACKGROUND,
                        outputs=ALL)
        assert out["rgb"].dtype == dtype and out["rgb"].shape == (cam.height, cam.width, 3)
        errs = _max_errors(out, ref, cam.width, cam.height, 250)
        bad = {k: v for k, v in errs.items() if not v <= TOL[dtype]}
        assert not bad, f"camera {cam.name}: {bad}"
        drawn += ref["alpha"].mean()
    assert drawn / len(view_cameras()) > 0.2  # the scenes are not empty


@pytest.mark.parametrize("options", [RasterOptions(tile_size=1), RasterOptions(tile_size=7, chunk=3),
                                     RasterOptions(tile_size=16, chunk=1000, batch_elements=4096)])
def test_tile_size_and_chunking_do_not_change_the_image(options):
    scene = random_scene(200, 5, log_scale=-1.8)
    cam = view_cameras()[0]
    ref = _oracle(scene, cam)
    out = rasterize(scene["means"], scene["rotations"], scene["log_scales"], scene["opacity_logits"], cam,
                    colors=scene["colors"], features=scene["features"], background=BACKGROUND, outputs=ALL,
                    options=options)
    errs = _max_errors(out, ref, cam.width, cam.height, 200)
    assert max(errs.values()) <= 1e-9, errs


def test_three_sigma_extent_only_drops_faint_tails():
    scene = random_scene(200, 2)
    cam = view_cameras()[1]
    ref = _oracle(scene, cam)
    out = rasterize(scene["means"], scene["rotations"], scene["log_scales"], scene["opacity_logits"], cam,
                    colors=scene["colors"], background=BACKGROUND, outputs=("rgb", "alpha"),
                    options=RasterOptions(extent="3sigma"))
    err = np.abs(out["rgb"].numpy() - ref["color"][..., :3]).max()
    # beyond 3σ a Gaussian's α is at most 0.99·e^-4.5 ≈ 0.011: the error is bounded by a few of those
    assert 0 < err < 0.05


@pytest.mark.parametrize("tile_size", [None, 8])
def test_dense_reference_matches_oracle(tile_size):
    scene = random_scene(120, 3)
    cam = view_cameras()[0]
    ref = _oracle(scene, cam)
    out = rasterize_reference(scene["means"], scene["rotations"], scene["log_scales"], scene["opacity_logits"],
                              cam, colors=scene["colors"], features=scene["features"],
                              background=torch.tensor(BACKGROUND, dtype=torch.float64),
                              outputs=("rgb", "features", "depth", "alpha"), tile_size=tile_size)
    assert np.abs(out["rgb"].numpy() - ref["color"][..., :3]).max() < 1e-9
    assert np.abs(out["features"].numpy() - ref["color"][..., 3:]).max() < 1e-9
    assert np.abs(out["alpha"][..., 0].numpy() - ref["alpha"]).max() < 1e-9
    assert np.abs(out["depth"][..., 0].numpy() - ref["depth"]).max() < 1e-9


def test_oracle_conventions_by_hand():
    """One isotropic Gaussian straight ahead: α at its centre pixel is min(0.99, o·exp(−½ d²/σ²))."""
    from fourlegs_engine.scene import Camera
    cam = Camera.look_at((0, -5, 0), (0, 0, 0), width=9, height=9, focal=100.0, up=(0, 0, 1))
    sigma_world = 0.02  # 0.4 px at 5 m, focal 100
    scene = {"means": torch.zeros(1, 3, dtype=torch.float64), "rotations": torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64),
             "log_scales": torch.full((1, 3), np.log(sigma_world), dtype=torch.float64),
             "opacity_logits": torch.tensor([0.0], dtype=torch.float64), "colors": torch.ones(1, 3, dtype=torch.float64)}
    out = rasterize(scene["means"], scene["rotations"], scene["log_scales"], scene["opacity_logits"], cam,
                    colors=scene["colors"], outputs=("alpha",))
    var = (100 * sigma_world / 5) ** 2 + 0.3  # projected variance + low-pass, px²
    # the mean projects to (4.5, 4.5): the centre of pixel (4, 4); its neighbour is 1 px away
    assert out["alpha"][4, 4, 0].item() == pytest.approx(0.5, rel=1e-12)
    assert out["alpha"][4, 5, 0].item() == pytest.approx(0.5 * np.exp(-0.5 / var), rel=1e-9)
    assert out["alpha"][0, 0, 0].item() == 0.0  # α = 0.5·e^{-16/var} < 1/255: skipped


KERNEL_OUTPUTS = ("rgb", "features", "depth", "alpha")


@pytest.mark.skipif(not cpu_kernels.available(), reason="numba is not installed")
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("options", [RasterOptions(), RasterOptions(tile_size=1), RasterOptions(tile_size=16)],
                         ids=["tile4", "tile1", "tile16"])
def test_fused_cpu_kernel_matches_oracle(dtype, options):
    """Without gradients (and without "weights"/"depth_median") the fused numba kernel blends; it is
    held to the same float64 oracle and tolerances as the torch path."""
    scene64 = random_scene(250, 1)
    scene = {k: v.to(dtype) for k, v in scene64.items()}
    for cam in view_cameras():
        ref = _oracle(scene64, cam)
        with torch.no_grad():
            out = rasterize(scene["means"], scene["rotations"], scene["log_scales"], scene["opacity_logits"], cam,
                            colors=scene["colors"], features=scene["features"], background=BACKGROUND,
                            outputs=KERNEL_OUTPUTS, options=options)
        errs = {
            "rgb": np.abs(out["rgb"].double().numpy() - ref["color"][..., :3]).max(),
            "features": np.abs(out["features"].double().numpy() - ref["color"][..., 3:]).max(),
            "alpha": np.abs(out["alpha"][..., 0].double().numpy() - ref["alpha"]).max(),
            "depth": np.abs(out["depth"][..., 0].double().numpy() - ref["depth"]).max() / 3.0,
        }
        bad = {k: v for k, v in errs.items() if not v <= TOL[dtype]}
        assert not bad, f"camera {cam.name}: {bad}"
        assert out["rgb"].dtype == dtype
