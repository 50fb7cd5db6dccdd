"""SIMD blending of one Gaussian over a chunk of :data:`LANES` pixel columns, row after row (numba + LLVM).

The forward kernels of :mod:`.blend_kernels` cut each tile–Gaussian pair's bounding box into chunks of
:data:`LANES` columns and walk a chunk's rows. α in lane l of row y is exp(E(x_l, y)) with
E = ln o − ½(a dx² + 2b dx dy + c dy²), a quadratic, so from one row to the next

    α(x_l, y + 1) = α(x_l, y)·ρ_l(y),    ρ_l(y + 1) = ρ_l(y)·e^(−c)

(:func:`chunk_start_py` evaluates α and ρ of the chunk's first row with two vector exps,
:func:`start_lanes`): a row costs two vector multiplications for α, then the blend of all its lanes at
once — the α floor and clamp, the stop rule and T·(1 − α), the weights, and the channel sums
(:func:`blend_lanes`), the fragments (:func:`fragment_lanes`) or the backward's gradient terms
(:func:`gradient_lanes`) — as explicit LLVM vector code (numba's own vectorizer leaves such a loop
scalar: it cannot prove that the tile planes do not alias). Each lane keeps the scalar arithmetic
exactly (no fused multiply-add, no reassociation), so a lane's result is the scalar rule applied to
its α.

The recurrence multiplies factors e^(±|E|); while every exponent it passes through on the chunk is at
least :data:`RECURRENCE_MIN_EXPONENT` they all stay normal float64 numbers and α keeps ~100 ulp of
relative accuracy. :func:`chunk_start_py` checks that on the chunk's corners (E is concave for a positive
definite conic, so its minimum over a rectangle is at a corner) and otherwise returns −1: the caller
then evaluates α directly, one exp per lane (:func:`direct_row_py`).

Every function here is also plain Python (the float64 reference the tests hold the LLVM code to, bit for
bit); importing :mod:`.lane_llvm` (the kernels of :mod:`.blend_kernels` do) gives numba the vector code
of :func:`start_lanes`, :func:`blend_lanes`, :func:`fragment_lanes`, :func:`gradient_lanes` and the
prefetch hints through ``overload``.
"""
from __future__ import annotations

import math

import numpy as np

try:  # pragma: no cover - exercised when numba is missing
    import numba
except ImportError:  # pragma: no cover
    numba = None

#: pixel columns blended together (one LLVM vector; two AVX-512 registers of float64)
LANES = 16
#: the α recurrence is used on a chunk while every exponent on it is at least this (see the module doc)
RECURRENCE_MIN_EXPONENT = -600.0


def _exponent_py(mx, my, a, b, c, log_o, x, y):  # pragma: no cover - compiled by numba
    """E = ln α at pixel (x, y) (centre at +0.5) before the clamp."""
    dx = x + 0.5 - mx
    dy = y + 0.5 - my
    return log_o - 0.5 * (a * dx * dx + 2.0 * b * dx * dy + c * dy * dy)


def _chunk_in_range_py(packed, k, cx, cy, x_last, y_last):  # pragma: no cover - compiled by numba
    """Whether the row recurrence applies to Gaussian rank k on the chunk [cx, x_last] × [cy, y_last]: a
    positive definite conic, and every exponent on [cx, x_last + 1] × [cy, y_last + 1] at least
    :data:`RECURRENCE_MIN_EXPONENT` (E is concave: its minimum over the rectangle is at a corner)."""
    mx, my, a, b, c, log_o = packed[k, 0], packed[k, 1], packed[k, 2], packed[k, 3], packed[k, 4], packed[k, 6]
    lowest = min(min(_exponent(mx, my, a, b, c, log_o, cx, cy), _exponent(mx, my, a, b, c, log_o, x_last + 1, cy)),
                 min(_exponent(mx, my, a, b, c, log_o, cx, y_last + 1),
                     _exponent(mx, my, a, b, c, log_o, x_last + 1, y_last + 1)))
    return a > 0.0 and a * c - b * b > 0.0 and lowest >= RECURRENCE_MIN_EXPONENT


def chunk_start_py(packed, k, cx, cy, x_last, y_last, lanes):  # pragma: no cover - compiled by numba
    """Start the row recurrence of Gaussian rank k on the chunk of columns cx .. x_last, rows cy .. y_last.

    Fills ``lanes`` (2·LANES,) float64: lanes[l] = α(cx + l, cy) before the clamp and lanes[LANES + l] =
    α(cx + l, cy + 1)/α(cx + l, cy), for every l < LANES (lanes past x_last included: the blend masks them),
    with :func:`start_lanes`. Returns the per-row factor e^(−c) of the ratios, or −1 when the recurrence
    does not apply (:func:`_chunk_in_range_py`); the ratios are then 1 and the caller fills α row by row
    (:func:`direct_row_py`).
    """
    if not _chunk_in_range(packed, k, cx, cy, x_last, y_last):
        for lane in range(LANES):
            lanes[LANES + lane] = 1.0
        return -1.0
    c = packed[k, 4]
    start_lanes(lanes, packed[k, 0], packed[k, 1], packed[k, 2], packed[k, 3], c, packed[k, 6], cx, cy)
    return math.exp(-c)


