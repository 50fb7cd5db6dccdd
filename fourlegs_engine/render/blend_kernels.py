"""Fused CPU blending kernels (numba) over :class:`~.tile_lists.TileLists`: forward, backward, splat.

Every kernel walks a tile's depth-ordered list front to back, one Gaussian at a time. Each pixel keeps
its own transmittance and stops as in 3DGS; a row whose pixels have all stopped is skipped, a tile whose
pixels have all stopped ends its list.

The forward kernels (:func:`_blend_narrow_py` for up to three channels, :func:`_blend_wide_py` for more)
blend each pair's bounding box (clipped to the tile) in chunks of LANES columns, row after row, with the
vector code of :mod:`.lane_kernels`: α follows a recurrence down the rows (two vector multiplications
per row, two vector exps per chunk), and a row's lanes are tested, blended and counted at once. The
table rows of the next list entries are prefetched (they are scattered over tables larger than the
caches).

The backward and splat kernels visit only the pixels of a Gaussian's footprint, row by row: for pixel
row y the footprint {dᵀΣ⁻¹d ≤ q} is the x-interval centred at mx − b·dy/a with half-width
sqrt(a·q − (ac − b²)·dy²)/a (:func:`_row_span`). Along a row the exponent is a quadratic in x, so α
follows a two-term recurrence — G(x+1) = G(x)·R(x), R(x+1) = R(x)·e^(−a) — two multiplications per pixel
instead of an exp (:data:`RECURRENCE_MAX_A` bounds where it is used; the steepest footprints, a handful
of pixels wide, take one exp per pixel). Pixels outside the footprint have α < α_floor, so both walks
blend the same pixels; their α agree to ~1e-13 relative (two evaluations of the same exponent), so they
decide alike except for a pixel whose T lands within that margin of the stop threshold.

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
except ImportError:  # pragma: no cover
    numba = None

#: the α recurrence along a row is used while the conic's a (1/px²) is at most this; above it the
#: footprint is a few pixels wide and α is evaluated directly (bounds the recurrence's factors by e^±36)
RECURRENCE_MAX_A = 16.0
#: slack, in pixels, added to each end of a row's footprint interval before the exact α test
SPAN_SLACK_PX = 1e-6
#: relative slack on a row's squared half-width (rounding at rows tangent to the footprint)
SPAN_SLACK_REL = 1e-12
#: channels the narrow forward kernel blends in planes beside T (fewer are zero)
NARROW_LANES = 3
#: list entries the forward kernels prefetch ahead of the one they blend
PREFETCH_AHEAD = 8
#: fragments the many-channel kernels collect before forming their channel sums
FRAGMENT_BATCH = 1 << 14


def _pair_setup_py(packed, k):  # pragma: no cover - compiled by numba
    """Per-Gaussian constants of the row footprints: (slope, h0, h1, recurrence, step).

    Row offset dy has the footprint x-interval centred at mx − slope·dy with half-width
    sqrt(h0 − h1·dy²) (slope = b/a, h0 = q/a, h1 = (ac − b²)/a²); ``recurrence`` says whether α may
    follow the two-term recurrence along the row, whose ratio shrinks by ``step`` = e^(−a) per pixel.
    A conic that is not positive definite gets h0 = inf (every pixel of the box is evaluated).
    """
    a, b, c, reach = packed[k, 2], packed[k, 3], packed[k, 4], packed[k, 7]
    if not a > 0.0:
        return 0.0, math.inf, 0.0, False, 1.0
    inv_a = 1.0 / a
    recurrence = a <= RECURRENCE_MAX_A
    return b * inv_a, reach * inv_a, (a * c - b * b) * inv_a * inv_a, recurrence, math.exp(-a) if recurrence else 1.0


def _row_span_py(centre, h0, h1_dy2, lo, hi):  # pragma: no cover - compiled by numba
    """Columns [x_start, x_end] of a row whose footprint is centred at column ``centre`` (pixel-centre
    coordinate − 0.5) with squared half-width h0 − h1_dy2, clipped to [lo, hi] (empty: x_start > x_end).
    A row that only grazes the footprint (squared half-width negative by rounding) keeps its tangent
    column; h0 = inf (conic not positive definite) gives all of [lo, hi]."""
    half_sq = h0 - h1_dy2
    if half_sq < -SPAN_SLACK_REL * (abs(h0) + abs(h1_dy2)):
        return 1, 0
    half = math.sqrt(max(half_sq, 0.0)) + SPAN_SLACK_PX
    start = min(max(centre - half, lo - 1.0), hi + 1.0)  # also maps NaN/inf into range
    end = min(max(centre + half, lo - 1.0), hi + 1.0)
    x_start = max(int(math.ceil(start)), lo)
    x_end = min(int(math.floor(end)), hi)
    if h0 == math.inf:
        x_start, x_end = lo, hi
    return x_start, x_end


def _tile_reset_py(tile, tiles_x, tile_w, tile_h, width, height, transmittance, row_live):  # pragma: no cover
    """Set up a tile's pixel state: T = 1, and every row's live columns (tile-local, inclusive) the
    whole row. Returns (x0, y0, tile width, tile height)."""
    x0 = (tile % tiles_x) * tile_w
    y0 = (tile // tiles_x) * tile_h
    tw = min(tile_w, width - x0)
    th = min(tile_h, height - y0)
    for p in range(tw * th):
        transmittance[p] = 1.0
    for r in range(th):
        row_live[r, 0] = 0
        row_live[r, 1] = tw - 1
    return x0, y0, tw, th


def _shrink_row_py(transmittance, row_live, r, tw):  # pragma: no cover - compiled by numba
    """Move row r's live column range inward past the pixels that have stopped (T stored negative), so
    later Gaussians skip a row, or its ends, where nothing can be blended any more."""
    lo = row_live[r, 0]
    hi = row_live[r, 1]
    base = r * tw
    while lo <= hi and transmittance[base + lo] < 0.0:
        lo += 1
    while hi >= lo and transmittance[base + hi] < 0.0:
        hi -= 1
    row_live[r, 0] = lo
    row_live[r, 1] = hi


def _row_start_py(packed, k, x, y):  # pragma: no cover - compiled by numba
    """(α-before-clamp at pixel (x, y), ratio to the next pixel's) for Gaussian rank k."""
    mx, my, a, b, c, log_o = packed[k, 0], packed[k, 1], packed[k, 2], packed[k, 3], packed[k, 4], packed[k, 6]
    dx = x + 0.5 - mx
    dy = y + 0.5 - my
    return (math.exp(log_o - 0.5 * (a * dx * dx + 2.0 * b * dx * dy + c * dy * dy)),
            math.exp(-(a * dx + b * dy) - 0.5 * a))


def _gauss_at_py(packed, k, x, y):  # pragma: no cover - compiled by numba
    """α before the clamp at pixel (x, y) for Gaussian rank k, evaluated directly."""
    mx, my, a, b, c, log_o = packed[k, 0], packed[k, 1], packed[k, 2], packed[k, 3], packed[k, 4], packed[k, 6]
    dx = x + 0.5 - mx
    dy = y + 0.5 - my
    return math.exp(log_o - 0.5 * (a * dx * dx + 2.0 * b * dx * dy + c * dy * dy))


def _blend_narrow_py(tiles, offsets, ranks, order, packed, boxes, tiles_x, tile_w, tile_h, width, height, values,
                     alpha_floor, alpha_max, transmittance_min, accum, transmittance_out):  # pragma: no cover
    """accum[p, :C] = Σ_i w_i(p)·values[g_i, :C] and transmittance_out[p] = T_final for the pixels of
    ``tiles``, for C ≤ 3 channels (values (N, C), g_i = order[rank]), each pair's box blended in chunks of
    LANES columns by :func:`~.lane_kernels.blend_lanes` into float64 planes (T, three channel sums).

    Arrays: see :class:`~.tile_lists.TileLists`; accum (H·W, C) and transmittance_out (H·W,) are written
    for every pixel of the listed tiles (tiles own disjoint pixels, so tile subsets run concurrently).
    A stopped pixel keeps −T in ``trans`` (T ≥ transmittance_min > 0, so the sign is free).
    """
    channels = accum.shape[1]
    pitch = tile_w + LANES  # a chunk's vector reaches LANES − 1 columns past its row's last pixel
    plane = tile_h * pitch
    trans = np.empty(plane, dtype=np.float64)
    c0 = np.empty(plane, dtype=np.float64)
    c1 = np.empty(plane, dtype=np.float64)
    c2 = np.empty(plane, dtype=np.float64)
    lanes = np.empty(2 * LANES, dtype=np.float64)
    row_live = np.empty(tile_h, dtype=np.int64)
    for tile in tiles:
        x0, y0, tw, th = _tile_origin(tile, tiles_x, tile_w, tile_h, width, height)
        trans[:] = 1.0
        c0[:] = 0.0
        c1[:] = 0.0
        c2[:] = 0.0
        row_live[:th] = tw
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
            v0 = np.float64(vals[0]) if channels > 0 else 0.0
            v1 = np.float64(vals[1]) if channels > 1 else 0.0
            v2 = np.float64(vals[2]) if channels > 2 else 0.0
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
                    stopped = blend_lanes(trans, c0, c1, c2, lanes, r * pitch + cx - x0, n_lanes,
                                          1.0 if direct else step, v0, v1, v2, alpha_floor, alpha_max,
                                          transmittance_min)
                    row_live[r] -= stopped
                    live -= stopped
            if live == 0:
                break
        for r in range(th):
            row = (y0 + r) * width + x0
            for x in range(tw):
                p = r * pitch + x
                transmittance_out[row + x] = abs(trans[p])
                if channels > 0:
                    accum[row + x, 0] = c0[p]
                if channels > 1:
                    accum[row + x, 1] = c1[p]
                if channels > 2:
                    accum[row + x, 2] = c2[p]


def _tile_origin_py(tile, tiles_x, tile_w, tile_h, width, height):  # pragma: no cover - compiled by numba
    """(x0, y0, tile width, tile height) of tile number ``tile`` (edge tiles are cut by the image)."""
    x0 = (tile % tiles_x) * tile_w
    y0 = (tile // tiles_x) * tile_h
    return x0, y0, min(tile_w, width - x0), min(tile_h, height - y0)


def _skip_row_py(lanes, step):  # pragma: no cover - compiled by numba
    """Advance a chunk's α recurrence past a row without blending it (nothing to do for direct rows)."""
    if step >= 0.0:
        for lane in range(LANES):
            lanes[lane] *= lanes[LANES + lane]
            lanes[LANES + lane] *= step


def _row_fragments_py(transmittance, p0, n, gauss, ratio, step, alpha_floor, alpha_max, transmittance_min,
                      frag_pixel, frag_weight, frag_alpha, n_frag):  # pragma: no cover - compiled by numba
    """Blend one row segment's α into the tile's transmittance (the rule of
    :func:`~.lane_kernels.blend_lanes`) and append
    its fragments (pixel, weight w = α·T, α). Returns (fragments now, pixels stopped)."""
    stopped = 0
    for i in range(n):
        alpha = gauss
        gauss *= ratio
        ratio *= step
        p = p0 + np.uint64(i)
        t_before = transmittance[p]
        if t_before < 0.0:
            continue
        if alpha > alpha_max:
            alpha = alpha_max
        if alpha <= alpha_floor:
            continue
        after = t_before * (1.0 - alpha)
        if after < transmittance_min:
            transmittance[p] = -t_before
            stopped += 1
            continue
        frag_pixel[n_frag] = p
        frag_weight[n_frag] = alpha * t_before
        frag_alpha[n_frag] = alpha
        n_frag += 1
        transmittance[p] = after
    return n_frag, stopped


def _row_segments_py(packed, boxes, k, x0, y0, tw, th, row_live, seg_p0, seg_n, seg_row,
                     seg_exp):  # pragma: no cover - compiled by numba
    """The row segments of Gaussian rank k's footprint in the tile at (x0, y0) of size tw × th, within each
    row's live columns: first pixel seg_p0, length seg_n, tile row seg_row, and at seg_exp[2i], seg_exp[2i+1]
    the α at the first pixel and the recurrence's first ratio (the exps of all rows together: they
    overlap). Returns (segments, whether the α recurrence applies, its step e^(−a))."""
    slope, h0, h1, recurrence, step = _pair_setup(packed, k)
    mx, my, a, b, c, log_o = packed[k, 0], packed[k, 1], packed[k, 2], packed[k, 3], packed[k, 4], packed[k, 6]
    lo = max(boxes[k, 0], x0)
    hi = min(boxes[k, 1], x0 + tw - 1)
    # the row segments first (their exponents are independent: the exps overlap), then the pixels
    n_seg = 0
    for y in range(max(boxes[k, 2], y0), min(boxes[k, 3], y0 + th - 1) + 1):
        r = y - y0
        lo_r = max(lo, x0 + row_live[r, 0])
        hi_r = min(hi, x0 + row_live[r, 1])
        if lo_r > hi_r:
            continue
        dy = y + 0.5 - my
        xs, xe = _row_span(mx - 0.5 - slope * dy, h0, h1 * dy * dy, lo_r, hi_r)
        if xs > xe:
            continue
        dx = xs + 0.5 - mx
        seg_p0[n_seg] = np.uint64(r * tw + xs - x0)
        seg_n[n_seg] = xe - xs + 1
        seg_row[n_seg] = r
        seg_exp[2 * n_seg] = log_o - 0.5 * (a * dx * dx + 2.0 * b * dx * dy + c * dy * dy)
        seg_exp[2 * n_seg + 1] = -(a * dx + b * dy) - 0.5 * a
        n_seg += 1
    for i in range(2 * n_seg):
        seg_exp[i] = math.exp(seg_exp[i])
    return n_seg, recurrence, step


def _pair_fragments_py(packed, boxes, k, x0, y0, tw, th, transmittance, row_live, seg_p0, seg_n, seg_row, seg_exp,
                       alpha_floor, alpha_max, transmittance_min, frag_pixel, frag_weight, frag_alpha,
                       n_frag):  # pragma: no cover - compiled by numba
    """All fragments of Gaussian rank k in the tile at (x0, y0) of size tw × th, front to back after
    those already blended. Returns (fragments now, pixels stopped)."""
    n_seg, recurrence, step = _row_segments(packed, boxes, k, x0, y0, tw, th, row_live, seg_p0, seg_n, seg_row,
                                            seg_exp)
    stopped = 0
    for i in range(n_seg):
        if recurrence:
            n_frag, row_stopped = _row_fragments(transmittance, seg_p0[i], seg_n[i], seg_exp[2 * i], seg_exp[2 * i + 1],
                                                 step, alpha_floor, alpha_max, transmittance_min, frag_pixel,
                                                 frag_weight, frag_alpha, n_frag)
        else:  # steep footprint, a few pixels wide: α evaluated directly, one pixel at a time
            row_stopped = 0
            y = y0 + seg_row[i]
            xs = x0 + int(seg_p0[i]) - seg_row[i] * tw
            for j in range(seg_n[i]):
                n_frag, one = _row_fragments(transmittance, seg_p0[i] + np.uint64(j), 1, _gauss_at(packed, k, xs + j, y),
                                             1.0, 1.0, alpha_floor, alpha_max, transmittance_min, frag_pixel,
                                             frag_weight, frag_alpha, n_frag)
                row_stopped += one
        if row_stopped:
            _shrink_row(transmittance, row_live, seg_row[i], tw)
        stopped += row_stopped
    return n_frag, stopped


def _blend_wide_py(tiles, offsets, ranks, order, packed, boxes, tiles_x, tile_w, tile_h, width, height, values,
                   alpha_floor, alpha_max, transmittance_min, accum, transmittance_out):  # pragma: no cover
    """As :func:`_blend_narrow_py` for any number of channels: values (N, C) indexed by Gaussian id
    (order[rank]). Two phases per batch of list entries: the fragments (pixel, w) of every entry
    (:func:`~.lane_kernels.fragment_lanes`, chunk rows as in the narrow kernel), then the channel sums
    acc[pixel] += w·values[g] over them (SIMD over the channels, in accum's dtype)."""
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
        x0, y0, tw, th = _tile_origin(tile, tiles_x, tile_w, tile_h, width, height)
        trans[:] = 1.0
        row_live[:th] = tw
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
                ahead = ranks[m + PREFETCH_AHEAD]
                prefetch(packed, ahead)
                prefetch(boxes, ahead)
            entry_gaussian[n_entry] = order[k]
            entry_start[n_entry] = n_frag
            n_entry += 1
            bx0, bx1 = max(boxes[k, 0], x0), min(boxes[k, 1], x0 + tw - 1)
            by0, by1 = max(boxes[k, 2], y0), min(boxes[k, 3], y0 + th - 1)
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
                    n_frag, stopped = fragment_lanes(trans, lanes, r * pitch + cx - x0, n_lanes,
                                                     1.0 if direct else step, r * tw + cx - x0, frag_pixel,
                                                     frag_weight, n_frag, alpha_floor, alpha_max, transmittance_min)
                    row_live[r] -= stopped
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
    transmittance = np.empty(n_pix, dtype=np.float64)
    row_live = np.empty((tile_h, 2), dtype=np.int64)
    local = np.empty((n_pix, channels), dtype=out.dtype)
    sums = np.empty(channels, dtype=out.dtype)
    seg_p0 = np.empty(tile_h, dtype=np.uint64)
    seg_n = np.empty(tile_h, dtype=np.int64)
    seg_row = np.empty(tile_h, dtype=np.int64)
    seg_exp = np.empty(2 * tile_h, dtype=np.float64)
    frag_pixel = np.empty(n_pix, dtype=np.uint64)
    frag_weight = np.empty(n_pix, dtype=out.dtype)
    frag_alpha = np.empty(n_pix, dtype=np.float64)
    for tile in tiles:
        x0, y0, tw, th = _tile_reset(tile, tiles_x, tile_w, tile_h, width, height, transmittance, row_live)
        for r in range(th):
            row = (y0 + r) * width + x0
            for x in range(tw):
                src = pixel_values[row + x]
                dst = local[r * tw + x]
                for s in range(channels):
                    dst[s] = src[s]
        live = tw * th
        for m in range(offsets[tile], offsets[tile + 1]):
            k = ranks[m]
            n_frag, stopped = _pair_fragments(packed, boxes, k, x0, y0, tw, th, transmittance, row_live, seg_p0, seg_n,
                                              seg_row, seg_exp, alpha_floor, alpha_max, transmittance_min, frag_pixel,
                                              frag_weight, frag_alpha, 0)
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
    _pair_setup = _jit_inline(_pair_setup_py)
    _row_span = _jit_inline(_row_span_py)
    _tile_reset = _jit_inline(_tile_reset_py)
    _shrink_row = _jit_inline(_shrink_row_py)
    _row_start = _jit_inline(_row_start_py)
    _gauss_at = _jit_inline(_gauss_at_py)
    _jit = numba.njit(nogil=True, cache=JIT_CACHE)
    _blend_narrow = _jit(_blend_narrow_py)
    _tile_origin = _jit_inline(_tile_origin_py)
    _skip_row = _jit_inline(_skip_row_py)
    _row_fragments = _jit_inline(_row_fragments_py)
    _row_segments = _jit_inline(_row_segments_py)
    _pair_fragments = _jit_inline(_pair_fragments_py)
    _blend_wide = _jit(_blend_wide_py)
    _splat = _jit(_splat_py)
else:  # pragma: no cover
    _pair_setup = _row_span = _tile_reset = _shrink_row = _row_start = _gauss_at = None
    _blend_narrow = _blend_wide = _splat = _row_fragments = _row_segments = _pair_fragments = None
    _tile_origin = _skip_row = None
