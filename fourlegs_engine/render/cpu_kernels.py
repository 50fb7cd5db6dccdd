"""Fused CPU kernels (numba) for the rasterizer's inference passes: blending and its transpose.

* :func:`blend_tiles` — front-to-back blending of per-Gaussian values into pixels (rgb, features,
  depth and alpha of :func:`~fourlegs_engine.render.rasterize` when no gradient is needed: the query's
  relevancy maps, label coverage, the Blender render engine);
* :func:`splat_tiles` — the transpose, :func:`~fourlegs_engine.render.splat`, which the learning-free
  lift runs once per training view.

The batched torch formulation in :mod:`.rasterizer` evaluates α for every (pixel, list entry) of a tile
batch as dense tensors; these kernels walk each tile's depth-sorted list the way the 3DGS CUDA kernel
does (every pixel of the tile keeps its own transmittance), so they skip the zero weights and the
dense intermediates. Same α, clamping, skipping and termination rules, so they agree with the torch
path up to float rounding (tested against it and, through it, against the float64 oracle). The torch
path stays the reference, the only path with gradients, and the fallback where numba is not installed
(it is an optional speed-up, e.g. inside Blender).
"""
from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import torch

from ..jit_cache import JIT_CACHE
from ..threads import kernel_thread_count

try:  # pragma: no cover - exercised when numba is missing
    import numba
except ImportError:  # pragma: no cover
    numba = None


def available() -> bool:
    """True when numba is importable (the fused kernel can run)."""
    return numba is not None


