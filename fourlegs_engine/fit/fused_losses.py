"""Fused CPU kernels (numba) of the fit's costliest loss terms, each with its analytic backward pass: the
image loss (L1 + D-SSIM) of :func:`.losses.image_loss`, the SSIM of :func:`.losses.ssim` and the kNN
priors of :class:`.losses.Priors`.

As torch graphs, a fit step's two image losses (five blurred moments each) and its priors (F·K neighbour
pairs) are dozens of full-size operations forward and as many backward, and cost several times the
rasterizer's share of the step. Each kernel here is one pass each way over the same formulas. The torch
versions stay in :mod:`.losses` (``image_loss_reference``, ``ssim_reference``, ``Priors.reference``) as the
test oracles.

SSIM (Gaussian window g, zero padding): with per-pixel moments μx = g∗a, μy = g∗b, exx = g∗a², eyy = g∗b²,
exy = g∗ab and s = (2μxμy + C1)(2σxy + C2) / ((μx² + μy² + C1)(σxx + σyy + C2)), σxx = exx − μx²,
σxy = exy − μxμy, the mean SSIM over M values has

    ∂mean/∂a = (g∗∂s/∂μx + 2a·(g∗∂s/∂exx) + b·(g∗∂s/∂exy)) / M

(the blur's adjoint is the blur itself: the window is symmetric and the padding zero). Images are
(H, W, C) arrays viewed as (H, W·C) rows, so a horizontal tap is an offset of C along a contiguous row.
"""
from __future__ import annotations

import math
import threading
import weakref

import numpy as np
import torch

from ..jit_cache import JIT_CACHE

try:  # pragma: no cover - exercised when numba is missing
    import numba
except ImportError:  # pragma: no cover
    numba = None

#: dtypes the fused kernels take (others fall back to the torch formulations)
FUSED_DTYPES = (torch.float32, torch.float64)
#: the smooth square root's ε² in the priors' norms (as :func:`.losses._weighted_norm`)
NORM_EPS2 = 1e-20


_SCRATCH = threading.local()


