"""The pure-torch backend: projection → tile binning → tile rasterizer with a hand-written backward."""
from __future__ import annotations

import torch

from ..scene.camera import Camera
from . import cpu_kernels, kernel_backend
from .binning import bin_gaussians
from .compose import output_maps, stack_values
from .options import BlendWeights, RasterOptions
from .projection import project_gaussians
from .rasterizer import RasterizeTiles, tiles_to_image


def rasterize_torch(means: torch.Tensor, rotations: torch.Tensor, log_scales: torch.Tensor,
                    opacity_logits: torch.Tensor, camera: Camera, *, colors: torch.Tensor | None,
                    features: torch.Tensor | None, bg_rgb: torch.Tensor | None, bg_feat: torch.Tensor | None,
                    outputs: tuple[str, ...], options: RasterOptions, dtype: torch.dtype) -> dict:
    """Inputs already checked by :func:`~fourlegs_engine.render.rasterize`; same outputs. Served by the
    fused kernels of :mod:`.kernel_backend` where they apply (``RasterOptions(kernel="v2")``)."""
    if kernel_backend.applies(options, outputs, means.device, features, dtype):
        return kernel_backend.rasterize_kernels(means, rotations, log_scales, opacity_logits, camera, colors=colors,
                                                features=features, bg_rgb=bg_rgb, bg_feat=bg_feat, outputs=outputs,
                                                options=options, dtype=dtype)
    proj = project_gaussians(means, rotations, log_scales, opacity_logits, camera, options, dtype)
    channels = (3 if "rgb" in outputs else 0) + (features.shape[1] if "features" in outputs else 0) + 1
    binning = bin_gaussians(proj, camera.width, camera.height, options.tile_size, channels)
    geom = torch.cat([proj.means2d, proj.conics, proj.opacities[:, None]], dim=-1)
    return composite(geom, proj.depths, binning, colors=colors, features=features, bg_rgb=bg_rgb,
                     bg_feat=bg_feat, outputs=outputs, options=options, dtype=dtype)


def composite(geom: torch.Tensor, depths: torch.Tensor, binning, *, colors, features, bg_rgb, bg_feat,
              outputs: tuple[str, ...], options: RasterOptions, dtype: torch.dtype) -> dict:
    """Blend the requested channels and assemble the output maps.

    Args:
        geom: (N,6) screen-space mx, my, conic a, b, c, opacity. depths: (N,) camera z.
    """
    N = geom.shape[0]
    # one channel group is blended straight from its own storage (float16 features stay float16 in
    # memory and are widened per chunk: half the gather traffic)
    values, slices = stack_values(geom, depths, colors=colors, features=features, outputs=outputs, dtype=dtype,
                                  keep_half=True)
    want_median, want_weights = "depth_median" in outputs, "weights" in outputs
    if not (want_median or want_weights) and cpu_kernels.usable(options, geom, values):
        accum, trans = cpu_kernels.blend_tiles(geom, binning, values, options, dtype)  # (H,W,C), (H,W,1)
    else:
        accum_t, trans_t, median_t, pix, gid, wt = RasterizeTiles.apply(
            geom, values, binning, options, want_median, want_weights)
        accum = tiles_to_image(accum_t, binning)
        trans = tiles_to_image(trans_t, binning)  # (H,W,1)
    out = output_maps(accum, trans, slices, bg_rgb=bg_rgb, bg_feat=bg_feat, outputs=outputs)
    if "depth_median" in outputs:
        ids = tiles_to_image(median_t, binning)
        picked = depths.to(dtype)[ids.clamp_min(0)] if N else torch.zeros_like(trans)
        out["depth_median"] = torch.where(ids >= 0, picked, torch.zeros_like(picked))
    if "weights" in outputs:
        out["weights"] = BlendWeights(pixel=pix, gaussian=gid, weight=wt, width=binning.width,
                                      height=binning.height)
    return out


def splat_torch(means: torch.Tensor, rotations: torch.Tensor, log_scales: torch.Tensor,
                opacity_logits: torch.Tensor, camera: Camera, pixel_values: torch.Tensor,
                options: RasterOptions, dtype: torch.dtype, out: torch.Tensor | None = None) -> torch.Tensor:
    """(H,W,S) per-pixel values -> (N,S) Σ_p w_i(p)·values(p); see :func:`~fourlegs_engine.render.splat`."""
    from .rasterizer import rasterize_forward
    if kernel_backend.applies(options, ("features",), means.device, None, dtype):
        return kernel_backend.splat_kernels(means, rotations, log_scales, opacity_logits, camera, pixel_values, options,
                                            dtype, out)
    with torch.no_grad():
        proj = project_gaussians(means, rotations, log_scales, opacity_logits, camera, options, dtype)
        binning = bin_gaussians(proj, camera.width, camera.height, options.tile_size, pixel_values.shape[-1])
        geom = torch.cat([proj.means2d, proj.conics, proj.opacities[:, None]], dim=-1)
        if cpu_kernels.usable(options, geom, pixel_values):
            S = pixel_values.shape[-1]
            if out is None:
                out = torch.zeros(means.shape[0], S, dtype=dtype)
            return cpu_kernels.splat_tiles(geom, binning, pixel_values.reshape(-1, S), options, out)
        ts = binning.tile_size
        S = pixel_values.shape[-1]
        padded = pixel_values.new_zeros(binning.tiles_y * ts, binning.tiles_x * ts, S)
        padded[:binning.height, :binning.width] = pixel_values
        res = rasterize_forward(geom, geom.new_zeros(geom.shape[0], 0), binning, options,
                                splat=padded.reshape(-1, S), splat_out=out)
    return res.splatted