def _tile_pixels_py(tile, tiles_x, tile_size, width, height, rows, lxs, lys, transmittance):  # pragma: no cover
    """Pack the pixels of ``tile`` that lie inside the image: their row in the (H·W) image, their
    tile-local centre (x + 0.5, y + 0.5) and T = 1. Returns how many there are."""
    x0 = (tile % tiles_x) * tile_size
    y0 = (tile // tiles_x) * tile_size
    live = 0
    for py in range(tile_size):
        for px in range(tile_size):
            if y0 + py < height and x0 + px < width:
                rows[live] = (y0 + py) * width + x0 + px
                lxs[live] = px + 0.5
                lys[live] = py + 0.5
                transmittance[live] = 1.0
                live += 1
    return live


_tile_pixels = numba.njit(nogil=True, cache=JIT_CACHE, inline="always")(_tile_pixels_py) if numba is not None else None


def _blend_tiles_py(tiles, coef, gids, tile_offsets, tiles_x, tile_size, width, height, values, alpha_floor,
                    alpha_max, transmittance_min, accum, transmittance_out):  # pragma: no cover - numba
    """accum[p] += Σ_g w_g(p)·values[g] and transmittance_out[p] = T after blending, for the pixels of
    the listed ``tiles`` (tiles own disjoint pixels, so disjoint tile lists can run concurrently).

    coef, gids, tile_offsets: as for :func:`_splat_tiles_py`; values: (N, C); accum: (H·W, C) zeros;
    transmittance_out: (H·W,) ones.
    """
    channels = values.shape[1]
    power_floor = math.log(alpha_floor)
    n_pix = tile_size * tile_size
    transmittance = np.empty(n_pix, dtype=np.float64)
    stopped = np.empty(n_pix, dtype=np.bool_)
    rows = np.empty(n_pix, dtype=np.int64)
    lxs = np.empty(n_pix, dtype=np.float64)
    lys = np.empty(n_pix, dtype=np.float64)
    weight_cast = np.empty(1, dtype=accum.dtype)
    for tile in tiles:
        start = tile_offsets[tile]
        end = tile_offsets[tile + 1]
        if start == end:
            continue
        live = _tile_pixels(tile, tiles_x, tile_size, width, height, rows, lxs, lys, transmittance)
        stopped[:live] = False
        saturated = 0
        for m in range(start, end):
            c0, c1, c2, c3, c4, c5 = coef[m, 0], coef[m, 1], coef[m, 2], coef[m, 3], coef[m, 4], coef[m, 5]
            g = gids[m]
            for p in range(live):
                if stopped[p]:
                    continue
                lx = lxs[p]
                ly = lys[p]
                power = c0 * lx * lx + c1 * lx * ly + c2 * ly * ly + c3 * lx + c4 * ly + c5
                if power <= power_floor:
                    continue
                alpha = math.exp(power)
                if alpha > alpha_max:
                    alpha = alpha_max
                if alpha <= alpha_floor:
                    continue
                t_before = transmittance[p]
                after = t_before * (1.0 - alpha)
                if after < transmittance_min:
                    stopped[p] = True
                    saturated += 1
                    continue
                weight_cast[0] = alpha * t_before
                weight = weight_cast[0]
                row = rows[p]
                for s in range(channels):
                    accum[row, s] += weight * values[g, s]
                transmittance[p] = after
            if saturated == live:
                break
        for p in range(live):
            transmittance_out[rows[p]] = transmittance[p]


def _splat_tiles_py(coef, gids, tile_offsets, tiles_x, tile_size, width, height, values, alpha_floor,
                    alpha_max, transmittance_min, out):  # pragma: no cover - compiled by numba
    """out[g] += Σ_p w_g(p)·values[p] over every tile's pixels, front to back.

    coef: (M, 6) exponent coefficients per (tile, Gaussian) pair (see ``pair_coefficients``);
    gids: (M,) Gaussian ids; tile_offsets: (n_tiles + 1,); values: (H·W, S); out: (N, S).
    ``alpha_floor``: α at or below it is skipped (the float just below alpha_min).

    The list is the outer loop and the tile's pixels the inner one (each pixel keeps its own
    transmittance), so every pair's S-wide sum is formed in a small buffer and added to ``out`` once:
    one scattered row write per pair instead of one per (pixel, Gaussian) fragment.
    """
    n_tiles = tile_offsets.shape[0] - 1
    channels = values.shape[1]
    power_floor = math.log(alpha_floor)
    n_pix = tile_size * tile_size
    transmittance = np.empty(n_pix, dtype=np.float64)
    rows = np.empty(n_pix, dtype=np.int64)
    lxs = np.empty(n_pix, dtype=np.float64)
    lys = np.empty(n_pix, dtype=np.float64)
    acc = np.empty(channels, dtype=out.dtype)
    weight_cast = np.empty(1, dtype=out.dtype)  # the weight in out's dtype keeps the S-loop in one precision (SIMD)
    for tile in range(n_tiles):
        start = tile_offsets[tile]
        end = tile_offsets[tile + 1]
        if start == end:
            continue
        live = _tile_pixels(tile, tiles_x, tile_size, width, height, rows, lxs, lys, transmittance)
        for m in range(start, end):
            c0, c1, c2, c3, c4, c5 = coef[m, 0], coef[m, 1], coef[m, 2], coef[m, 3], coef[m, 4], coef[m, 5]
            touched = False
            saturated = 0
            for p in range(live):
                t_before = transmittance[p]
                if t_before < 0.0:  # this pixel has stopped
                    saturated += 1
                    continue
                lx = lxs[p]
                ly = lys[p]
                power = c0 * lx * lx + c1 * lx * ly + c2 * ly * ly + c3 * lx + c4 * ly + c5
                if power <= power_floor:  # most entries miss most pixels: skip the exp
                    continue
                alpha = math.exp(power)
                if alpha > alpha_max:
                    alpha = alpha_max
                if alpha <= alpha_floor:
                    continue
                after = t_before * (1.0 - alpha)
                if after < transmittance_min:
                    transmittance[p] = -1.0
                    saturated += 1
                    continue
                weight_cast[0] = alpha * t_before
                weight = weight_cast[0]
                row = rows[p]
                if not touched:
                    for s in range(channels):
                        acc[s] = weight * values[row, s]
                    touched = True
                else:
                    for s in range(channels):
                        acc[s] += weight * values[row, s]
                transmittance[p] = after
            if touched:
                g = gids[m]
                for s in range(channels):
                    out[g, s] += acc[s]
            if saturated == live:
                break


_splat_tiles = numba.njit(nogil=True, cache=JIT_CACHE)(_splat_tiles_py) if numba is not None else None
_blend_tiles = numba.njit(nogil=True, cache=JIT_CACHE)(_blend_tiles_py) if numba is not None else None


def _pair_arrays(geom: torch.Tensor, binning: Any, dtype: torch.dtype) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    from .rasterizer import pair_coefficients
    coef, _ = pair_coefficients(geom, binning)
    return (np.ascontiguousarray(coef[:binning.num_pairs].to(dtype).numpy()),
            np.ascontiguousarray(binning.gaussian_ids.numpy()), np.ascontiguousarray(binning.tile_offsets.numpy()))


def _require(out_like: torch.Tensor) -> None:
    if numba is None:
        raise RuntimeError("numba is not installed; the fused CPU kernels are unavailable")
    if out_like.device.type != "cpu":
        raise ValueError("the fused kernels run on CPU tensors only")


def usable(options: Any, *tensors: torch.Tensor) -> bool:
    """Whether :func:`blend_tiles` / :func:`splat_tiles` apply: numba present, ``options.cpu_kernel``,
    CPU tensors, and no gradient to track through them."""
    return (numba is not None and options.cpu_kernel and all(t.device.type == "cpu" for t in tensors)
            and not (torch.is_grad_enabled() and any(t.requires_grad for t in tensors)))


def blend_tiles(geom: torch.Tensor, binning: Any, values: torch.Tensor, options: Any,
                dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Blend per-Gaussian ``values`` (N, C) front to back: -> accum (H, W, C), transmittance (H, W, 1).

    Args:
        geom: (N, 6) screen-space mx, my, conic a, b, c, opacity; binning: the depth-sorted tile lists.
    """
    from .rasterizer import _below
    _require(geom)
    H, W, C = binning.height, binning.width, values.shape[1]
    accum = torch.zeros(H * W, C, dtype=dtype)
    trans = torch.ones(H * W, dtype=dtype)
    if binning.num_pairs:
        coef, gids, offsets = _pair_arrays(geom, binning, dtype)
        args = (coef, gids, offsets, int(binning.tiles_x), int(binning.tile_size), W, H,
                np.ascontiguousarray(values.detach().to(dtype).numpy()), _below(options.alpha_min, dtype),
                float(options.alpha_max), float(options.transmittance_min), accum.numpy(), trans.numpy())
        busy = np.flatnonzero(np.diff(offsets) > 0)
        run_on_workers(lambda part, _: _blend_tiles(part, *args), busy, max(1, min(kernel_thread_count(), busy.size // 64)))
    return accum.view(H, W, C), trans.view(H, W, 1)


def run_on_workers(kernel, tiles: np.ndarray, workers: int) -> None:
    """``kernel(part, k)`` for the k-th of ``workers`` interleaved parts of ``tiles`` (interleaving
    balances the load), on threads that block while idle; the kernels release the GIL."""
    if workers <= 1:
        kernel(tiles, 0)
        return
    with ThreadPoolExecutor(workers) as pool:
        list(pool.map(lambda k: kernel(tiles[k::workers], k), range(workers)))


def splat_tiles(geom: torch.Tensor, binning: Any, pixel_values: torch.Tensor, options: Any,
                out: torch.Tensor) -> torch.Tensor:
    """Σ_p w_g(p)·pixel_values[p] per Gaussian, added to ``out`` (N, S) in place and returned.

    Args:
        geom: (N, 6) as for :func:`blend_tiles`; pixel_values: (H·W, S) in ``out``'s dtype.
    """
    from .rasterizer import _below
    _require(out)
    if not out.is_contiguous():
        raise ValueError("the fused splat needs a contiguous output tensor")
    if binning.num_pairs:
        dtype = out.dtype
        coef, gids, offsets = _pair_arrays(geom, binning, dtype)
        _splat_tiles(coef, gids, offsets, int(binning.tiles_x), int(binning.tile_size), int(binning.width),
                     int(binning.height), np.ascontiguousarray(pixel_values.detach().to(dtype).numpy()),
                     _below(options.alpha_min, dtype), float(options.alpha_max), float(options.transmittance_min),
                     out.numpy())
    return out