def _scratch(name: str, shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:
    """A per-thread scratch array kept between calls: a fit step's SSIM needs tens of MB of intermediate
    planes, and fresh allocations that size cost a page fault per 4 KB on every call."""
    cache = _SCRATCH.__dict__.setdefault("arrays", {})
    arr = cache.get(name)
    if arr is None or arr.shape != shape or arr.dtype != dtype:
        arr = cache[name] = np.empty(shape, dtype=dtype)
    return arr


# ------------------------------------------------------------------------------------------------ SSIM
def _blur_rows_py(src, out, g, channels):  # pragma: no cover - compiled by numba
    """out[k] = the horizontal blur of src[k] (each (H, W·C), taps ``channels`` apart, zero padding).
    Each tap is a loop over two slices with non-negative indices, which LLVM vectorizes."""
    planes, height, width = src.shape
    half = g.shape[0] // 2
    for k in range(planes):
        for y in range(height):
            row = src[k, y]
            acc = out[k, y]
            acc[:] = 0.0
            for t in range(g.shape[0]):
                off = (t - half) * channels
                gt = g[t]
                lo = max(0, -off)
                hi = min(width, width - off)
                dst = acc[lo:hi]
                taps = row[lo + off:hi + off]
                for i in range(hi - lo):
                    dst[i] += gt * taps[i]


def _blur_column_py(src, y, acc, g):  # pragma: no cover - compiled by numba
    """acc[k] = row y of the vertical blur of src[k] ((planes, H, W·C), zero padding)."""
    planes, height, width = src.shape
    half = g.shape[0] // 2
    for k in range(planes):
        out = acc[k]
        out[:] = 0.0
        for t in range(g.shape[0]):
            yy = y + t - half
            if yy < 0 or yy >= height:
                continue
            gt = g[t]
            row = src[k, yy]
            for j in range(width):
                out[j] += gt * row[j]


def _ssim_terms_py(acc, j, c1, c2):  # pragma: no cover - compiled by numba
    """(μx, μy, A1, A2, B1, B2) at column j of the blurred moments acc (5, W·C), float64: SSIM = A1·A2/(B1·B2)."""
    mu_x = np.float64(acc[0, j])
    mu_y = np.float64(acc[1, j])
    a1 = 2.0 * mu_x * mu_y + c1
    a2 = 2.0 * (np.float64(acc[4, j]) - mu_x * mu_y) + c2
    b1 = mu_x * mu_x + mu_y * mu_y + c1
    b2 = np.float64(acc[2, j]) - mu_x * mu_x + np.float64(acc[3, j]) - mu_y * mu_y + c2
    return mu_x, mu_y, a1, a2, b1, b2


def _ssim_forward_py(a, b, g, channels, c1, c2, want_grad, partials, moments, rows):  # pragma: no cover
    """Σ of the SSIM map of (H, W·C) images ``a``, ``b``; when ``want_grad``, partials[0..2] (H, W·C)
    receive ∂s/∂μx, ∂s/∂exx, ∂s/∂exy per pixel. Blurs run in a's dtype, the per-pixel formula in float64;
    moments and rows are (5, H, W·C) scratch."""
    height, width = a.shape
    for y in range(height):
        for j in range(width):
            av = a[y, j]
            bv = b[y, j]
            moments[0, y, j] = av
            moments[1, y, j] = bv
            moments[2, y, j] = av * av
            moments[3, y, j] = bv * bv
            moments[4, y, j] = av * bv
    _blur_rows(moments, rows, g, channels)
    acc = np.empty((5, width), dtype=a.dtype)
    ssim_row = np.empty(width)
    total = 0.0
    for y in range(height):
        _blur_column(rows, y, acc, g)
        # branch-free loops over the row (vectorized); the sum is taken afterwards
        for j in range(width):
            mu_x, mu_y, a1, a2, b1, b2 = _ssim_terms(acc, j, c1, c2)
            ssim_row[j] = a1 * a2 / (b1 * b2)
        if want_grad:
            for j in range(width):
                mu_x, mu_y, a1, a2, b1, b2 = _ssim_terms(acc, j, c1, c2)
                inv_den = 1.0 / (b1 * b2)
                s = ssim_row[j]
                partials[0, y, j] = 2.0 * mu_y * (a2 - a1) * inv_den + 2.0 * mu_x * s * (1.0 / b2 - 1.0 / b1)
                partials[1, y, j] = -s / b2
                partials[2, y, j] = 2.0 * a1 * inv_den
        for j in range(width):
            total += ssim_row[j]
    return total


def _ssim_backward_py(a, b, partials, g, channels, scale, l1_scale, grad, rows):  # pragma: no cover
    """grad (H, W·C) = scale·(g∗∂s/∂μx + 2a·(g∗∂s/∂exx) + b·(g∗∂s/∂exy)) + l1_scale·sign(a − b);
    rows: (3, H, W·C) scratch."""
    height, width = a.shape
    _blur_rows(partials, rows, g, channels)
    acc = np.empty((3, width), dtype=partials.dtype)
    for y in range(height):
        _blur_column(rows, y, acc, g)
        for j in range(width):
            diff = a[y, j] - b[y, j]
            sign = 1.0 if diff > 0.0 else (-1.0 if diff < 0.0 else 0.0)
            grad[y, j] = scale * (acc[0, j] + 2.0 * a[y, j] * acc[1, j] + b[y, j] * acc[2, j]) + l1_scale * sign


def _abs_diff_sum_py(a, b):  # pragma: no cover - compiled by numba
    """Σ |a − b| over two (H, W·C) images, float64."""
    total = 0.0
    for y in range(a.shape[0]):
        for j in range(a.shape[1]):
            total += abs(np.float64(a[y, j]) - np.float64(b[y, j]))
    return total


_POOL = threading.local()


def _take(shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:
    """An array for SSIM partials that live as long as their autograd node, from a per-thread pool of
    released ones (a fit step has two in flight, and fresh arrays of that size page-fault)."""
    pool = _POOL.__dict__.setdefault("arrays", [])
    for i, arr in enumerate(pool):
        if arr.shape == shape and arr.dtype == dtype:
            return pool.pop(i)
    return np.empty(shape, dtype=dtype)


def _give(arr: np.ndarray) -> None:
    pool = _POOL.__dict__.setdefault("arrays", [])
    if len(pool) < 4:
        pool.append(arr)


def _ssim_forward_pass(ctx, a: torch.Tensor, b: torch.Tensor, window: torch.Tensor, c1: float, c2: float):
    """(SSIM sum, a and b as (H, W·C) arrays); keeps what the backward pass needs on ``ctx``."""
    H, W, C = a.shape
    a2 = a.detach().contiguous().numpy().reshape(H, W * C)
    b2 = b.detach().to(a.dtype).contiguous().numpy().reshape(H, W * C)
    want_grad = bool(ctx.needs_input_grad[0])
    partials = _take((3, H, W * C), a2.dtype) if want_grad else np.empty((3, 1, 1), dtype=a2.dtype)
    g = window.detach().to(a.dtype).numpy()
    total = _ssim_forward(a2, b2, g, C, float(c1), float(c2), want_grad, partials,
                          _scratch("moments", (5, H, W * C), a2.dtype), _scratch("rows", (5, H, W * C), a2.dtype))
    ctx.arrays = (a2, b2, partials, g, C) if want_grad else None
    if want_grad:  # back to the pool when autograd lets go of this node (a backward pass may run twice)
        weakref.finalize(ctx, _give, partials)
    return total, a2, b2


def _ssim_backward_pass(ctx, ssim_scale: float, l1_scale: float) -> torch.Tensor:
    a2, b2, partials, g, C = ctx.arrays
    grad = np.empty_like(a2)
    _ssim_backward(a2, b2, partials, g, C, ssim_scale, l1_scale, grad,
                   _scratch("rows", (5,) + a2.shape, a2.dtype)[:3])
    return torch.from_numpy(grad).view(a2.shape[0], -1, C)


class FusedSSIM(torch.autograd.Function):
    """(a (H,W,C), b (H,W,C), window (T,), C1, C2) -> mean SSIM (scalar); the gradient flows to ``a``."""

    @staticmethod
    def forward(ctx, a, b, window, c1, c2):  # noqa: D401
        total, _, _ = _ssim_forward_pass(ctx, a, b, window, c1, c2)
        return torch.tensor(total / a.numel(), dtype=a.dtype)

    @staticmethod
    def backward(ctx, grad_out):
        n = ctx.arrays[0].size
        return _ssim_backward_pass(ctx, float(grad_out) / n, 0.0), None, None, None, None


class FusedImageLoss(torch.autograd.Function):
    """(a (H,W,C), b (H,W,C), window, C1, C2, λ) -> λ·mean|a − b| + (1 − λ)·(1 − SSIM(a, b)), the
    fit's image loss in one pass each way; the gradient flows to ``a`` (|·|' = 0 where a = b)."""

    @staticmethod
    def forward(ctx, a, b, window, c1, c2, l1_weight):  # noqa: D401
        total, a2, b2 = _ssim_forward_pass(ctx, a, b, window, c1, c2)
        n = a.numel()
        ctx.l1_weight = float(l1_weight)
        loss = l1_weight * _abs_diff_sum(a2, b2) / n + (1.0 - l1_weight) * (1.0 - total / n)
        return torch.tensor(loss, dtype=a.dtype)

    @staticmethod
    def backward(ctx, grad_out):
        n = ctx.arrays[0].size
        g = float(grad_out)
        grad = _ssim_backward_pass(ctx, -g * (1.0 - ctx.l1_weight) / n, g * ctx.l1_weight / n)
        return grad, None, None, None, None, None


# ---------------------------------------------------------------------------------------------- priors
def _quat_rel_py(q, p, n):  # pragma: no cover - compiled by numba
    """rel = q[n] ⊗ conj(p[n]) as (w, x, y, z), float64."""
    qw, qx, qy, qz = np.float64(q[n, 0]), np.float64(q[n, 1]), np.float64(q[n, 2]), np.float64(q[n, 3])
    cw, cx, cy, cz = np.float64(p[n, 0]), -np.float64(p[n, 1]), -np.float64(p[n, 2]), -np.float64(p[n, 3])
    return (qw * cw - qx * cx - qy * cy - qz * cz,
            qw * cx + qx * cw + qy * cz - qz * cy,
            qw * cy - qx * cz + qy * cw + qz * cx,
            qw * cz + qx * cy - qy * cx + qz * cw)


def _priors_py(means, quats, prev_means, prev_quats, neighbors, weights, distances, want_grad, rel, rot_mat,
               grad_means, grad_rel, grad_rot_mat):  # pragma: no cover - compiled by numba
    """The three prior sums (rigid, rot, iso, each Σ w·term over the N·K pairs) and, when ``want_grad``,
    the gradients of each sum (float64, zeroed here): grad_means (2, N, 3) of rigid and of iso,
    grad_rel (N, 4) of rot, grad_rot_mat (N, 3, 3) of rigid."""
    N, K = neighbors.shape
    for n in range(N):
        rw, rx, ry, rz = _quat_rel(quats, prev_quats, n)
        rel[n, 0], rel[n, 1], rel[n, 2], rel[n, 3] = rw, rx, ry, rz
        norm = max(math.sqrt(rw * rw + rx * rx + ry * ry + rz * rz), 1e-12)
        w, x, y, z = rw / norm, rx / norm, ry / norm, rz / norm
        rot_mat[n, 0, 0] = 1 - 2 * (y * y + z * z)
        rot_mat[n, 0, 1] = 2 * (x * y - w * z)
        rot_mat[n, 0, 2] = 2 * (x * z + w * y)
        rot_mat[n, 1, 0] = 2 * (x * y + w * z)
        rot_mat[n, 1, 1] = 1 - 2 * (x * x + z * z)
        rot_mat[n, 1, 2] = 2 * (y * z - w * x)
        rot_mat[n, 2, 0] = 2 * (x * z - w * y)
        rot_mat[n, 2, 1] = 2 * (y * z + w * x)
        rot_mat[n, 2, 2] = 1 - 2 * (x * x + y * y)
    if want_grad:
        grad_means[:] = 0.0
        grad_rel[:] = 0.0
        grad_rot_mat[:] = 0.0
    rigid = 0.0
    rot = 0.0
    iso = 0.0
    o = np.empty(3)
    for n in range(N):
        R = rot_mat[n]
        for k in range(K):
            m = neighbors[n, k]
            wt = np.float64(weights[n, k])
            for i in range(3):
                o[i] = np.float64(means[m, i]) - np.float64(means[n, i])
            e0 = R[0, 0] * o[0] + R[1, 0] * o[1] + R[2, 0] * o[2] - (np.float64(prev_means[m, 0]) - np.float64(prev_means[n, 0]))
            e1 = R[0, 1] * o[0] + R[1, 1] * o[1] + R[2, 1] * o[2] - (np.float64(prev_means[m, 1]) - np.float64(prev_means[n, 1]))
            e2 = R[0, 2] * o[0] + R[1, 2] * o[1] + R[2, 2] * o[2] - (np.float64(prev_means[m, 2]) - np.float64(prev_means[n, 2]))
            e_len = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2 + NORM_EPS2)
            rigid += wt * e_len
            d0 = rel[m, 0] - rel[n, 0]
            d1 = rel[m, 1] - rel[n, 1]
            d2 = rel[m, 2] - rel[n, 2]
            d3 = rel[m, 3] - rel[n, 3]
            d_len = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2 + d3 * d3 + NORM_EPS2)
            rot += wt * d_len
            o_len = math.sqrt(o[0] * o[0] + o[1] * o[1] + o[2] * o[2] + NORM_EPS2)
            gap = o_len - np.float64(distances[n, k])
            iso += wt * abs(gap)
            if want_grad:
                # rigid: e = Rᵀo − o_prev;  ∂/∂o = R·ĝ, ∂/∂R[j, i] = o_j ĝ_i
                ge = wt / e_len
                g0, g1, g2 = ge * e0, ge * e1, ge * e2
                # iso: |‖o‖ − d|;  ∂/∂o = sign(gap)·o/‖o‖
                gi = wt * (1.0 if gap > 0.0 else (-1.0 if gap < 0.0 else 0.0)) / o_len
                for j in range(3):
                    go = R[j, 0] * g0 + R[j, 1] * g1 + R[j, 2] * g2
                    grad_means[0, m, j] += go
                    grad_means[0, n, j] -= go
                    grad_means[1, m, j] += gi * o[j]
                    grad_means[1, n, j] -= gi * o[j]
                    grad_rot_mat[n, j, 0] += o[j] * g0
                    grad_rot_mat[n, j, 1] += o[j] * g1
                    grad_rot_mat[n, j, 2] += o[j] * g2
                # rot: ‖rel_m − rel_n‖
                gr = wt / d_len
                grad_rel[m, 0] += gr * d0
                grad_rel[m, 1] += gr * d1
                grad_rel[m, 2] += gr * d2
                grad_rel[m, 3] += gr * d3
                grad_rel[n, 0] -= gr * d0
                grad_rel[n, 1] -= gr * d1
                grad_rel[n, 2] -= gr * d2
                grad_rel[n, 3] -= gr * d3
    return rigid, rot, iso


