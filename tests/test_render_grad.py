"""Gradients: the hand-written backward against finite differences (gradcheck, float64) and against
autograd through the dense reference implementation."""
from __future__ import annotations

import pytest
import torch

from _render_helpers import random_scene, view_cameras
from fourlegs_engine.render import RasterOptions, rasterize
from fourlegs_engine.render.reference import rasterize_reference
from fourlegs_engine.scene import Camera

NAMES = ("means", "rotations", "log_scales", "opacity_logits", "colors", "features")
OUTS = ("rgb", "features", "depth", "alpha")


def _projected_loss_fn(cam, options, n_proj=3, seed=0):
    """A function of the six inputs returning n_proj random projections of every output map."""
    g = torch.Generator().manual_seed(seed)
    H, W = cam.height, cam.width
    weights = {k: torch.randn(n_proj, H, W, c, generator=g, dtype=torch.float64)
               for k, c in (("rgb", 3), ("features", 2), ("depth", 1), ("alpha", 1))}

    def fn(means, rotations, log_scales, opacity_logits, colors, features):
        out = rasterize(means, rotations, log_scales, opacity_logits, cam, colors=colors, features=features,
                        background=[0.3, 0.1, 0.2], outputs=OUTS, options=options)
        return sum((weights[k] * out[k][None]).flatten(1).sum(1) for k in OUTS)
    return fn


@pytest.mark.parametrize("options,fast", [(RasterOptions(tile_size=4), False),
                                          (RasterOptions(tile_size=3, chunk=2), True)])
def test_gradcheck_all_inputs(options, fast):
    """Finite differences for colours, features, opacities, means, log-scales and rotations (the
    chunked variant in gradcheck's fast mode: random projections of the Jacobian)."""
    scene = random_scene(7, 11, channels=2, spread=0.25, log_scale=-1.6)
    cam = Camera.look_at((0.0, -2.0, 0.4), (0, 0, 0), width=12, height=10, fov_y=0.8)
    inputs = tuple(scene[k].clone().requires_grad_() for k in NAMES)
    fn = _projected_loss_fn(cam, options)
    assert (fn(*inputs).abs() > 0).all()
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-5, fast_mode=fast)


def test_gradients_match_autograd_through_the_dense_reference():
    scene = random_scene(150, 4, channels=3)
    for cam in view_cameras(24, 18)[:4]:
        inputs = [scene[k].clone().requires_grad_() for k in NAMES]
        g = torch.Generator().manual_seed(1)
        w = {k: torch.randn(cam.height, cam.width, c, generator=g, dtype=torch.float64)
             for k, c in (("rgb", 3), ("features", 3), ("depth", 1), ("alpha", 1))}
        kw = dict(colors=inputs[4], features=inputs[5], outputs=OUTS)
        fast = rasterize(*inputs[:4], cam, background=[0.3, 0.1, 0.2], options=RasterOptions(chunk=5), **kw)
        ref = rasterize_reference(*inputs[:4], cam, background=torch.tensor([0.3, 0.1, 0.2], dtype=torch.float64),
                                  tile_size=None, **kw)
        g_fast = torch.autograd.grad(sum((fast[k] * w[k]).sum() for k in OUTS), inputs)
        g_ref = torch.autograd.grad(sum((ref[k] * w[k]).sum() for k in OUTS), inputs)
        for name, a, b in zip(NAMES, g_fast, g_ref):
            scale = b.abs().max().item()
            assert scale > 0, (cam.name, name)
            assert (a - b).abs().max().item() <= 1e-6 * scale + 1e-12, (cam.name, name)


def test_float32_gradients_close_to_float64():
    scene = random_scene(150, 8, channels=3)
    cam = view_cameras()[0]
    grads = {}
    weight = torch.randn(cam.height, cam.width, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    for dtype in (torch.float64, torch.float32):
        inputs = [scene[k].to(dtype).requires_grad_() for k in NAMES]
        out = rasterize(*inputs[:4], cam, colors=inputs[4], features=inputs[5], outputs=("rgb", "features"))
        loss = (out["rgb"] * weight.to(dtype)).sum() + (out["features"] ** 2).sum()
        grads[dtype] = torch.autograd.grad(loss, inputs)
    for name, a, b in zip(NAMES, grads[torch.float32], grads[torch.float64]):
        assert (a.double() - b).abs().max() <= 1e-3 * b.abs().max() + 1e-6, name


def test_features_only_backward_leaves_geometry_untouched():
    """Distillation: features learn, geometry frozen (no grad requested) — only features get .grad."""
    scene = random_scene(60, 9, channels=5, dtype=torch.float32)
    feats = scene["features"].clone().requires_grad_()
    out = rasterize(scene["means"], scene["rotations"], scene["log_scales"], scene["opacity_logits"],
                    view_cameras()[0], features=feats, outputs=("features",))
    out["features"].abs().sum().backward()
    assert feats.grad is not None and torch.isfinite(feats.grad).all() and feats.grad.abs().sum() > 0
    assert scene["means"].grad is None
