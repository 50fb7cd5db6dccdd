"""Shared by every CPU blending path: stacking the per-Gaussian channels to blend, and turning the
blended sums and final transmittance into the requested output maps."""
from __future__ import annotations

import torch

#: alpha below this counts as empty for the expected depth (depth is 0 there)
DEPTH_ALPHA_EPS = 1e-6


def stack_values(geom: torch.Tensor, depths: torch.Tensor, *, colors, features, outputs: tuple[str, ...],
                 dtype: torch.dtype, keep_half: bool) -> tuple[torch.Tensor, dict[str, slice]]:
    """The channels to blend, (N, C), and where each output's channels sit in them.

    Args:
        geom: any (N, ·) per-Gaussian tensor (its N, dtype and device make the empty result).
        depths: (N,) camera z; colors (N, 3) | None; features (N, F) | None.
        keep_half: a lone float16/bfloat16 feature block stays in its dtype (blended per chunk by the
            torch path); otherwise every block is converted to ``dtype``.
    """
    parts, slices, start = [], {}, 0
    for name, tensor in (("rgb", colors), ("features", features), ("depth", depths[:, None])):
        if name in outputs:
            parts.append(tensor)
            slices[name] = slice(start, start + tensor.shape[1])
            start += tensor.shape[1]
    if len(parts) == 1:
        kept = (dtype, torch.float16, torch.bfloat16) if keep_half else (dtype,)
        values = parts[0] if parts[0].dtype in kept else parts[0].to(dtype)
    else:
        values = torch.cat([p.to(dtype) for p in parts], dim=-1) if parts else geom.new_zeros(geom.shape[0], 0)
    return values, slices


def output_maps(accum: torch.Tensor, trans: torch.Tensor, slices: dict[str, slice], *, bg_rgb, bg_feat,
                outputs: tuple[str, ...]) -> dict:
    """"rgb", "features", "depth" and "alpha" maps from accum (H, W, C) = Σ w·values and trans (H, W, 1)."""
    alpha = 1.0 - trans
    out: dict = {}
    if "rgb" in outputs:
        out["rgb"] = over_background(accum[..., slices["rgb"]], trans, bg_rgb)
    if "features" in outputs:
        out["features"] = over_background(accum[..., slices["features"]], trans, bg_feat)
    if "depth" in outputs:
        has = alpha > DEPTH_ALPHA_EPS
        safe = torch.where(has, alpha, torch.ones_like(alpha))
        out["depth"] = torch.where(has, accum[..., slices["depth"]] / safe, torch.zeros_like(alpha))
    if "alpha" in outputs:
        out["alpha"] = alpha
    return out


def over_background(accum: torch.Tensor, trans: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """accum + T·background; a black background costs no pass over the image."""
    if not background.requires_grad and not bool(background.any()):
        return accum
    return accum + trans * background