def _priors_rotation_grad_py(quats, prev_quats, rel, grad_rel, grad_rot_mat, grad_quats):  # pragma: no cover
    """grad_quats (N,4) = ∂L/∂q from ∂L/∂rel and ∂L/∂R (R = R(rel/‖rel‖), rel = q ⊗ conj(p))."""
    N = quats.shape[0]
    for n in range(N):
        rw, rx, ry, rz = rel[n, 0], rel[n, 1], rel[n, 2], rel[n, 3]
        norm = max(math.sqrt(rw * rw + rx * rx + ry * ry + rz * rz), 1e-12)
        w, x, y, z = rw / norm, rx / norm, ry / norm, rz / norm
        G = grad_rot_mat[n]
        gw = 2 * (-z * G[0, 1] + y * G[0, 2] + z * G[1, 0] - x * G[1, 2] - y * G[2, 0] + x * G[2, 1])
        gx = 2 * (y * G[0, 1] + z * G[0, 2] + y * G[1, 0] - 2 * x * G[1, 1] - w * G[1, 2] + z * G[2, 0]
                  + w * G[2, 1] - 2 * x * G[2, 2])
        gy = 2 * (-2 * y * G[0, 0] + x * G[0, 1] + w * G[0, 2] + x * G[1, 0] + z * G[1, 2] - w * G[2, 0]
                  + z * G[2, 1] - 2 * y * G[2, 2])
        gz = 2 * (-2 * z * G[0, 0] - w * G[0, 1] + x * G[0, 2] + w * G[1, 0] - 2 * z * G[1, 1] + y * G[1, 2]
                  + x * G[2, 0] + y * G[2, 1])
        # through u = rel/‖rel‖ (the clamp's branch has no gradient through the norm)
        if math.sqrt(rw * rw + rx * rx + ry * ry + rz * rz) > 1e-12:
            radial = w * gw + x * gx + y * gy + z * gz
            gw, gx, gy, gz = (gw - w * radial) / norm, (gx - x * radial) / norm, (gy - y * radial) / norm, \
                (gz - z * radial) / norm
        else:
            gw, gx, gy, gz = gw / norm, gx / norm, gy / norm, gz / norm
        g0 = grad_rel[n, 0] + gw
        g1 = grad_rel[n, 1] + gx
        g2 = grad_rel[n, 2] + gy
        g3 = grad_rel[n, 3] + gz
        # rel = M(c)·q with c = conj(p): rows (w, x, y, z) of the right-multiplication by c
        cw, cx, cy, cz = np.float64(prev_quats[n, 0]), -np.float64(prev_quats[n, 1]), \
            -np.float64(prev_quats[n, 2]), -np.float64(prev_quats[n, 3])
        grad_quats[n, 0] = cw * g0 + cx * g1 + cy * g2 + cz * g3
        grad_quats[n, 1] = -cx * g0 + cw * g1 - cz * g2 + cy * g3
        grad_quats[n, 2] = -cy * g0 + cz * g1 + cw * g2 - cx * g3
        grad_quats[n, 3] = -cz * g0 - cy * g1 + cx * g2 + cw * g3