def start_lanes(lanes, mx, my, a, b, c, log_o, cx, cy):
    """lanes[l] = exp(E(cx + l, cy)) and lanes[LANES + l] = exp(E(cx + l, cy + 1) − E(cx + l, cy)) for the
    conic (a, b, c), mean (mx, my) and ln o, with :func:`exp_lanes` (numba: one vector of LANES lanes)."""
    dx = (cx + np.arange(LANES)) + 0.5 - mx
    dy = cy + 0.5 - my
    lanes[:LANES] = exp_lanes(log_o - 0.5 * (a * dx * dx + 2.0 * b * dx * dy + c * dy * dy))
    lanes[LANES:] = exp_lanes(-(b * dx + c * dy) - 0.5 * c)


#: exp's argument is clamped to ±EXP_LIMIT (e^±708 are normal float64 numbers)
EXP_LIMIT = 708.0
_LOG2_E = 1.4426950408889634
#: ln 2 in two parts: n·_LN2_HIGH is exact for |n| < 2^32 (its low 32 bits are zero)
_LN2_HIGH = 0.6931471803691238
_LN2_LOW = 1.9082149292705877e-10
#: Taylor coefficients 1/k! of e^r, k = 0 .. 13 (|r| ≤ ln2/2: truncation below 1e-17)
_EXP_TAYLOR = tuple(1.0 / math.factorial(k) for k in range(14))


def exp_lanes(x):
    """e^x for a float64 array, to a few ulp: x clamped to ±EXP_LIMIT, n = rint(x·log2 e), r = x − n·ln 2
    in two parts, e^r by its Taylor polynomial (Horner), then n added to the exponent bits. Every
    operation is one IEEE float64 operation, in the order the vector code of numba's overload performs it,
    so both give the same bits."""
    x = np.minimum(np.maximum(np.asarray(x, dtype=np.float64), -EXP_LIMIT), EXP_LIMIT)
    n = np.rint(x * _LOG2_E)
    r = (x - n * _LN2_HIGH) - n * _LN2_LOW
    poly = np.full_like(r, _EXP_TAYLOR[-1])
    for coefficient in _EXP_TAYLOR[-2::-1]:
        poly = poly * r + coefficient
    return (poly.view(np.int64) + (n.astype(np.int64) << 52)).view(np.float64)


def direct_row_py(packed, k, cx, y, lanes):  # pragma: no cover - compiled by numba
    """lanes[l] = α(cx + l, y) before the clamp, one exp per lane (where :func:`chunk_start_py` returned −1)."""
    mx, my, a, b, c, log_o = packed[k, 0], packed[k, 1], packed[k, 2], packed[k, 3], packed[k, 4], packed[k, 6]
    for lane in range(LANES):
        lanes[lane] = math.exp(_exponent(mx, my, a, b, c, log_o, cx + lane, y))


def _lane_rule(gauss, t_before, lane, n_lanes, alpha_floor, alpha_max, transmittance_min):
    """One lane of the blend: (T to store, weight w = α·T or 0, stopped here, blended here)."""
    alpha = gauss if gauss < alpha_max else alpha_max
    ok = lane < n_lanes and t_before > 0.0 and alpha > alpha_floor
    after = t_before * (1.0 - alpha)
    if ok and after < transmittance_min:
        return -t_before, 0.0, True, False
    if ok:
        return after, alpha * t_before, False, True
    return t_before, 0.0, False, False


def blend_lanes(trans, planes, lanes, base, n_lanes, step, vals, alpha_floor, alpha_max, transmittance_min):
    """Blend one chunk row: pixels base .. base + LANES − 1 of the tile planes (T, and per channel j the sum
    planes[j]), lanes l < n_lanes only, α = lanes[l] (then α ← α·ratio, ratio ← ratio·step for the next row).

    Arrays: trans (P,) and planes (C, P) float64 with P ≥ base + LANES; vals (C,) the Gaussian's values. A
    stopped pixel keeps −T (T ≥ transmittance_min > 0, so the sign is free). Returns how many pixels
    stopped in this row.
    """
    stopped = 0
    for lane in range(LANES):
        p = base + lane
        t_new, w, stop, _ = _lane_rule(lanes[lane], trans[p], lane, n_lanes, alpha_floor, alpha_max,
                                       transmittance_min)
        trans[p] = t_new
        for j in range(planes.shape[0]):
            planes[j, p] += w * np.float64(vals[j])
        stopped += stop
        lanes[lane] *= lanes[LANES + lane]
        lanes[LANES + lane] *= step
    return stopped


