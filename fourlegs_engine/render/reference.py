"""Straightforward dense rasterizers: the baselines for speed and the autograd reference.

``rasterize_reference`` shares the projection with the fast path but blends with plain torch ops
and autograd (no hand-written backward, no batching tricks):

- ``tile_size=None`` ("oracle" mode): every pixel × every visible Gaussian, depth-sorted, no tiles
  and no footprint bounds. Run in float64 this is the brute-force oracle of the benchmark.
- ``tile_size=s`` ("dense-tile" mode): a Python loop over s×s tiles, each tile a dense
  (pixels × Gaussians overlapping the tile) problem.

Both return the same dict as :func:`~fourlegs_engine.render.rasterize` for "rgb", "features",
"depth" and "alpha".
"""
from __future__ import annotations

from typing import Sequence

import torch

from ..scene.camera import Camera
from .binning import bin_gaussians
from .options import RasterOptions
from .projection import project_gaussians


def blend_dense(px: torch.Tensor, py: torch.Tensor, geom: torch.Tensor, values: torch.Tensor,
                opts: RasterOptions) -> tuple[torch.Tensor, torch.Tensor]:
    """Blend K depth-sorted Gaussians over P pixels with differentiable ops.

    Args: px, py (P,) pixel-centre coordinates; geom (K,6) mx, my, conic a, b, c, opacity;
        values (K,C).
    Returns: Σ w·v (P,C) and final transmittance (P,).
    """
    mx, my, ca, cb, cc, o = geom.unbind(-1)
    dx = px[:, None] - mx[None, :]
    dy = py[:, None] - my[None, :]
    power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
    alpha = torch.clamp(o * torch.exp(power), max=opts.alpha_max)
    alpha = torch.where(alpha >= opts.alpha_min, alpha, torch.zeros_like(alpha))
    t_incl = torch.cumprod(1.0 - alpha, dim=-1)
    blend = t_incl >= opts.transmittance_min
    alpha = torch.where(blend, alpha, torch.zeros_like(alpha))
    t_excl = torch.cat([torch.ones_like(t_incl[:, :1]), t_incl[:, :-1]], dim=-1)
    t_final = torch.where(blend, t_incl, torch.ones_like(t_incl)).amin(dim=-1) if alpha.shape[1] else \
        torch.ones_like(px)
    w = alpha * t_excl
    return w @ values, t_final


def rasterize_reference(means: torch.Tensor, rotations: torch.Tensor, log_scales: torch.Tensor,
                        opacity_logits: torch.Tensor, camera: Camera, *, colors: torch.Tensor | None = None,
                        features: torch.Tensor | None = None, background: torch.Tensor | None = None,
                        outputs: Sequence[str] = ("rgb",), options: RasterOptions | None = None,
                        tile_size: int | None = None, pixel_chunk: int = 4096) -> dict[str, torch.Tensor]:
    """Dense reference render (see module docstring). Working dtype = ``means.dtype``."""
    opts = options or RasterOptions()
    dtype = means.dtype
    W, H = camera.width, camera.height
    proj = project_gaussians(means, rotations, log_scales, opacity_logits, camera, opts, dtype)
    geom = torch.cat([proj.means2d, proj.conics, proj.opacities[:, None]], dim=-1)
    parts, names = [], []
    for name, t in (("rgb", colors), ("features", features), ("depth", proj.depths[:, None])):
        if name in outputs:
            parts.append(t.to(dtype))
            names.append((name, t.shape[1]))
    values = torch.cat(parts, -1) if parts else geom.new_zeros(geom.shape[0], 0)
    ys, xs = torch.meshgrid(torch.arange(H, device=means.device), torch.arange(W, device=means.device),
                            indexing="ij")
    px_all = xs.reshape(-1).to(dtype) + 0.5
    py_all = ys.reshape(-1).to(dtype) + 0.5
    if tile_size is None:
        # the oracle ignores footprint bounds: every in-range Gaussian against every pixel
        in_range = _in_range(proj, camera)
        order = torch.nonzero(in_range).squeeze(1)
        order = order[torch.sort(proj.depths.detach()[order], stable=True).indices]
        g, v = geom[order], values[order]
        acc, tr = [], []
        for s in range(0, H * W, pixel_chunk):
            a, t = blend_dense(px_all[s:s + pixel_chunk], py_all[s:s + pixel_chunk], g, v, opts)
            acc.append(a)
            tr.append(t)
        accum, trans = torch.cat(acc), torch.cat(tr)
    else:
        binning = bin_gaussians(proj, W, H, tile_size)
        offsets = binning.tile_offsets.tolist()
        pix_index, acc, tr = [], [], []
        for tile in range(binning.num_tiles):
            tx, ty = tile % binning.tiles_x, tile // binning.tiles_x
            x = torch.arange(tx * tile_size, min(W, tx * tile_size + tile_size), device=means.device)
            y = torch.arange(ty * tile_size, min(H, ty * tile_size + tile_size), device=means.device)
            yy, xx = torch.meshgrid(y, x, indexing="ij")
            ids = binning.gaussian_ids[offsets[tile]:offsets[tile + 1]]
            a, t = blend_dense(xx.reshape(-1).to(dtype) + 0.5, yy.reshape(-1).to(dtype) + 0.5, geom[ids],
                               values[ids], opts)
            pix_index.append((yy * W + xx).reshape(-1))
            acc.append(a)
            tr.append(t)
        inv = torch.argsort(torch.cat(pix_index))
        accum, trans = torch.cat(acc)[inv], torch.cat(tr)[inv]
    accum = accum.reshape(H, W, -1)
    trans = trans.reshape(H, W, 1)
    alpha = 1.0 - trans
    out, start = {}, 0
    for name, c in names:
        chunk = accum[..., start:start + c]
        start += c
        if name == "depth":
            has = alpha > 1e-6
            out[name] = torch.where(has, chunk / torch.where(has, alpha, torch.ones_like(alpha)),
                                    torch.zeros_like(alpha))
        else:
            bg = background if (background is not None and name == "rgb") else None
            out[name] = chunk + trans * bg.to(dtype) if bg is not None else chunk
    if "alpha" in outputs:
        out["alpha"] = alpha
    return out


def _in_range(proj, camera: Camera) -> torch.Tensor:
    z = proj.depths.detach()
    finite = torch.isfinite(proj.conics.detach()).all(-1) & torch.isfinite(proj.means2d.detach()).all(-1)
    return (z >= camera.near) & (z <= camera.far) & finite & (proj.opacities.detach() > 0)