class FusedPriors(torch.autograd.Function):
    """(means (N,3), unit rotations (N,4), previous means and rotations, neighbours (N,K), weights (N,K),
    distances (N,K)) -> (rigid, rot, iso) scalars as :class:`.losses.Priors`; gradients flow to the
    current means and rotations. The forward pass also forms each term's gradient (one walk over the
    pairs); the backward pass only weighs and chains them."""

    @staticmethod
    def forward(ctx, means, quats, prev_means, prev_quats, neighbors, weights, distances):  # noqa: D401
        arrays = [t.detach().contiguous().numpy() for t in (means, quats, prev_means, prev_quats)]
        nb = neighbors.detach().contiguous().numpy()
        w = weights.detach().contiguous().numpy()
        d = distances.detach().contiguous().numpy()
        N, K = nb.shape
        want_grad = bool(ctx.needs_input_grad[0] or ctx.needs_input_grad[1])
        rel = np.empty((N, 4))
        rot_mat = np.empty((N, 3, 3))
        grads = (np.empty((2, N, 3)), np.empty((N, 4)), np.empty((N, 3, 3))) if want_grad else \
            (np.zeros((2, 0, 3)), np.zeros((0, 4)), np.zeros((0, 3, 3)))
        rigid, rot, iso = _priors(*arrays, nb, w, d, want_grad, rel, rot_mat, *grads)
        if want_grad:
            ctx.arrays = (arrays[1], arrays[3], rel, *grads, max(N * K, 1), torch.from_numpy(arrays[0][:0]).dtype)
        scale = 1.0 / max(N * K, 1)
        return tuple(torch.tensor(v * scale, dtype=means.dtype) for v in (rigid, rot, iso))

    @staticmethod
    def backward(ctx, g_rigid, g_rot, g_iso):
        quats, prev_quats, rel, grad_means, grad_rel, grad_rot_mat, pairs, dtype = ctx.arrays
        s_rigid, s_rot, s_iso = (0.0 if g is None else float(g) / pairs for g in (g_rigid, g_rot, g_iso))
        grad_quats = np.empty((quats.shape[0], 4))
        _priors_rotation_grad(quats, prev_quats, rel, s_rot * grad_rel, s_rigid * grad_rot_mat, grad_quats)
        grad_pos = s_rigid * grad_means[0] + s_iso * grad_means[1]
        return (torch.from_numpy(grad_pos).to(dtype), torch.from_numpy(grad_quats).to(dtype),
                None, None, None, None, None)


def fused_applies(*tensors: torch.Tensor) -> bool:
    """Whether the fused kernels serve these tensors: numba present, CPU, float32/float64."""
    return numba is not None and all(t.device.type == "cpu" and t.dtype in FUSED_DTYPES for t in tensors)


if numba is not None:
    _inline = numba.njit(nogil=True, cache=JIT_CACHE, inline="always")
    _jit = numba.njit(nogil=True, cache=JIT_CACHE)
    _blur_rows = _jit(_blur_rows_py)
    _blur_column = _inline(_blur_column_py)
    _ssim_terms = _inline(_ssim_terms_py)
    _ssim_forward = _jit(_ssim_forward_py)
    _ssim_backward = _jit(_ssim_backward_py)
    _abs_diff_sum = _jit(_abs_diff_sum_py)
    _quat_rel = _inline(_quat_rel_py)
    _priors = _jit(_priors_py)
    _priors_rotation_grad = _jit(_priors_rotation_grad_py)
else:  # pragma: no cover
    _blur_rows = _blur_column = _ssim_terms = _ssim_forward = _ssim_backward = _abs_diff_sum = None
    _quat_rel = _priors = _priors_rotation_grad = None
