"""The fused CPU path (``RasterOptions(kernel="v2")``): projection → per-tile lists → SIMD lane
kernels, forward and backward, on worker threads that block while idle.

The projection is one fused pass each way (:mod:`.kernel_projection`), the lists come from
:mod:`.tile_lists`, and the blending is one :class:`TileBlend` autograd function whose forward and
backward are the kernels of :mod:`.blend_kernels` and :mod:`.backward_kernels`; autograd chains them.
"""
from __future__ import annotations

import numpy as np
import torch

from ..scene.camera import Camera
from ..threads import kernel_thread_count
from . import backward_kernels, blend_kernels, cpu_kernels
from .compose import output_maps, stack_values
from .kernel_projection import project_gaussians_fused
from .options import RasterOptions
from .projection import Projected
from .tile_lists import TileLists, build_tile_lists, kernel_tile_shape

#: outputs the fused kernels produce ("depth_median" and "weights" stay on the torch path)
KERNEL_OUTPUTS = frozenset({"rgb", "features", "depth", "alpha"})
#: threads of a backward pass that needs value gradients each add into their own (N, C) buffer;
#: beyond this many bytes of buffers the pass runs on one thread
GRAD_BUFFER_BUDGET = 256 << 20
#: a worker thread is worth starting for about this many busy tiles
TILES_PER_WORKER = 32


def applies(options: RasterOptions, outputs: tuple[str, ...], device: torch.device, features: torch.Tensor | None,
            dtype: torch.dtype) -> bool:
    """Whether :func:`rasterize_kernels` serves this call: numba present, ``cpu_kernel`` with
    ``kernel="v2"``, CPU tensors, only rgb/features/depth/alpha, and no half-precision features that
    need a gradient."""
    if not (blend_kernels.numba is not None and options.cpu_kernel and options.kernel == "v2"
            and torch.device(device).type == "cpu" and set(outputs) <= KERNEL_OUTPUTS):
        return False
    half_grad = (features is not None and "features" in outputs and features.dtype != dtype
                 and features.requires_grad and torch.is_grad_enabled())
    return not half_grad


def _needs_grad(*tensors: torch.Tensor | None) -> bool:
    return torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in tensors)


def tile_lists(proj: Projected, camera: Camera, options: RasterOptions, dtype: torch.dtype,
               channels: int) -> TileLists:
    """The per-tile lists of ``proj`` for ``camera``'s image, tiles shaped for ``channels`` blended values."""
    tile_w, tile_h = kernel_tile_shape(options.tile_size, channels)
    return build_tile_lists(proj.means2d, proj.conics, proj.opacities, proj.depths, proj.visible, proj.bounds,
                            camera.width, camera.height, tile_w, tile_h, alpha_floor(options, dtype))


def alpha_floor(options: RasterOptions, dtype: torch.dtype) -> float:
    """The largest ``dtype`` number below alpha_min: α at or below it is not drawn."""
    t = torch.tensor(options.alpha_min, dtype=dtype)
    return float(torch.nextafter(t, torch.zeros_like(t)))


def rasterize_kernels(means: torch.Tensor, rotations: torch.Tensor, log_scales: torch.Tensor,
                      opacity_logits: torch.Tensor, camera: Camera, *, colors: torch.Tensor | None,
                      features: torch.Tensor | None, bg_rgb: torch.Tensor | None, bg_feat: torch.Tensor | None,
                      outputs: tuple[str, ...], options: RasterOptions, dtype: torch.dtype) -> dict:
    """Inputs already checked by :func:`~fourlegs_engine.render.rasterize`; its outputs (when
    :func:`applies`)."""
    proj = project_gaussians_fused(means, rotations, log_scales, opacity_logits, camera, options, dtype)
    values, slices = stack_values(proj.means2d, proj.depths, colors=colors, features=features, outputs=outputs,
                                  dtype=dtype, keep_half=False)
    lists = tile_lists(proj, camera, options, dtype, values.shape[1])
    H, W = camera.height, camera.width
    if _needs_grad(proj.means2d, proj.conics, proj.opacities, values):
        geom = torch.cat([proj.means2d, proj.conics, proj.opacities[:, None]], dim=-1)
        accum, trans = TileBlend.apply(geom, values, lists, options)
    else:
        accum, trans = blend_forward(lists, values.detach(), options)
    return output_maps(accum.view(H, W, -1), trans.view(H, W, 1), slices, bg_rgb=bg_rgb, bg_feat=bg_feat,
                       outputs=outputs)


