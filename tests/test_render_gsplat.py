"""The gsplat CUDA backend agrees with the torch rasterizer (skipped without CUDA and gsplat)."""
from __future__ import annotations

import pytest
import torch

from _render_helpers import random_scene, view_cameras
from fourlegs_engine.render import rasterize
from fourlegs_engine.render.backends import gsplat_available

pytestmark = [pytest.mark.cuda,
              pytest.mark.skipif(not torch.cuda.is_available() or not gsplat_available(),
                                 reason="needs CUDA and gsplat (pip install 'fourlegs[cuda]')")]


def test_gsplat_agrees_with_torch_backend():
    scene = random_scene(300, 0, channels=8, dtype=torch.float32)
    # keep α below both conventions' caps (gsplat: 0.999, ours: 0.99) so only footprint bounds differ
    scene["opacity_logits"] = scene["opacity_logits"].clamp(max=3.0)
    scene = {k: v.cuda().requires_grad_() for k, v in scene.items()}
    outs = ("rgb", "features", "depth", "alpha")
    for cam in view_cameras(64, 48)[:4]:
        kw = dict(colors=scene["colors"], features=scene["features"], background=[0.1, 0.2, 0.3], outputs=outs)
        args = [scene[k] for k in ("means", "rotations", "log_scales", "opacity_logits")]
        a = rasterize(*args, cam, backend="gsplat", **kw)
        b = rasterize(*args, cam, backend="torch", **kw)
        for k in outs:
            diff = (a[k] - b[k]).abs()
            scale = 3.0 if k == "depth" else 1.0
            assert diff.mean().item() < 2e-3 * scale, (cam.name, k)
            assert diff.max().item() < 5e-2 * scale, (cam.name, k)
        ga = torch.autograd.grad(a["rgb"].sum() + a["features"].sum(), [scene["colors"], scene["features"]])
        gb = torch.autograd.grad(b["rgb"].sum() + b["features"].sum(), [scene["colors"], scene["features"]])
        for x, y in zip(ga, gb):
            assert (x - y).abs().max().item() < 0.05 * y.abs().max().item() + 1e-3


def test_auto_prefers_gsplat_only_for_supported_outputs():
    from fourlegs_engine.render.backends import select_backend
    from fourlegs_engine.render.gsplat_backend import rasterize_gsplat
    from fourlegs_engine.render.torch_backend import rasterize_torch
    dev = torch.device("cuda")
    assert select_backend("auto", dev, ("rgb", "depth")) is rasterize_gsplat
    assert select_backend("auto", dev, ("rgb", "weights")) is rasterize_torch
