"""Held-out camera metrics of a fitted scene: PSNR and SSIM per timestep and test camera."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from ..render import rasterize
from ..render.options import RasterOptions
from .dataset import Capture
from .losses import psnr, ssim


@dataclass
class TestMetrics:
    """psnr[i][c], ssim[i][c] for the i-th evaluated timestep and c-th test camera; ``timesteps`` the
    dataset timesteps; ``cameras`` the test camera ids; ``renders``/``targets`` (optional) images;
    ``region_sse[i][c]``/``region_pixels[i][c]`` the summed squared error (over the 3 channels) and the
    pixel count of the evaluated region (all zero when no region was asked for)."""

    timesteps: list[int]
    cameras: list[str]
    psnr: np.ndarray
    ssim: np.ndarray
    renders: dict[tuple[int, str], np.ndarray]
    targets: dict[tuple[int, str], np.ndarray]
    region_sse: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    region_pixels: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.int64))

    def region_psnr(self) -> list[list[float | None]]:
        """PSNR (dB) of the region per timestep and camera; None where the region is empty."""
        return [[_psnr_of(e, n) for e, n in zip(row_e, row_n)] for row_e, row_n in zip(self.region_sse, self.region_pixels)]

    def region_psnr_per_timestep(self) -> list[float | None]:
        """Mean over the cameras that see the region of their region PSNR; None where none does."""
        out = []
        for row in self.region_psnr():
            seen = [v for v in row if v is not None]
            out.append(float(np.mean(seen)) if seen else None)
        return out

    @property
    def mean_region_psnr(self) -> float | None:
        """Mean region PSNR over every (timestep, camera) that sees the region; None when none does."""
        seen = [v for row in self.region_psnr() for v in row if v is not None]
        return float(np.mean(seen)) if seen else None

    @property
    def mean_psnr(self) -> float:
        return float(self.psnr.mean()) if self.psnr.size else float("nan")

    @property
    def mean_ssim(self) -> float:
        return float(self.ssim.mean()) if self.ssim.size else float("nan")


def _psnr_of(sse: float, pixels: int) -> float | None:
    if pixels <= 0:
        return None
    mse = float(sse) / (3.0 * int(pixels))
    return 100.0 if mse <= 1e-10 else -10.0 * math.log10(mse)


def region_error(render: np.ndarray, target: np.ndarray, region: Callable[[np.ndarray], np.ndarray]) -> tuple[float, int]:
    """Summed squared error (3 channels) and pixel count over a region of two (H, W, 3) images in [0, 1].

    The region is ``region`` (an (H, W, 3) uint8 image -> (H, W) bool mask) found in the ground truth
    or in the render: a thing the render lost and a thing it put in the wrong place both count."""
    render = np.clip(render, 0.0, 1.0)
    as_bytes = lambda im: np.round(im * 255.0).astype(np.uint8)  # noqa: E731
    mask = np.asarray(region(as_bytes(target)), bool) | np.asarray(region(as_bytes(render)), bool)
    diff = render[mask].astype(np.float64) - target[mask].astype(np.float64)
    return float((diff * diff).sum()), int(mask.sum())


def evaluate_test_views(bundle: str | Path, capture: Capture | str | Path, *, resolution_scale: float = 0.5,
                        keep_images_at: tuple[int, ...] = (),
                        region: Callable[[np.ndarray], np.ndarray] | None = None) -> TestMetrics:
    """Render every timestep of ``bundle`` from the capture's test cameras and compare.

    The test cameras have no colour correction of their own, so renders are compared as they are
    (the paper's protocol): a fitted bundle's colours are the average training camera's. ``keep_images_at`` lists bundle timestep positions whose images are kept.
    ``region`` (an (H, W, 3) uint8 image -> (H, W) bool mask, e.g. the orange ball's colour threshold)
    adds the region's PSNR (:func:`region_error`).
    """
    from ..scene.bundle import load_bundle

    scene = load_bundle(bundle)
    cap = capture if isinstance(capture, Capture) else Capture(capture)
    first = int(scene.metadata.get("first_timestep", 0))
    test_idx = cap.camera_indices("test", None)
    g = scene.gaussians
    opts = RasterOptions(tile_size="auto", validate=False)
    T = g.num_timesteps
    ps = np.zeros((T, len(test_idx)))
    ss = np.zeros((T, len(test_idx)))
    region_sse = np.zeros((T, len(test_idx)))
    region_pixels = np.zeros((T, len(test_idx)), np.int64)
    renders, targets = {}, {}
    log_scales = torch.from_numpy(np.array(g.log_scales, np.float32))
    opac = torch.from_numpy(np.array(g.opacity_logits, np.float32))
    static_colors = torch.from_numpy(np.array(g.colors, np.float32)) if g.colors.ndim == 2 else None
    for i in range(T):
        t = first + i
        colors = static_colors if static_colors is not None else torch.from_numpy(np.array(g.colors[i], np.float32))
        means = torch.from_numpy(np.array(g.means[i], np.float32))
        rots = torch.from_numpy(np.array(g.rotations[i], np.float32))
        for j, c in enumerate(test_idx):
            cam = cap.test.cameras[t][c].scaled(resolution_scale)
            target = torch.from_numpy(cap.load_image("test", t, c, (cam.width, cam.height)))
            with torch.no_grad():
                img = rasterize(means, rots, log_scales, opac, cam, colors=colors, options=opts)["rgb"].clamp(0, 1)
            ps[i, j] = psnr(img, target)
            ss[i, j] = float(ssim(img, target))
            if region is not None:
                region_sse[i, j], region_pixels[i, j] = region_error(img.numpy(), target.numpy(), region)
            name = cap.test.cam_ids[t][c]
            if i in keep_images_at:
                renders[(t, name)] = img.numpy()
                targets[(t, name)] = target.numpy()
    return TestMetrics([first + i for i in range(T)], [cap.test.cam_ids[first][c] for c in test_idx], ps, ss,
                       renders, targets, region_sse, region_pixels)
