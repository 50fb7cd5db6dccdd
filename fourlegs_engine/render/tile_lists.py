"""Per-tile, depth-ordered Gaussian lists for the fused kernels (:mod:`.blend_kernels`), built in numba.

Differences from the torch binning of :mod:`.binning` (which the batched torch rasterizer keeps using):

* a Gaussian joins a tile only when its footprint ellipse {dᵀΣ⁻¹d ≤ 2 ln(o/α_floor)} reaches a pixel
  centre of that tile (the exact ellipse–rectangle test of :func:`ellipse_reaches_rect`), not every tile
  of its bounding box: a tilted or faint Gaussian no longer drags the empty corners of its box along;
* the visible Gaussians are put in depth order once (a stable LSD radix sort on the bits of the
  working-dtype depth, ties by index like the torch path's stable sort), their screen-space geometry is
  packed in that order (float64, one row per Gaussian, read front to back), and each tile's list is a
  run of increasing ranks into that packed table — no per-pair coefficient table, no global pair sort.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..jit_cache import JIT_CACHE
from .lane_kernels import prefetch_for_write

try:  # pragma: no cover - exercised when numba is missing
    import numba

    from . import lane_llvm  # noqa: F401 (the prefetch hints' code)
except ImportError:  # pragma: no cover
    numba = None

#: columns of :attr:`TileLists.packed`
PACKED_COLUMNS = ("mx", "my", "conic_a", "conic_b", "conic_c", "opacity", "log_opacity", "reach")
N_PACKED = len(PACKED_COLUMNS)
#: relative slack of the ellipse–tile test (keeps a pixel centre that rounding puts on the border)
REACH_SLACK = 1e-9
#: the tile side the fused kernels use for tile_size="auto" when many channels are blended
AUTO_TILE_SIZE = 32
#: (tile_w, tile_h) for tile_size="auto" when at most WIDE_TILE_MAX_CHANNELS channels are blended
WIDE_TILE = (128, 32)
WIDE_TILE_MAX_CHANNELS = 8
RADIX_BITS = 11
#: Gaussians ahead whose packed rows the list build asks the CPU to fetch before writing them
SCATTER_PREFETCH = 16


@dataclass
class TileLists:
    """Depth-ordered Gaussian lists per square pixel tile.

    Attributes:
        order: (V,) int64 Gaussian index of each visible Gaussian, front to back (its rank).
        packed: (V, 8) float64 per rank: mx, my (pixel coordinates, centres at +0.5), the conic a, b, c
            (dᵀΣ⁻¹d = a dx² + 2b dx dy + c dy²), opacity o, ln o and the reach q = 2 ln(o/α_floor)
            (α ≥ α_min exactly where dᵀΣ⁻¹d ≤ q).
        boxes: (V, 4) int64 inclusive pixel bounds x0, x1, y0, y1 per rank.
        tile_offsets: (n_tiles + 1,) int64; tile t lists ``tile_ranks[tile_offsets[t]:tile_offsets[t+1]]``.
        tile_ranks: (M,) int32 ranks, increasing (front to back) inside each tile.
        tiles_x, tiles_y, tile_w, tile_h, width, height: the grid (tile t = ty·tiles_x + tx covers
            pixels [tx·tile_w, (tx + 1)·tile_w) × [ty·tile_h, (ty + 1)·tile_h)) and the image size.
        pairs_in_boxes: tile–Gaussian pairs the bounding boxes alone would give (for the benchmark).
    """

    order: np.ndarray
    packed: np.ndarray
    boxes: np.ndarray
    tile_offsets: np.ndarray
    tile_ranks: np.ndarray
    tiles_x: int
    tiles_y: int
    tile_w: int
    tile_h: int
    width: int
    height: int
    pairs_in_boxes: int

    @property
    def num_tiles(self) -> int:
        return self.tiles_x * self.tiles_y

    @property
    def num_pairs(self) -> int:
        return int(self.tile_ranks.shape[0])

    @property
    def num_visible(self) -> int:
        return int(self.order.shape[0])


def _ellipse_reaches_rect_py(mx, my, a, b, c, reach, x_lo, x_hi, y_lo, y_hi):  # pragma: no cover - numba
    """Whether min over the rectangle [x_lo, x_hi] × [y_lo, y_hi] of Q(x − mx, y − my) ≤ reach, with
    Q(dx, dy) = a dx² + 2b dx dy + c dy² (positive definite; anything else counts as reaching)."""
    if not (a > 0.0 and c > 0.0):
        return True
    if x_lo <= mx <= x_hi and y_lo <= my <= y_hi:
        return True
    best = math.inf
    for k in range(4):
        if k < 2:  # vertical edge: dx fixed, the best dy clamped into the edge
            dx = (x_lo if k == 0 else x_hi) - mx
            dy = min(max(-b * dx / c, y_lo - my), y_hi - my)
        else:
            dy = (y_lo if k == 2 else y_hi) - my
            dx = min(max(-b * dy / a, x_lo - mx), x_hi - mx)
        value = a * dx * dx + 2.0 * b * dx * dy + c * dy * dy
        if value < best:
            best = value
    if math.isnan(best):
        return True
    return best <= reach + REACH_SLACK * (abs(reach) + 1.0)


def _radix_order_py(keys, key_bits, out):  # pragma: no cover - compiled by numba
    """Stable LSD radix sort: ``out`` (V,) ← 0..V−1 ordered by the unsigned integer ``keys`` (V,) (only
    the low ``key_bits`` bits are looked at); equal keys keep index order."""
    n = keys.shape[0]
    buckets = 1 << RADIX_BITS
    mask = np.uint64(buckets - 1)
    src = np.arange(n)
    dst = np.empty(n, dtype=np.int64)
    counts = np.empty(buckets, dtype=np.int64)
    shift = 0
    while shift < key_bits:
        counts[:] = 0
        sh = np.uint64(shift)
        for i in range(n):
            counts[(np.uint64(keys[src[i]]) >> sh) & mask] += 1
        if counts.max() < n:  # a digit that is the same everywhere changes nothing
            total = 0
            for d in range(buckets):
                cnt = counts[d]
                counts[d] = total
                total += cnt
            for i in range(n):
                j = src[i]
                d = (np.uint64(keys[j]) >> sh) & mask
                dst[counts[d]] = j
                counts[d] += 1
            src, dst = dst, src
        shift += RADIX_BITS
    out[:] = src


def _build_lists_py(visible, depth_bits, key_bits, means2d, conics, opacities, bounds, tile_w, tile_h, tiles_x,
                    n_tiles, log_alpha_floor, tile_offsets):  # pragma: no cover - compiled by numba
    """Returns (order, packed, boxes, tile_ranks, pairs_in_boxes) and fills tile_offsets; see
    :class:`TileLists`. depth_bits (N,): the depths' IEEE bits as unsigned integers (positive floats
    sort like their bits); the other arrays in the working dtype."""
    n_vis = 0
    for g in range(visible.shape[0]):
        n_vis += visible[g]
    visible_ids = np.empty(n_vis, dtype=np.int64)
    keys = np.empty(n_vis, dtype=depth_bits.dtype)
    j = 0
    for g in range(visible.shape[0]):
        if visible[g]:
            visible_ids[j] = g
            keys[j] = depth_bits[g]
            j += 1
    order = np.empty(n_vis, dtype=np.int64)
    packed = np.empty((n_vis, N_PACKED), dtype=np.float64)
    boxes = np.empty((n_vis, 4), dtype=np.int64)
    ranked = np.empty(n_vis, dtype=np.int64)
    _radix_order(keys, key_bits, ranked)
    rank_of = np.empty(n_vis, dtype=np.int64)
    for r in range(n_vis):
        rank_of[ranked[r]] = r
    # read the Gaussians in memory order and scatter them to their ranks (random writes are cheaper
    # than random reads of five arrays)
    in_boxes = 0
    for j in range(n_vis):
        if j + SCATTER_PREFETCH < n_vis:
            ahead = rank_of[j + SCATTER_PREFETCH]
            prefetch_for_write(packed, ahead)
            prefetch_for_write(boxes, ahead)
            prefetch_for_write(order, ahead)
        g = visible_ids[j]
        r = rank_of[j]
        order[r] = g
        o = np.float64(opacities[g])
        log_o = math.log(o)
        packed[r, 0] = means2d[g, 0]
        packed[r, 1] = means2d[g, 1]
        packed[r, 2] = conics[g, 0]
        packed[r, 3] = conics[g, 1]
        packed[r, 4] = conics[g, 2]
        packed[r, 5] = o
        packed[r, 6] = log_o
        packed[r, 7] = 2.0 * (log_o - log_alpha_floor)
        for k in range(4):
            boxes[r, k] = bounds[g, k]
        in_boxes += ((bounds[g, 1] // tile_w - bounds[g, 0] // tile_w + 1)
                     * (bounds[g, 3] // tile_h - bounds[g, 2] // tile_h + 1))
    pair_tile = np.empty(in_boxes, dtype=np.int32)
    pair_rank = np.empty(in_boxes, dtype=np.int32)
    counts = np.zeros(n_tiles, dtype=np.int64)
    m = 0
    for r in range(n_vis):
        bx0, bx1, by0, by1 = boxes[r, 0], boxes[r, 1], boxes[r, 2], boxes[r, 3]
        tx0, tx1, ty0, ty1 = bx0 // tile_w, bx1 // tile_w, by0 // tile_h, by1 // tile_h
        if tx0 == tx1 and ty0 == ty1:  # the box lies in one tile, and the box is the footprint's
            tile = ty0 * tiles_x + tx0
            pair_tile[m] = tile
            pair_rank[m] = r
            counts[tile] += 1
            m += 1
            continue
        mx, my, a, b, c, reach = packed[r, 0], packed[r, 1], packed[r, 2], packed[r, 3], packed[r, 4], packed[r, 7]
        for ty in range(ty0, ty1 + 1):
            y_lo = max(by0, ty * tile_h) + 0.5
            y_hi = min(by1, ty * tile_h + tile_h - 1) + 0.5
            for tx in range(tx0, tx1 + 1):
                x_lo = max(bx0, tx * tile_w) + 0.5
                x_hi = min(bx1, tx * tile_w + tile_w - 1) + 0.5
                if _ellipse_reaches_rect(mx, my, a, b, c, reach, x_lo, x_hi, y_lo, y_hi):
                    tile = ty * tiles_x + tx
                    pair_tile[m] = tile
                    pair_rank[m] = r
                    counts[tile] += 1
                    m += 1
    tile_offsets[0] = 0
    for t in range(n_tiles):
        tile_offsets[t + 1] = tile_offsets[t] + counts[t]
    tile_ranks = np.empty(m, dtype=np.int32)
    for t in range(n_tiles):
        counts[t] = tile_offsets[t]
    for k in range(m):  # pairs are in rank order, so every tile's run comes out front to back
        t = pair_tile[k]
        tile_ranks[counts[t]] = pair_rank[k]
        counts[t] += 1
    return order, packed, boxes, tile_ranks, in_boxes


if numba is not None:
    _ellipse_reaches_rect = numba.njit(nogil=True, cache=JIT_CACHE, inline="always")(_ellipse_reaches_rect_py)
    _radix_order = numba.njit(nogil=True, cache=JIT_CACHE)(_radix_order_py)
    _build_lists = numba.njit(nogil=True, cache=JIT_CACHE)(_build_lists_py)
else:  # pragma: no cover
    _ellipse_reaches_rect = _radix_order = _build_lists = None


def ellipse_reaches_rect(mx: float, my: float, a: float, b: float, c: float, reach: float, x_lo: float,
                         x_hi: float, y_lo: float, y_hi: float) -> bool:
    """Whether the ellipse {a dx² + 2b dx dy + c dy² ≤ reach} around (mx, my) meets the rectangle
    [x_lo, x_hi] × [y_lo, y_hi] (up to a relative slack of :data:`REACH_SLACK`; a conic that is not
    positive definite always meets it)."""
    return bool(_ellipse_reaches_rect(float(mx), float(my), float(a), float(b), float(c), float(reach),
                                      float(x_lo), float(x_hi), float(y_lo), float(y_hi)))


def kernel_tile_shape(tile_size: int | str, channels: int) -> tuple[int, int]:
    """(tile_w, tile_h) of the fused kernels: a square of side ``tile_size``, or for "auto" large tiles
    (fewer Gaussians cut at tile borders: fewer row segments, each set up once) — :data:`WIDE_TILE` for a
    few channels, :data:`AUTO_TILE_SIZE` squares for many (their channel sums stay in the core's cache)."""
    if tile_size != "auto":
        return int(tile_size), int(tile_size)
    return (WIDE_TILE if channels <= WIDE_TILE_MAX_CHANNELS else (AUTO_TILE_SIZE, AUTO_TILE_SIZE))


def build_tile_lists(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, depths: torch.Tensor,
                     visible: torch.Tensor, bounds: torch.Tensor, width: int, height: int, tile_w: int, tile_h: int,
                     alpha_floor: float) -> TileLists:
    """Depth-ordered per-tile lists of the visible Gaussians.

    Args:
        means2d (N,2), conics (N,3), opacities (N,), depths (N,): screen-space Gaussians (CPU, working
            dtype; detached values are used). visible (N,) bool; bounds (N,4) int64 inclusive pixel
            bounds (see :class:`~.projection.Projected`).
        tile_w, tile_h: tile size in pixels. alpha_floor: α at or below it is not drawn (the float just
            below alpha_min in the working dtype).
    """
    if numba is None:
        raise RuntimeError("numba is not installed; the fused kernels are unavailable")
    tiles_x = (width + tile_w - 1) // tile_w
    tiles_y = (height + tile_h - 1) // tile_h
    n_tiles = tiles_x * tiles_y
    with torch.no_grad():
        depth_np = _numpy(depths)
        # visible depths are ≥ near > 0: the IEEE bits of a positive float sort like the float
        depth_bits, key_bits = (depth_np.view(np.uint64), 64) if depth_np.dtype == np.float64 else (
            depth_np.view(np.uint32), 32)
        offsets = np.empty(n_tiles + 1, dtype=np.int64)
        order, packed, boxes, tile_ranks, in_boxes = _build_lists(
            _numpy(visible), depth_bits, key_bits, _numpy(means2d), _numpy(conics), _numpy(opacities), _numpy(bounds),
            tile_w, tile_h, tiles_x, n_tiles, math.log(alpha_floor), offsets)
    return TileLists(order=order, packed=packed, boxes=boxes, tile_offsets=offsets, tile_ranks=tile_ranks,
                     tiles_x=tiles_x, tiles_y=tiles_y, tile_w=tile_w, tile_h=tile_h, width=width, height=height,
                     pairs_in_boxes=int(in_boxes))


def _numpy(t: torch.Tensor) -> np.ndarray:
    """A contiguous numpy view of a CPU tensor (float16/bfloat16 widened to float32)."""
    t = t.detach()
    if t.dtype in (torch.float16, torch.bfloat16):
        t = t.float()
    return np.ascontiguousarray(t.numpy())
