"""Fused CPU blending kernels (numba) over :class:`~.tile_lists.TileLists`: forward, backward, splat.

Every kernel walks a tile's depth-ordered list front to back, one Gaussian at a time, and blends each
pair's bounding box (clipped to the tile) in chunks of LANES columns, row after row, with the vector code
of :mod:`.lane_kernels`: α follows a recurrence down the rows (two vector multiplications per row, two
vector exps per chunk), and a row's lanes are tested, blended and counted at once. Each pixel keeps its
own transmittance and stops as in 3DGS; a row whose pixels have all stopped is skipped, a tile whose
pixels have all stopped ends its list. The table rows of the next list entries are prefetched (they are
scattered over tables larger than the caches).

The narrow forward (up to NARROW_CHANNELS channels, :func:`_blend_narrow_py`) adds the channel sums in the
lanes;
the others collect each entry's fragments (pixel, w = α·T, α) with :func:`_entry_fragments_py` — the same
walk, so the forward, the backward, the splat and the work counter decide alike what is blended — and
form their sums over the fragments.

The α test (α ≤ α_floor is skipped), the α_max clamp, the stop rule and the blending order are those of
:mod:`.rasterizer`; arithmetic is float64 except the channel loops, which run in the working dtype.

The backward pass recomputes α and T in the same order as the forward, and needs no back-to-front walk:
with s_i = ∂L/∂w_i = g_p·v_i,

    ∂L/∂α_i = T_i s_i − (Σ_{k>i} w_k s_k + T_final ∂L/∂T_final) / (1 − α_i)

and the suffix sum is (g_p·accum_p + T_final ∂L/∂T_final) − Σ_{k≤i} w_k s_k, where accum_p is the
forward's output. ∂L/∂power = ∂L/∂α·α (where α is not clamped), chained per Gaussian to
(mx, my, a, b, c, o) through six running sums over its pixels.
"""
from __future__ import annotations

import math

import numpy as np

from ..jit_cache import JIT_CACHE
from .lane_kernels import LANES, blend_lanes, chunk_start, direct_row, fragment_lanes, prefetch

try:  # pragma: no cover - exercised when numba is missing
    import numba

    from . import lane_llvm  # noqa: F401 (the vector code of the lane functions)
except ImportError:  # pragma: no cover
    numba = None

#: at most this many channels are blended in the lanes themselves (more: fragments, then channel sums)
NARROW_CHANNELS = 8
#: list entries the kernels prefetch ahead of the one they blend
PREFETCH_AHEAD = 8
#: fragments the many-channel kernels collect before forming their channel sums
FRAGMENT_BATCH = 1 << 14


def _gauss_at_py(packed, k, x, y):  # pragma: no cover - compiled by numba
    """α before the clamp at pixel (x, y) for Gaussian rank k, evaluated directly."""
    mx, my, a, b, c, log_o = packed[k, 0], packed[k, 1], packed[k, 2], packed[k, 3], packed[k, 4], packed[k, 6]
    dx = x + 0.5 - mx
    dy = y + 0.5 - my
    return math.exp(log_o - 0.5 * (a * dx * dx + 2.0 * b * dx * dy + c * dy * dy))