def fragment_lanes(trans, lanes, base, n_lanes, step, pixel_base, frag_pixel, frag_weight, frag_alpha, n_frag,
                   alpha_floor, alpha_max, transmittance_min):
    """As :func:`blend_lanes` without channels: each blended lane appends a fragment (pixel pixel_base + l,
    weight w = α·T, and α after the clamp unless ``frag_alpha`` is None) at index n_frag, n_frag + 1, … of
    frag_pixel, frag_weight, frag_alpha, in lane order. Returns (fragments now, pixels stopped)."""
    stopped = 0
    for lane in range(LANES):
        p = base + lane
        t_new, w, stop, blend = _lane_rule(lanes[lane], trans[p], lane, n_lanes, alpha_floor, alpha_max,
                                           transmittance_min)
        if blend:
            frag_pixel[n_frag] = pixel_base + lane
            frag_weight[n_frag] = w
            if frag_alpha is not None:
                frag_alpha[n_frag] = min(lanes[lane], alpha_max)
            n_frag += 1
        trans[p] = t_new
        stopped += stop
        lanes[lane] *= lanes[LANES + lane]
        lanes[LANES + lane] *= step
    return n_frag, stopped


#: rows of the accumulator of :func:`gradient_lanes` before the value-gradient sums: Σ∂L/∂power·(1, dx,
#: dy, dx², dx·dy, dy²)
GEOMETRY_SUMS = 6


def gradient_lanes(trans, grads, total, prefix, lanes, base, n_lanes, step, vals, dx_first, dy, sums, alpha_floor,
                   alpha_max, transmittance_min):
    """The backward of :func:`blend_lanes` for one chunk row: the same blend of T (and the same α update),
    and for each blended lane l (pixel p = base + l, weight w, value dot s = Σ_j g_j·v_j with
    g_j = grads[j, p] = ∂L/∂accum_j):

    * prefix[p] += w·s (Σ_{k≤i} w_k s_k of the backward's suffix-sum form);
    * sums[GEOMETRY_SUMS + j, l] += w·g_j (∂L/∂values);
    * if α < α_max: ∂L/∂power = (w/α·s − (total[p] − prefix[p])/(1 − α))·α is added to sums[0..5, l] times
      (1, dx, dy, dx², dx·dy, dy²), dx = dx_first + l, dy = dy (pixel centre minus mean).

    Arrays: trans, total, prefix (P,) and grads (C, P) float64 planes (as :func:`blend_lanes`), vals (C,),
    sums (GEOMETRY_SUMS + C, LANES) float64. Returns how many pixels stopped in this row.
    """
    stopped = 0
    channels = grads.shape[0]
    for lane in range(LANES):
        p = base + lane
        gauss = lanes[lane]
        alpha = gauss if gauss < alpha_max else alpha_max
        t_new, w, stop, blend = _lane_rule(gauss, trans[p], lane, n_lanes, alpha_floor, alpha_max, transmittance_min)
        trans[p] = t_new
        stopped += stop
        if blend:
            dot = 0.0
            for j in range(channels):
                dot += grads[j, p] * np.float64(vals[j])
            prefix[p] += w * dot
            for j in range(channels):
                sums[GEOMETRY_SUMS + j, lane] += w * grads[j, p]
            if alpha < alpha_max:
                d_power = (w / alpha * dot - (total[p] - prefix[p]) / (1.0 - alpha)) * alpha
                dx = dx_first + lane
                sums[0, lane] += d_power
                sums[1, lane] += d_power * dx
                sums[2, lane] += d_power * dy
                sums[3, lane] += d_power * dx * dx
                sums[4, lane] += d_power * dx * dy
                sums[5, lane] += d_power * dy * dy
        lanes[lane] *= lanes[LANES + lane]
        lanes[LANES + lane] *= step
    return stopped


def prefetch(array, row):
    """Ask the CPU to start loading every cache line of ``array[row]`` (a hint; nothing in Python), for an
    array whose rows are contiguous (a row's bytes are its stride).

    The tile lists visit Gaussians in depth order, scattered over tables larger than the caches; the
    kernels prefetch a few list entries ahead so the loads overlap the blending instead of stalling it.
    """


def prefetch_for_write(array, row):
    """As :func:`prefetch`, for a row about to be written (the line is fetched ready to be modified)."""


if numba is not None:
    _jit_inline = numba.njit(nogil=True, inline="always")
    _exponent = _jit_inline(_exponent_py)
    _chunk_in_range = _jit_inline(_chunk_in_range_py)
    chunk_start = _jit_inline(chunk_start_py)
    direct_row = _jit_inline(direct_row_py)
else:  # pragma: no cover
    _exponent, _chunk_in_range, chunk_start = _exponent_py, _chunk_in_range_py, chunk_start_py
    direct_row = direct_row_py
