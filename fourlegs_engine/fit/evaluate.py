"""Held-out camera metrics of a fitted scene: PSNR and SSIM per timestep and test camera."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..render import rasterize
from ..render.options import RasterOptions
from .dataset import Capture
from .losses import psnr, ssim


@dataclass
class TestMetrics:
    """psnr[i][c], ssim[i][c] for the i-th evaluated timestep and c-th test camera; ``timesteps`` the
    dataset timesteps; ``cameras`` the test camera ids; ``renders``/``targets`` (optional) images."""

    timesteps: list[int]
    cameras: list[str]
    psnr: np.ndarray
    ssim: np.ndarray
    renders: dict[tuple[int, str], np.ndarray]
    targets: dict[tuple[int, str], np.ndarray]

    @property
    def mean_psnr(self) -> float:
        return float(self.psnr.mean()) if self.psnr.size else float("nan")

    @property
    def mean_ssim(self) -> float:
        return float(self.ssim.mean()) if self.ssim.size else float("nan")


def evaluate_test_views(bundle: str | Path, capture: Capture | str | Path, *, resolution_scale: float = 0.5,
                        keep_images_at: tuple[int, ...] = ()) -> TestMetrics:
    """Render every timestep of ``bundle`` from the capture's test cameras and compare.

    The test cameras have no colour correction of their own, so renders are compared as they are
    (the paper's protocol). ``keep_images_at`` lists bundle timestep positions whose images are kept.
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
    renders, targets = {}, {}
    log_scales = torch.from_numpy(np.array(g.log_scales, np.float32))
    opac = torch.from_numpy(np.array(g.opacity_logits, np.float32))
    colors = torch.from_numpy(np.array(g.colors if g.colors.ndim == 2 else g.colors[0], np.float32))
    for i in range(T):
        t = first + i
        means = torch.from_numpy(np.array(g.means[i], np.float32))
        rots = torch.from_numpy(np.array(g.rotations[i], np.float32))
        for j, c in enumerate(test_idx):
            cam = cap.test.cameras[t][c].scaled(resolution_scale)
            target = torch.from_numpy(cap.load_image("test", t, c, (cam.width, cam.height)))
            with torch.no_grad():
                img = rasterize(means, rots, log_scales, opac, cam, colors=colors, options=opts)["rgb"].clamp(0, 1)
            ps[i, j] = psnr(img, target)
            ss[i, j] = float(ssim(img, target))
            name = cap.test.cam_ids[t][c]
            if i in keep_images_at:
                renders[(t, name)] = img.numpy()
                targets[(t, name)] = target.numpy()
    return TestMetrics([first + i for i in range(T)], [cap.test.cam_ids[first][c] for c in test_idx], ps, ss,
                       renders, targets)
