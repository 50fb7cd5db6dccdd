"""The gsplat CUDA backend (optional extra ``fourlegs[cuda]``), behind the same interface.

Our options map onto ``gsplat.rasterization``: camera K / w2c → ``Ks`` / ``viewmats``, near/far →
``near_plane`` / ``far_plane``, ``eps2d`` → ``eps2d``, ``tile_size`` → ``tile_size``; RGB, features
and depth are blended in one call (render mode "RGB+D": the last channel is Σ w·z, normalized here
exactly like the torch backend), backgrounds are composited here with (1 − alpha).

Known convention differences (why the agreement test has a tolerance): gsplat caps α at 0.999
instead of 0.99 and bounds footprints by its own radius (≈3σ) instead of the opacity-aware
ellipse. Outputs gsplat cannot produce ("depth_median", "weights") are routed to the torch backend
by ``backend="auto"``.
"""
from __future__ import annotations

import torch

from ..scene.camera import Camera
from .options import RasterOptions
from .compose import DEPTH_ALPHA_EPS


def rasterize_gsplat(means: torch.Tensor, rotations: torch.Tensor, log_scales: torch.Tensor,
                     opacity_logits: torch.Tensor, camera: Camera, *, colors: torch.Tensor | None,
                     features: torch.Tensor | None, bg_rgb: torch.Tensor | None, bg_feat: torch.Tensor | None,
                     outputs: tuple[str, ...], options: RasterOptions, dtype: torch.dtype) -> dict:
    """Same contract as :func:`~fourlegs_engine.render.torch_backend.rasterize_torch` (CUDA only)."""
    import gsplat  # imported lazily: optional, and it compiles CUDA code on first use

    device = means.device
    f32 = torch.float32  # gsplat's kernels are float32
    N = means.shape[0]
    parts, slices, start = [], {}, 0
    for name, tensor in (("rgb", colors), ("features", features)):
        if name in outputs:
            parts.append(tensor.to(f32))
            slices[name] = slice(start, start + tensor.shape[1])
            start += tensor.shape[1]
    if not parts:  # alpha / depth only: blend one dummy channel
        parts.append(torch.zeros(N, 1, device=device, dtype=f32))
    values = torch.cat(parts, dim=-1)
    want_depth = "depth" in outputs
    viewmat = torch.as_tensor(camera.w2c, dtype=f32, device=device)[None]
    K = torch.as_tensor(camera.K, dtype=f32, device=device)[None]
    quats = rotations.to(f32)
    quats = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    render, alphas, _ = gsplat.rasterization(
        means=means.to(f32), quats=quats, scales=torch.exp(log_scales.to(f32)),
        opacities=torch.sigmoid(opacity_logits.to(f32)), colors=values, viewmats=viewmat, Ks=K,
        width=camera.width, height=camera.height, near_plane=camera.near, far_plane=camera.far,
        eps2d=options.eps2d, tile_size=options.tile_size if options.tile_size in (8, 16, 32) else 16,
        packed=False, render_mode="RGB+D" if want_depth else "RGB", rasterize_mode="classic")
    render = render[0].to(dtype)
    alpha = alphas[0].to(dtype)
    trans = 1.0 - alpha
    out: dict = {}
    if "rgb" in outputs:
        out["rgb"] = render[..., slices["rgb"]] + trans * bg_rgb
    if "features" in outputs:
        out["features"] = render[..., slices["features"]] + trans * bg_feat
    if want_depth:
        has = alpha > DEPTH_ALPHA_EPS
        safe = torch.where(has, alpha, torch.ones_like(alpha))
        out["depth"] = torch.where(has, render[..., -1:] / safe, torch.zeros_like(alpha))
    if "alpha" in outputs:
        out["alpha"] = alpha
    return out