def splat_kernels(means, rotations, log_scales, opacity_logits, camera: Camera, pixel_values: torch.Tensor,
                  options: RasterOptions, dtype: torch.dtype, out: torch.Tensor | None) -> torch.Tensor:
    """(H,W,S) per-pixel values -> (N,S) Σ_p w_i(p)·values(p) (added to ``out`` when given)."""
    with torch.no_grad():
        proj = project_gaussians_fused(means, rotations, log_scales, opacity_logits, camera, options, dtype)
        S = pixel_values.shape[-1]
        lists = tile_lists(proj, camera, options, dtype, S)
        if out is None:
            out = _host_zeros((means.shape[0], S), dtype)
        grad_pixels = np.ascontiguousarray(pixel_values.reshape(-1, S).to(dtype).numpy())
        _backward_threads(lists, None, grad_pixels, None, None, None, options, out, None, workers=1)
    return out


# ------------------------------------------------------------------------------------------ passes
def blend_forward(lists: TileLists, values: torch.Tensor, options: RasterOptions
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """accum (H·W, C) = Σ w·values and the final transmittance (H·W,), in ``values``' dtype.

    Args:
        values: (N, C) float32 or float64 (other float dtypes are converted).
    """
    dtype = values.dtype if values.dtype in (torch.float32, torch.float64) else torch.float32
    n_pix = lists.width * lists.height
    C = values.shape[1]
    # every tile is written by the kernel (empty ones with zeros and T = 1): no separate fill pass
    accum = _host_empty((n_pix, C), dtype)
    trans = _host_empty((n_pix,), dtype)
    tiles = np.arange(lists.num_tiles)
    vals = values.detach().to(dtype).numpy()
    shape = (lists.tiles_x, lists.tile_w, lists.tile_h, lists.width, lists.height)
    rules = (alpha_floor(options, dtype), float(options.alpha_max), float(options.transmittance_min))
    args = (lists.tile_offsets, lists.tile_ranks, lists.order, lists.packed, lists.boxes, *shape,
            np.ascontiguousarray(vals), *rules, accum.numpy(), trans.numpy())
    kernel = blend_kernels._blend_narrow if C <= blend_kernels.NARROW_CHANNELS else blend_kernels._blend_wide
    cpu_kernels.run_on_workers(lambda part, _: kernel(part, *args), tiles, _workers(_busy_tiles(lists).size))
    return accum, trans


def blend_backward(lists: TileLists, values: torch.Tensor, grad_accum: torch.Tensor, grad_trans: torch.Tensor,
                   trans: torch.Tensor, accum: torch.Tensor, options: RasterOptions, need_values: bool,
                   need_geometry: bool) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """(∂L/∂geom (N, 6) or None, ∂L/∂values (N, C) or None) from ∂L/∂accum (H·W, C) and ∂L/∂T (H·W,)."""
    dtype = accum.dtype
    N, C = values.shape
    grad_values = _host_zeros((N, C), dtype) if need_values else None
    grad_geometry = torch.zeros(N, 6, dtype=torch.float64) if need_geometry else None
    if _busy_tiles(lists).size:
        workers = _workers(_busy_tiles(lists).size)
        if need_values and workers > 1 and N * C * dtype.itemsize * workers > GRAD_BUFFER_BUDGET:
            workers = 1
        _backward_threads(lists, np.ascontiguousarray(values.detach().to(dtype).numpy()),
                          np.ascontiguousarray(grad_accum.detach().to(dtype).numpy()),
                          np.ascontiguousarray(grad_trans.detach().to(dtype).numpy()),
                          trans.detach().numpy(), accum.detach().numpy(), options, grad_values, grad_geometry,
                          workers=workers)
    return (grad_geometry.to(dtype) if grad_geometry is not None else None), grad_values


def _backward_threads(lists: TileLists, values, grad_accum, grad_trans, trans, accum, options: RasterOptions,
                      grad_values: torch.Tensor | None, grad_geometry: torch.Tensor | None, workers: int) -> None:
    """Run the backward kernel (the splat kernel when only value gradients are needed) over every busy
    tile on ``workers`` threads, each adding into its own gradient buffers (the first worker's are the
    outputs themselves)."""
    dtype = torch.float64 if grad_accum.dtype == np.float64 else torch.float32
    C = grad_accum.shape[1]
    need_values, need_geometry = grad_values is not None, grad_geometry is not None
    gv_main = grad_values.numpy() if need_values else np.zeros((0, C), dtype=grad_accum.dtype)
    gg_main = grad_geometry.numpy() if need_geometry else np.zeros((0, 6), dtype=np.float64)
    buffers = [(gv_main, gg_main)] + [
        (np.zeros_like(gv_main), np.zeros_like(gg_main)) for _ in range(workers - 1)]
    busy = _busy_tiles(lists)
    grid = (lists.tile_offsets, lists.tile_ranks, lists.order, lists.packed, lists.boxes, lists.tiles_x,
            lists.tile_w, lists.tile_h, lists.width, lists.height)
    rules = (alpha_floor(options, dtype), float(options.alpha_max), float(options.transmittance_min))
    if need_geometry:
        common = (*grid, values, grad_accum, grad_trans, trans, accum, *rules, need_values, need_geometry)
        backward = backward_kernels._backward_narrow if C <= blend_kernels.NARROW_CHANNELS else backward_kernels._backward
        kernel = lambda part, k: backward(part, *common, *buffers[k])  # noqa: E731
    else:
        kernel = lambda part, k: blend_kernels._splat(part, *grid, grad_accum, *rules, buffers[k][0])  # noqa: E731
    cpu_kernels.run_on_workers(kernel, busy, workers)
    if workers > 1:
        for gv, gg in buffers[1:]:
            gv_main += gv
            gg_main += gg


class TileBlend(torch.autograd.Function):
    """(geom (N, 6) mx, my, conic a, b, c, opacity; values (N, C)) -> (accum (H·W, C), T_final (H·W,))."""

    @staticmethod
    def forward(ctx, geom, values, lists, options):  # noqa: D401
        accum, trans = blend_forward(lists, values.detach(), options)
        ctx.lists, ctx.options = lists, options
        ctx.values_dtype = values.dtype
        ctx.save_for_backward(values, accum, trans)
        return accum, trans

    @staticmethod
    def backward(ctx, grad_accum, grad_trans):
        values, accum, trans = ctx.saved_tensors
        if grad_accum is None:
            grad_accum = torch.zeros_like(accum)
        if grad_trans is None:
            grad_trans = torch.zeros_like(trans)
        grad_geom, grad_values = blend_backward(ctx.lists, values, grad_accum.contiguous(), grad_trans.contiguous(),
                                                trans, accum, ctx.options, need_values=ctx.needs_input_grad[1],
                                                need_geometry=ctx.needs_input_grad[0])
        if grad_values is not None:
            grad_values = grad_values.to(ctx.values_dtype)
        return grad_geom, grad_values, None, None


# ----------------------------------------------------------------------------------------- helpers
def _host_empty(shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
    """An uninitialized CPU tensor whose memory numpy allocated: numpy asks the kernel for huge pages on
    large blocks, so a 100 MB feature image costs a few page faults instead of tens of thousands
    (first touch of torch's own allocation is several times slower than filling it)."""
    return torch.from_numpy(np.empty(shape, dtype=_NUMPY_DTYPES[dtype]))


def _host_zeros(shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
    """As :func:`_host_empty`, zero-filled."""
    return torch.from_numpy(np.zeros(shape, dtype=_NUMPY_DTYPES[dtype]))


_NUMPY_DTYPES = {torch.float32: np.float32, torch.float64: np.float64}


def _busy_tiles(lists: TileLists) -> np.ndarray:
    return np.flatnonzero(np.diff(lists.tile_offsets) > 0)


def _workers(busy_tiles: int) -> int:
    return max(1, min(kernel_thread_count(), busy_tiles // TILES_PER_WORKER))


def count_work(means: torch.Tensor, rotations: torch.Tensor, log_scales: torch.Tensor, opacity_logits: torch.Tensor,
               camera: Camera, options: RasterOptions | None = None, channels: int = 3) -> dict[str, int]:
    """How much work one view is, in pixel–Gaussian pairs (for the benchmark's floor):

    * ``in_boxes``: pixels inside the visible Gaussians' bounding boxes;
    * ``in_footprints``: of those, the ones where α ≥ alpha_min (ignoring occlusion);
    * ``evaluated``: the pairs the v2 forward evaluates (each pair's box columns in the tile, on the rows
      that still have pixels to blend);
    * ``blended``: the pairs actually blended (front to back, until each pixel stops);
    * ``tile_pairs``, ``tile_pairs_in_boxes``: tile–Gaussian list entries of the v2 lists, and how many
      the bounding boxes alone would give; ``visible``: Gaussians drawn.
    """
    options = (options or RasterOptions()).check()
    dtype = means.dtype if means.dtype in (torch.float32, torch.float64) else torch.float32
    with torch.no_grad():
        proj = project_gaussians_fused(means, rotations, log_scales, opacity_logits, camera, options, dtype)
        lists = tile_lists(proj, camera, options, dtype, channels)
        counters = np.zeros(len(backward_kernels.WORK_COUNTERS), dtype=np.int64)
        backward_kernels._count(lists.tile_offsets, lists.tile_ranks, lists.packed, lists.boxes, lists.tiles_x,
                             lists.tile_w, lists.tile_h, lists.width, lists.height, alpha_floor(options, dtype),
                             float(options.alpha_max), float(options.transmittance_min), counters)
    work = {name: int(v) for name, v in zip(backward_kernels.WORK_COUNTERS, counters)}
    work.update(tile_pairs=lists.num_pairs, tile_pairs_in_boxes=lists.pairs_in_boxes, visible=lists.num_visible)
    return work
