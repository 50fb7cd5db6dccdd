"""Fused CPU kernels (numba) over :class:`~.tile_lists.TileLists` that walk the forward's decisions again:
the backward pass and the work counter.

The backward recomputes α and T in the same order as the forward, with the same code
(:func:`~.blend_kernels._entry_fragments_py` decides what is blended), and needs no back-to-front walk;
see :mod:`.blend_kernels` for the suffix-sum form.
"""
from __future__ import annotations

import numpy as np

from ..jit_cache import JIT_CACHE
from .blend_kernels import PREFETCH_AHEAD, _entry_fragments, _gauss_at, _skip_row, _tile_start, numba
from .lane_kernels import GEOMETRY_SUMS, LANES, chunk_start, direct_row, gradient_lanes, prefetch

#: work counters of :func:`count_work` (see its docstring)
WORK_COUNTERS = ("in_boxes", "in_footprints", "evaluated", "blended")


def _backward_py(tiles, offsets, ranks, order, packed, boxes, tiles_x, tile_w, tile_h, width, height, values,
                 grad_accum, grad_transmittance, transmittance_final, accum, alpha_floor, alpha_max,
                 transmittance_min, need_values, need_geometry, grad_values, grad_geometry):  # pragma: no cover
    """Add ∂L/∂values (N, C) to ``grad_values`` and ∂L/∂(mx, my, a, b, c, o) (N, 6) to ``grad_geometry``.

    grad_accum (H·W, C) = ∂L/∂accum; grad_transmittance (H·W,) = ∂L/∂T_final; transmittance_final
    (H·W,) and accum (H·W, C): the forward's outputs (used only for the geometry). Per list entry, the
    fragment pass of the forward (same α, same decisions) and then its gradient sums over the fragments.
    """
    channels = grad_accum.shape[1]
    n_pix = tile_w * tile_h
    pitch = tile_w + LANES
    trans = np.empty(tile_h * pitch, dtype=np.float64)
    lanes = np.empty(2 * LANES, dtype=np.float64)
    row_live = np.empty(tile_h, dtype=np.int64)
    prefix = np.empty(n_pix, dtype=np.float64)
    total = np.empty(n_pix, dtype=np.float64)
    grad_local = np.empty((n_pix, channels), dtype=grad_accum.dtype)
    sums = np.empty(channels, dtype=grad_values.dtype)
    weight_cast = np.empty(1, dtype=grad_values.dtype)
    vals64 = np.empty(channels, dtype=np.float64)
    frag_pixel = np.empty(n_pix, dtype=np.uint64)
    frag_weight = np.empty(n_pix, dtype=np.float64)
    frag_alpha = np.empty(n_pix, dtype=np.float64)
    for tile in tiles:
        x0, y0, tw, th = _tile_start(tile, tiles_x, tile_w, tile_h, width, height, trans, row_live)
        for r in range(th):
            row = (y0 + r) * width + x0
            for x in range(tw):
                p = r * tw + x
                src = grad_accum[row + x]
                dst = grad_local[p]
                for s in range(channels):
                    dst[s] = src[s]
                if need_geometry:
                    dot = 0.0
                    for s in range(channels):
                        dot += np.float64(src[s]) * np.float64(accum[row + x, s])
                    total[p] = dot + transmittance_final[row + x] * grad_transmittance[row + x]
                    prefix[p] = 0.0
        live = tw * th
        end = offsets[tile + 1]
        for m in range(offsets[tile], end):
            k = ranks[m]
            if m + PREFETCH_AHEAD < end:
                prefetch(packed, ranks[m + PREFETCH_AHEAD])
                prefetch(boxes, ranks[m + PREFETCH_AHEAD])
            n_frag, stopped, _ = _entry_fragments(packed, boxes, k, x0, y0, tw, th, pitch, trans, row_live, lanes,
                                                  frag_pixel, frag_weight, frag_alpha, 0, alpha_floor, alpha_max,
                                                  transmittance_min)
            live -= stopped
            if n_frag:
                g = order[k]
                if need_values:
                    sums[:] = 0
                    for f in range(n_frag):
                        weight_cast[0] = frag_weight[f]  # the sums run in the gradient's dtype (SIMD)
                        w = weight_cast[0]
                        src = grad_local[frag_pixel[f]]
                        for s in range(channels):
                            sums[s] += w * src[s]
                    dst = grad_values[g]
                    for s in range(channels):
                        dst[s] += sums[s]
                if need_geometry:
                    mx, my = packed[k, 0], packed[k, 1]
                    for s in range(channels):
                        vals64[s] = values[g, s]
                    s_1 = s_x = s_y = s_xx = s_xy = s_yy = 0.0
                    ox = x0 + 0.5 - mx
                    oy = y0 + 0.5 - my
                    for f in range(n_frag):
                        p = frag_pixel[f]
                        weight = frag_weight[f]
                        alpha = frag_alpha[f]
                        src = grad_local[p]
                        dot = 0.0
                        for s in range(channels):
                            dot += np.float64(src[s]) * vals64[s]
                        prefix[p] += weight * dot
                        if alpha < alpha_max:  # clamped α passes no gradient to the exponent
                            d_alpha = weight / alpha * dot - (total[p] - prefix[p]) / (1.0 - alpha)
                            d_power = d_alpha * alpha
                            dx = ox + np.float64(p % np.uint64(tw))
                            dy = oy + np.float64(p // np.uint64(tw))
                            s_1 += d_power
                            s_x += d_power * dx
                            s_y += d_power * dy
                            s_xx += d_power * dx * dx
                            s_xy += d_power * dx * dy
                            s_yy += d_power * dy * dy
                    _add_geometry_gradient(grad_geometry, g, packed, k, s_1, s_x, s_y, s_xx, s_xy, s_yy)
            if live == 0:
                break


def _add_geometry_gradient_py(grad_geometry, g, packed, k, s_1, s_x, s_y, s_xx, s_xy, s_yy):  # pragma: no cover
    """Chain Σ∂L/∂power·(1, dx, dy, dx², dx·dy, dy²) over a Gaussian's pixels to ∂L/∂(mx, my, a, b, c, o):
    power = ln o − ½(a dx² + 2b dx dy + c dy²), dx = x + 0.5 − mx."""
    a, b, c, o = packed[k, 2], packed[k, 3], packed[k, 4], packed[k, 5]
    grad_geometry[g, 0] += a * s_x + b * s_y
    grad_geometry[g, 1] += b * s_x + c * s_y
    grad_geometry[g, 2] -= 0.5 * s_xx
    grad_geometry[g, 3] -= s_xy
    grad_geometry[g, 4] -= 0.5 * s_yy
    grad_geometry[g, 5] += s_1 / o


def _backward_narrow_py(tiles, offsets, ranks, order, packed, boxes, tiles_x, tile_w, tile_h, width, height, values,
                        grad_accum, grad_transmittance, transmittance_final, accum, alpha_floor, alpha_max,
                        transmittance_min, need_values, need_geometry, grad_values,
                        grad_geometry):  # pragma: no cover - compiled by numba
    """:func:`_backward_py` for C ≤ NARROW_CHANNELS, in the forward's lanes: each chunk row's gradient terms
    are formed by :func:`~.lane_kernels.gradient_lanes` in float64 planes (∂L/∂accum per channel, the
    suffix-sum total and prefix) and summed per lane, then over the lanes once per list entry."""
    channels = grad_accum.shape[1]
    pitch = tile_w + LANES
    plane = tile_h * pitch
    trans = np.empty(plane, dtype=np.float64)
    grads = np.empty((channels, plane), dtype=np.float64)
    total = np.empty(plane, dtype=np.float64)
    prefix = np.empty(plane, dtype=np.float64)
    lanes = np.empty(2 * LANES, dtype=np.float64)
    sums = np.empty((GEOMETRY_SUMS + channels, LANES), dtype=np.float64)
    totals = np.empty(GEOMETRY_SUMS + channels, dtype=np.float64)
    row_live = np.empty(tile_h, dtype=np.int64)
    for tile in tiles:
        x0, y0, tw, th = _tile_start(tile, tiles_x, tile_w, tile_h, width, height, trans, row_live)
        grads[:, :] = 0.0
        total[:] = 0.0
        prefix[:] = 0.0
        for r in range(th):
            row = (y0 + r) * width + x0
            for x in range(tw):
                p = r * pitch + x
                src = grad_accum[row + x]
                for j in range(channels):
                    grads[j, p] = src[j]
                if need_geometry:
                    dot = 0.0
                    for s in range(channels):
                        dot += np.float64(src[s]) * np.float64(accum[row + x, s])
                    total[p] = dot + transmittance_final[row + x] * grad_transmittance[row + x]
        live = tw * th
        end = offsets[tile + 1]
        for m in range(offsets[tile], end):
            k = ranks[m]
            if m + PREFETCH_AHEAD < end:
                ahead = ranks[m + PREFETCH_AHEAD]
                prefetch(packed, ahead)
                prefetch(boxes, ahead)
                prefetch(values, order[ahead])
            g = order[k]
            vals = values[g]
            mx, my = packed[k, 0], packed[k, 1]
            bx0, bx1 = max(boxes[k, 0], x0), min(boxes[k, 1], x0 + tw - 1)
            by0, by1 = max(boxes[k, 2], y0), min(boxes[k, 3], y0 + th - 1)
            sums[:, :] = 0.0
            blended = False
            for cx in range(bx0, bx1 + 1, LANES):
                n_lanes = min(LANES, bx1 - cx + 1)
                step = chunk_start(packed, k, cx, by0, cx + n_lanes - 1, by1, lanes)
                direct = step < 0.0
                dx_first = cx + 0.5 - mx
                for y in range(by0, by1 + 1):
                    r = y - y0
                    if direct:
                        direct_row(packed, k, cx, y, lanes)
                    if row_live[r] == 0:
                        _skip_row(lanes, step)
                        continue
                    stopped = gradient_lanes(trans, grads, total, prefix, lanes, r * pitch + cx - x0, n_lanes,
                                             1.0 if direct else step, vals, dx_first, y + 0.5 - my, sums,
                                             alpha_floor, alpha_max, transmittance_min)
                    row_live[r] -= stopped
                    live -= stopped
                    blended = True
            if blended:
                for j in range(GEOMETRY_SUMS + channels):
                    acc = 0.0
                    for lane in range(LANES):
                        acc += sums[j, lane]
                    totals[j] = acc
                if need_values:
                    for s in range(channels):
                        grad_values[g, s] += totals[GEOMETRY_SUMS + s]
                if need_geometry:
                    _add_geometry_gradient(grad_geometry, g, packed, k, totals[0], totals[1], totals[2], totals[3],
                                           totals[4], totals[5])
            if live == 0:
                break


def _count_py(offsets, ranks, packed, boxes, tiles_x, tile_w, tile_h, width, height, alpha_floor, alpha_max,
              transmittance_min, counters):  # pragma: no cover - compiled by numba
    """Add the work counters of :func:`count_work` to ``counters`` (4,) int64."""
    pitch = tile_w + LANES
    trans = np.empty(tile_h * pitch, dtype=np.float64)
    lanes = np.empty(2 * LANES, dtype=np.float64)
    row_live = np.empty(tile_h, dtype=np.int64)
    frag_pixel = np.empty(tile_w * tile_h, dtype=np.uint64)
    frag_weight = np.empty(tile_w * tile_h, dtype=np.float64)
    for k in range(packed.shape[0]):
        counters[0] += (boxes[k, 1] - boxes[k, 0] + 1) * (boxes[k, 3] - boxes[k, 2] + 1)
        for y in range(boxes[k, 2], boxes[k, 3] + 1):
            for x in range(boxes[k, 0], boxes[k, 1] + 1):
                if min(_gauss_at(packed, k, x, y), alpha_max) > alpha_floor:
                    counters[1] += 1
    for tile in range(offsets.shape[0] - 1):
        x0, y0, tw, th = _tile_start(tile, tiles_x, tile_w, tile_h, width, height, trans, row_live)
        live = tw * th
        for m in range(offsets[tile], offsets[tile + 1]):
            n_frag, stopped, evaluated = _entry_fragments(packed, boxes, ranks[m], x0, y0, tw, th, pitch, trans,
                                                          row_live, lanes, frag_pixel, frag_weight, None, 0,
                                                          alpha_floor, alpha_max, transmittance_min)
            counters[2] += evaluated
            counters[3] += n_frag
            live -= stopped
            if live == 0:
                break


if numba is not None:
    _add_geometry_gradient = numba.njit(nogil=True, cache=JIT_CACHE, inline="always")(_add_geometry_gradient_py)
    _backward = numba.njit(nogil=True, cache=JIT_CACHE)(_backward_py)
    _backward_narrow = numba.njit(nogil=True, cache=JIT_CACHE)(_backward_narrow_py)
    _count = numba.njit(nogil=True, cache=JIT_CACHE)(_count_py)
else:  # pragma: no cover
    _backward = _backward_narrow = _count = None