def _tile_start_py(tile, tiles_x, tile_w, tile_h, width, height, trans, row_live):  # pragma: no cover - numba
    """Set up tile number ``tile``: T = 1 on the whole plane ``trans`` (tile_h · pitch), and every row's
    count of live pixels its width. Returns (x0, y0, tile width, tile height) (edge tiles are cut by the
    image)."""
    x0 = (tile % tiles_x) * tile_w
    y0 = (tile // tiles_x) * tile_h
    tw = min(tile_w, width - x0)
    th = min(tile_h, height - y0)
    trans[:] = 1.0
    row_live[:th] = tw
    return x0, y0, tw, th


def _skip_row_py(lanes, step):  # pragma: no cover - compiled by numba
    """Advance a chunk's α recurrence past a row without blending it (nothing to do for direct rows)."""
    if step >= 0.0:
        for lane in range(LANES):
            lanes[lane] *= lanes[LANES + lane]
            lanes[LANES + lane] *= step


def _entry_fragments_py(packed, boxes, k, x0, y0, tw, th, pitch, trans, row_live, lanes, frag_pixel, frag_weight,
                        frag_alpha, n_frag, alpha_floor, alpha_max, transmittance_min):  # pragma: no cover - numba
    """Blend list entry k (Gaussian rank k) into the tile at (x0, y0) of size tw × th and append its
    fragments — pixel r·tw + x (tile-local), weight w = α·T, α after the clamp (unless ``frag_alpha`` is
    None) — at frag_*[n_frag …], chunk by chunk, row by row.

    trans: the tile's T plane (tile_h rows of ``pitch`` = tile_w + LANES), a stopped pixel holding −T;
    row_live (tile_h,): live pixels per row (rows at 0 are skipped). Returns (fragments now, pixels
    stopped, pixels evaluated).
    """
    bx0, bx1 = max(boxes[k, 0], x0), min(boxes[k, 1], x0 + tw - 1)
    by0, by1 = max(boxes[k, 2], y0), min(boxes[k, 3], y0 + th - 1)
    stopped = 0
    evaluated = 0
    for cx in range(bx0, bx1 + 1, LANES):
        n_lanes = min(LANES, bx1 - cx + 1)
        step = chunk_start(packed, k, cx, by0, cx + n_lanes - 1, by1, lanes)
        direct = step < 0.0
        for y in range(by0, by1 + 1):
            r = y - y0
            if direct:
                direct_row(packed, k, cx, y, lanes)
            if row_live[r] == 0:
                _skip_row(lanes, step)
                continue
            n_frag, row_stopped = fragment_lanes(trans, lanes, r * pitch + cx - x0, n_lanes,
                                                 1.0 if direct else step, r * tw + cx - x0, frag_pixel,
                                                 frag_weight, frag_alpha, n_frag, alpha_floor, alpha_max,
                                                 transmittance_min)
            row_live[r] -= row_stopped
            stopped += row_stopped
            evaluated += n_lanes
    return n_frag, stopped, evaluated


def _blend_narrow_py(tiles, offsets, ranks, order, packed, boxes, tiles_x, tile_w, tile_h, width, height, values,
                     alpha_floor, alpha_max, transmittance_min, accum, transmittance_out):  # pragma: no cover
    """accum[p, :C] = Σ_i w_i(p)·values[g_i, :C] and transmittance_out[p] = T_final for the pixels of
    ``tiles``, for C ≤ NARROW_CHANNELS (values (N, C), g_i = order[rank]), each pair's box blended in chunks
    of LANES columns by :func:`~.lane_kernels.blend_lanes` into float64 planes (T, one sum per channel).

    Arrays: see :class:`~.tile_lists.TileLists`; accum (H·W, C) and transmittance_out (H·W,) are written
    for every pixel of the listed tiles (tiles own disjoint pixels, so tile subsets run concurrently).
    A stopped pixel keeps −T in ``trans`` (T ≥ transmittance_min > 0, so the sign is free).
    """
    channels = accum.shape[1]
    pitch = tile_w + LANES  # a chunk's vector reaches LANES − 1 columns past its row's last pixel
    plane = tile_h * pitch
    trans = np.empty(plane, dtype=np.float64)
    planes = np.empty((channels, plane), dtype=np.float64)
    lanes = np.empty(2 * LANES, dtype=np.float64)
    row_live = np.empty(tile_h, dtype=np.int64)
    for tile in tiles:
        x0, y0, tw, th = _tile_start(tile, tiles_x, tile_w, tile_h, width, height, trans, row_live)
        planes[:, :] = 0.0
        live = tw * th
        end = offsets[tile + 1]
        for m in range(offsets[tile], end):
            k = ranks[m]
            if m + PREFETCH_AHEAD < end:
                ahead = ranks[m + PREFETCH_AHEAD]
                prefetch(packed, ahead)
                prefetch(boxes, ahead)
                prefetch(values, order[ahead])
            bx0, bx1 = max(boxes[k, 0], x0), min(boxes[k, 1], x0 + tw - 1)
            by0, by1 = max(boxes[k, 2], y0), min(boxes[k, 3], y0 + th - 1)
            vals = values[order[k]]
            for cx in range(bx0, bx1 + 1, LANES):
                n_lanes = min(LANES, bx1 - cx + 1)
                step = chunk_start(packed, k, cx, by0, cx + n_lanes - 1, by1, lanes)
                direct = step < 0.0
                for y in range(by0, by1 + 1):
                    r = y - y0
                    if direct:
                        direct_row(packed, k, cx, y, lanes)
                    if row_live[r] == 0:
                        _skip_row(lanes, step)
                        continue
                    stopped = blend_lanes(trans, planes, lanes, r * pitch + cx - x0, n_lanes, 1.0 if direct else step,
                                          vals, alpha_floor, alpha_max, transmittance_min)
                    row_live[r] -= stopped
                    live -= stopped
            if live == 0:
                break
        for r in range(th):
            row = (y0 + r) * width + x0
            for x in range(tw):
                p = r * pitch + x
                transmittance_out[row + x] = abs(trans[p])
                for j in range(channels):
                    accum[row + x, j] = planes[j, p]


def _blend_wide_py(tiles, offsets, ranks, order, packed, boxes, tiles_x, tile_w, tile_h, width, height, values,
                   alpha_floor, alpha_max, transmittance_min, accum, transmittance_out):  # pragma: no cover
    """As :func:`_blend_narrow_py` for any number of channels: values (N, C) indexed by Gaussian id
    (order[rank]). Two phases per batch of list entries: the fragments (pixel, w) of every entry
    (:func:`_entry_fragments_py`), then the channel sums acc[pixel] += w·values[g] over them (SIMD over
    the channels, in accum's dtype)."""
    channels = values.shape[1]
    n_pix = tile_w * tile_h
    pitch = tile_w + LANES
    trans = np.empty(tile_h * pitch, dtype=np.float64)
    lanes = np.empty(2 * LANES, dtype=np.float64)
    row_live = np.empty(tile_h, dtype=np.int64)
    acc = np.empty((n_pix, channels), dtype=accum.dtype)
    capacity = max(FRAGMENT_BATCH, 2 * n_pix)
    frag_pixel = np.empty(capacity, dtype=np.uint64)
    frag_weight = np.empty(capacity, dtype=accum.dtype)
    entry_gaussian = np.empty(capacity, dtype=np.int64)
    entry_start = np.empty(capacity + 1, dtype=np.int64)
    for tile in tiles:
        x0, y0, tw, th = _tile_start(tile, tiles_x, tile_w, tile_h, width, height, trans, row_live)
        acc[:tw * th] = 0
        live = tw * th
        n_frag = 0
        n_entry = 0
        start = offsets[tile]
        end = offsets[tile + 1]
        for m in range(start, end + 1):
            # channel sums of the batch so far: at the end, or before its fragments or entries could overflow
            if m == end or live == 0 or n_frag + tw * th > capacity or n_entry == capacity:
                entry_start[n_entry] = n_frag
                for e in range(min(n_entry, PREFETCH_AHEAD)):
                    prefetch(values, entry_gaussian[e])
                for e in range(n_entry):
                    if e + PREFETCH_AHEAD < n_entry:
                        prefetch(values, entry_gaussian[e + PREFETCH_AHEAD])
                    vals = values[entry_gaussian[e]]
                    for f in range(entry_start[e], entry_start[e + 1]):
                        acc_row = acc[frag_pixel[f]]
                        w = frag_weight[f]
                        for s in range(channels):
                            acc_row[s] += w * vals[s]
                n_frag = 0
                n_entry = 0
                if m == end or live == 0:
                    break
            k = ranks[m]
            if m + PREFETCH_AHEAD < end:
                prefetch(packed, ranks[m + PREFETCH_AHEAD])
                prefetch(boxes, ranks[m + PREFETCH_AHEAD])
            entry_gaussian[n_entry] = order[k]
            entry_start[n_entry] = n_frag
            n_entry += 1
            n_frag, stopped, _ = _entry_fragments(packed, boxes, k, x0, y0, tw, th, pitch, trans, row_live, lanes,
                                                  frag_pixel, frag_weight, None, n_frag, alpha_floor, alpha_max,
                                                  transmittance_min)
            live -= stopped
        for r in range(th):
            row = (y0 + r) * width + x0
            for x in range(tw):
                p = r * tw + x
                transmittance_out[row + x] = abs(trans[r * pitch + x])
                out_row = accum[row + x]
                acc_row = acc[p]
                for s in range(channels):
                    out_row[s] = acc_row[s]


def _splat_py(tiles, offsets, ranks, order, packed, boxes, tiles_x, tile_w, tile_h, width, height, pixel_values,
              alpha_floor, alpha_max, transmittance_min, out):  # pragma: no cover - compiled by numba
    """out[g] += Σ_p w_g(p)·pixel_values[p] (pixel_values (H·W, S), out (N, S)): the transpose of
    :func:`_blend_wide_py`, in the same two phases (fragments of one list entry, then its S-wide sum)."""
    channels = pixel_values.shape[1]
    n_pix = tile_w * tile_h
    pitch = tile_w + LANES
    trans = np.empty(tile_h * pitch, dtype=np.float64)
    lanes = np.empty(2 * LANES, dtype=np.float64)
    row_live = np.empty(tile_h, dtype=np.int64)
    local = np.empty((n_pix, channels), dtype=out.dtype)
    sums = np.empty(channels, dtype=out.dtype)
    frag_pixel = np.empty(n_pix, dtype=np.uint64)
    frag_weight = np.empty(n_pix, dtype=out.dtype)
    for tile in tiles:
        x0, y0, tw, th = _tile_start(tile, tiles_x, tile_w, tile_h, width, height, trans, row_live)
        for r in range(th):
            row = (y0 + r) * width + x0
            for x in range(tw):
                src = pixel_values[row + x]
                dst = local[r * tw + x]
                for s in range(channels):
                    dst[s] = src[s]
        live = tw * th
        end = offsets[tile + 1]
        for m in range(offsets[tile], end):
            k = ranks[m]
            if m + PREFETCH_AHEAD < end:
                prefetch(packed, ranks[m + PREFETCH_AHEAD])
                prefetch(boxes, ranks[m + PREFETCH_AHEAD])
            n_frag, stopped, _ = _entry_fragments(packed, boxes, k, x0, y0, tw, th, pitch, trans, row_live, lanes,
                                                  frag_pixel, frag_weight, None, 0, alpha_floor, alpha_max,
                                                  transmittance_min)
            live -= stopped
            if n_frag:
                sums[:] = 0
                for f in range(n_frag):
                    w = frag_weight[f]
                    src = local[frag_pixel[f]]
                    for s in range(channels):
                        sums[s] += w * src[s]
                dst = out[order[k]]
                for s in range(channels):
                    dst[s] += sums[s]
            if live == 0:
                break


if numba is not None:
    _jit_inline = numba.njit(nogil=True, cache=JIT_CACHE, inline="always")
    _jit = numba.njit(nogil=True, cache=JIT_CACHE)
    _gauss_at = _jit_inline(_gauss_at_py)
    _tile_start = _jit_inline(_tile_start_py)
    _skip_row = _jit_inline(_skip_row_py)
    _entry_fragments = _jit_inline(_entry_fragments_py)
    _blend_narrow = _jit(_blend_narrow_py)
    _blend_wide = _jit(_blend_wide_py)
    _splat = _jit(_splat_py)
else:  # pragma: no cover
    _gauss_at = _tile_start = _skip_row = _entry_fragments = None
    _blend_narrow = _blend_wide = _splat = None
