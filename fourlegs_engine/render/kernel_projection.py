"""The EWA projection of :mod:`.projection` as one fused numba loop, for views that need no geometry
gradient.

:func:`~.projection.project_gaussians` is a chain of about a hundred float64 torch operations over all
N Gaussians; each is cheap, but together they cost as much as blending the frame. This kernel does the
same arithmetic per Gaussian in one pass (float64 throughout, the same formulas in the same order), so
its results agree with the torch projection to float64 rounding (tested). Gradients still flow through
the torch projection: this twin is used only when no geometry input requires a gradient.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from ..jit_cache import JIT_CACHE
from ..scene.camera import Camera
from .options import RasterOptions
from .projection import BOUND_MARGIN_PX, MAX_LOG_SCALE, Projected

try:  # pragma: no cover - exercised when numba is missing
    import numba
except ImportError:  # pragma: no cover
    numba = None


def _fov_limits_py(fx, fy, cx, cy, width, height, fov_clamp):  # pragma: no cover - compiled by numba
    """The clamp of x/z and y/z in the EWA Jacobian: (x_pos, x_neg, y_pos, y_neg) as in :mod:`.projection`."""
    extra = fov_clamp - 1.0
    return ((width - cx) / fx + extra * width / (2 * fx), cx / fx + extra * width / (2 * fx),
            (height - cy) / fy + extra * height / (2 * fy), cy / fy + extra * height / (2 * fy))


def _to_camera_py(means, i, rot, trans):  # pragma: no cover - compiled by numba
    """Mean ``i`` (any float dtype) in camera coordinates, float64: (x, y, z)."""
    mx_w = np.float64(means[i, 0])
    my_w = np.float64(means[i, 1])
    mz_w = np.float64(means[i, 2])
    return (rot[0, 0] * mx_w + rot[0, 1] * my_w + rot[0, 2] * mz_w + trans[0],
            rot[1, 0] * mx_w + rot[1, 1] * my_w + rot[1, 2] * mz_w + trans[1],
            rot[2, 0] * mx_w + rot[2, 1] * my_w + rot[2, 2] * mz_w + trans[2])


def _unit_rotation_py(quats, i, rq):  # pragma: no cover - compiled by numba
    """Write R(q̂) of quaternion ``i`` (w, x, y, z) into ``rq`` (3,3), q̂ = q/max(|q|, 1e-12) as in
    quaternion_to_matrix; returns (q̂w, q̂x, q̂y, q̂z, |q|, max(|q|, 1e-12))."""
    q_raw_w = np.float64(quats[i, 0])
    q_raw_x = np.float64(quats[i, 1])
    q_raw_y = np.float64(quats[i, 2])
    q_raw_z = np.float64(quats[i, 3])
    q_norm = math.sqrt(q_raw_w * q_raw_w + q_raw_x * q_raw_x + q_raw_y * q_raw_y + q_raw_z * q_raw_z)
    qn = max(q_norm, 1e-12)
    qw = q_raw_w / qn
    qx = q_raw_x / qn
    qy = q_raw_y / qn
    qz = q_raw_z / qn
    rq[0, 0] = 1 - 2 * (qy * qy + qz * qz)
    rq[0, 1] = 2 * (qx * qy - qw * qz)
    rq[0, 2] = 2 * (qx * qz + qw * qy)
    rq[1, 0] = 2 * (qx * qy + qw * qz)
    rq[1, 1] = 1 - 2 * (qx * qx + qz * qz)
    rq[1, 2] = 2 * (qy * qz - qw * qx)
    rq[2, 0] = 2 * (qx * qz - qw * qy)
    rq[2, 1] = 2 * (qy * qz + qw * qx)
    rq[2, 2] = 1 - 2 * (qx * qx + qy * qy)
    return qw, qx, qy, qz, q_norm, qn


def _footprint_factor_py(jr, rq, scales, i, m):  # pragma: no cover - compiled by numba
    """Write M = JR·R(q̂)·diag(s) (2,3) into ``m`` (Σ₂D = M Mᵀ) and return (a, b, c) of M Mᵀ."""
    for r in range(2):
        for k in range(3):
            m[r, k] = (jr[r, 0] * rq[0, k] + jr[r, 1] * rq[1, k] + jr[r, 2] * rq[2, k]) * scales[i, k]
    a = m[0, 0] * m[0, 0] + m[0, 1] * m[0, 1] + m[0, 2] * m[0, 2]
    b = m[0, 0] * m[1, 0] + m[0, 1] * m[1, 1] + m[0, 2] * m[1, 2]
    c = m[1, 0] * m[1, 0] + m[1, 1] * m[1, 1] + m[1, 2] * m[1, 2]
    return a, b, c


def _cross_rows_py(m):  # pragma: no cover - compiled by numba
    """m0 × m1 of the rows of ``m`` (2,3); |m0 × m1|² = det(M Mᵀ)."""
    return (m[0, 1] * m[1, 2] - m[0, 2] * m[1, 1], m[0, 2] * m[1, 0] - m[0, 0] * m[1, 2],
            m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0])


def _jacobian_rows_py(rot, fx, fy, inv_z, tx, ty, jr):  # pragma: no cover - compiled by numba
    """Write JR = J·R_cam (2,3) into ``jr`` for the clamped EWA Jacobian J at (tx, ty) = clamped (x/z, y/z)."""
    for k in range(3):
        jr[0, k] = fx * inv_z * rot[0, k] - fx * tx * inv_z * rot[2, k]
        jr[1, k] = fy * inv_z * rot[1, k] - fy * ty * inv_z * rot[2, k]


def _pixel_bounds_py(u, v, a_lp, b, c_lp, log_reach, opacity, opacity_extent, alpha_min, width,
                     height):  # pragma: no cover - compiled by numba
    """The footprint's pixel box as projection._pixel_bounds: (x0, x1, y0, y1, visible, finite)."""
    if opacity_extent:
        q = 2.0 * log_reach
        visible = q > 0
        q = max(q, 0.0)
        rx = math.sqrt(q * a_lp)
        ry = math.sqrt(q * c_lp)
    else:
        lam_max = 0.5 * (a_lp + c_lp) + math.sqrt(max(0.25 * (a_lp - c_lp) ** 2 + b * b, 0.0))
        rx = 3.0 * math.sqrt(lam_max)
        ry = rx
        visible = opacity >= alpha_min
    rx += BOUND_MARGIN_PX
    ry += BOUND_MARGIN_PX
    finite = math.isfinite(u) and math.isfinite(v) and not math.isnan(rx) and not math.isnan(ry)
    x0 = x1 = y0 = y1 = 0
    if finite:
        x0 = max(int(math.ceil(min(max(u - rx - 0.5, -1.0), width + 1.0))), 0)
        x1 = min(int(math.floor(min(max(u + rx - 0.5, -2.0), float(width)))), width - 1)
        y0 = max(int(math.ceil(min(max(v - ry - 0.5, -1.0), height + 1.0))), 0)
        y1 = min(int(math.floor(min(max(v + ry - 0.5, -2.0), float(height)))), height - 1)
    return x0, x1, y0, y1, visible, finite


def _project_py(means, quats, scales, opacities, log_reach, rot, trans, fx, fy, cx, cy, width, height, near, far,
                eps2d, fov_clamp, alpha_min, opacity_extent, out_means2d, out_conics, out_depths, out_visible,
                out_bounds):  # pragma: no cover - compiled by numba
    """Project every Gaussian; see :func:`project_gaussians_fused` for the arrays.

    means (N,3), quats (N,4): any float dtype; scales (N,3) float64 = exp(min(log_scale, MAX_LOG_SCALE));
    opacities (N,) (the sigmoid in the working dtype); log_reach (N,) float64 = ln(o / alpha_min) (the
    transcendental functions come vectorized from torch); rot (3,3), trans (3,) float64 world-to-camera;
    the outputs are written in their own dtypes.
    """
    lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg = _fov_limits(fx, fy, cx, cy, width, height, fov_clamp)
    jr = np.empty((2, 3))
    rq = np.empty((3, 3))
    m = np.empty((2, 3))
    for i in range(means.shape[0]):
        pc0, pc1, z = _to_camera(means, i, rot, trans)
        in_range = z >= near and z <= far
        z_safe = z if in_range else 1.0
        x_over_z = pc0 / z_safe
        y_over_z = pc1 / z_safe
        u = fx * x_over_z + cx
        v = fy * y_over_z + cy
        tx = min(max(x_over_z, -lim_x_neg), lim_x_pos)
        ty = min(max(y_over_z, -lim_y_neg), lim_y_pos)
        _jacobian_rows(rot, fx, fy, 1.0 / z_safe, tx, ty, jr)
        _unit_rotation(quats, i, rq)
        a, b, c = _footprint_factor(jr, rq, scales, i, m)
        cr0, cr1, cr2 = _cross_rows(m)
        a_lp = a + eps2d
        c_lp = c + eps2d
        det = cr0 * cr0 + cr1 * cr1 + cr2 * cr2 + eps2d * (a + c) + eps2d * eps2d
        nondegenerate = det > 0
        det_safe = det if nondegenerate else 1.0
        out_means2d[i, 0] = u
        out_means2d[i, 1] = v
        out_conics[i, 0] = c_lp / det_safe
        out_conics[i, 1] = -b / det_safe
        out_conics[i, 2] = a_lp / det_safe
        out_depths[i] = z
        x0, x1, y0, y1, visible, finite = _pixel_bounds(u, v, a_lp, b, c_lp, log_reach[i], np.float64(opacities[i]),
                                                        opacity_extent, alpha_min, width, height)
        out_bounds[i, 0] = x0
        out_bounds[i, 1] = x1
        out_bounds[i, 2] = y0
        out_bounds[i, 3] = y1
        out_visible[i] = (visible and finite and x0 <= x1 and y0 <= y1 and in_range and nondegenerate
                          and math.isfinite(det))


def _conic_backward_py(m, a, b, c, eps2d, g_ca, g_cb, g_cc, det_safe, nondegenerate, d_m):  # pragma: no cover
    """Write ∂L/∂M (2,3) into ``d_m`` from ∂L/∂conic, conic = ((c + eps)/det, −b/det, (a + eps)/det)."""
    inv_det = 1.0 / det_safe
    d_a = g_cc * inv_det
    d_b = -g_cb * inv_det
    d_c = g_ca * inv_det
    d_m[:, :] = 0.0
    if nondegenerate:
        cr0, cr1, cr2 = _cross_rows(m)
        d_det = -((c + eps2d) * g_ca - b * g_cb + (a + eps2d) * g_cc) * inv_det * inv_det
        d_a += d_det * eps2d
        d_c += d_det * eps2d
        # |m0 × m1|²: ∂/∂m0 = 2(m1 × (m0 × m1)), ∂/∂m1 = 2((m0 × m1) × m0)
        d_m[0, 0] += 2.0 * d_det * (m[1, 1] * cr2 - m[1, 2] * cr1)
        d_m[0, 1] += 2.0 * d_det * (m[1, 2] * cr0 - m[1, 0] * cr2)
        d_m[0, 2] += 2.0 * d_det * (m[1, 0] * cr1 - m[1, 1] * cr0)
        d_m[1, 0] += 2.0 * d_det * (cr1 * m[0, 2] - cr2 * m[0, 1])
        d_m[1, 1] += 2.0 * d_det * (cr2 * m[0, 0] - cr0 * m[0, 2])
        d_m[1, 2] += 2.0 * d_det * (cr0 * m[0, 1] - cr1 * m[0, 0])
    for k in range(3):
        d_m[0, k] += 2.0 * d_a * m[0, k] + d_b * m[1, k]
        d_m[1, k] += 2.0 * d_c * m[1, k] + d_b * m[0, k]


def _quaternion_backward_py(qw, qx, qy, qz, q_norm, qn, g, d_quats, i):  # pragma: no cover - compiled by numba
    """Write ∂L/∂q (raw quaternion ``i``) into ``d_quats`` from g = ∂L/∂R(q̂) (3,3)."""
    d_qw = 2.0 * (-qz * g[0, 1] + qy * g[0, 2] + qz * g[1, 0] - qx * g[1, 2] - qy * g[2, 0] + qx * g[2, 1])
    d_qx = 2.0 * (qy * g[0, 1] + qz * g[0, 2] + qy * g[1, 0] - 2.0 * qx * g[1, 1] - qw * g[1, 2] + qz * g[2, 0]
                  + qw * g[2, 1] - 2.0 * qx * g[2, 2])
    d_qy = 2.0 * (-2.0 * qy * g[0, 0] + qx * g[0, 1] + qw * g[0, 2] + qx * g[1, 0] + qz * g[1, 2] - qw * g[2, 0]
                  + qz * g[2, 1] - 2.0 * qy * g[2, 2])
    d_qz = 2.0 * (-2.0 * qz * g[0, 0] - qw * g[0, 1] + qx * g[0, 2] + qw * g[1, 0] - 2.0 * qz * g[1, 1]
                  + qy * g[1, 2] + qx * g[2, 0] + qy * g[2, 1])
    if q_norm > 1e-12:  # q̂ = q/|q|: remove the radial part
        radial = qw * d_qw + qx * d_qx + qy * d_qy + qz * d_qz
        d_qw -= qw * radial
        d_qx -= qx * radial
        d_qy -= qy * radial
        d_qz -= qz * radial
    d_quats[i, 0] = d_qw / qn
    d_quats[i, 1] = d_qx / qn
    d_quats[i, 2] = d_qy / qn
    d_quats[i, 3] = d_qz / qn


def _project_backward_py(means, quats, scales, rot, trans, fx, fy, cx, cy, width, height, near, far, eps2d,
                         fov_clamp, d_means2d, d_conics, d_depths, d_means, d_quats, d_scales):  # pragma: no cover
    """The gradient of :func:`_project_py`'s means2d (N,2), conics (N,3) and depths (N,) w.r.t. means
    (N,3), quaternions (N,4) and scales (N,3), written into d_means, d_quats, d_scales (float64).

    Recomputes each Gaussian's forward intermediates and chains back through conic = adj(Σ₂D)/det,
    Σ₂D = M Mᵀ + eps·I with M = J·R_cam·R(q̂)·diag(s), the clamped EWA Jacobian J(x/z, y/z), the
    quaternion normalization q̂ = q/max(|q|, 1e-12) and p = R_cam·m + t — the same branches as the
    forward (z outside [near, far] uses z = 1; a clamped x/z passes no gradient to J; det ≤ 0 uses
    det = 1).
    """
    lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg = _fov_limits(fx, fy, cx, cy, width, height, fov_clamp)
    jr = np.empty((2, 3))
    rq = np.empty((3, 3))
    m = np.empty((2, 3))
    d_m = np.empty((2, 3))
    d_v = np.empty((2, 3))
    g = np.empty((3, 3))
    d_jr = np.empty((2, 3))
    for i in range(means.shape[0]):
        g_u = np.float64(d_means2d[i, 0])
        g_v = np.float64(d_means2d[i, 1])
        g_z = np.float64(d_depths[i])
        if g_u == 0.0 and g_v == 0.0 and g_z == 0.0 and d_conics[i, 0] == 0 and d_conics[i, 1] == 0 \
                and d_conics[i, 2] == 0:
            d_means[i, :] = 0.0
            d_scales[i, :] = 0.0
            d_quats[i, :] = 0.0
            continue
        # ---- forward, as _project_py
        pc0, pc1, z = _to_camera(means, i, rot, trans)
        in_range = z >= near and z <= far
        z_safe = z if in_range else 1.0
        x_over_z = pc0 / z_safe
        y_over_z = pc1 / z_safe
        tx = min(max(x_over_z, -lim_x_neg), lim_x_pos)
        ty = min(max(y_over_z, -lim_y_neg), lim_y_pos)
        inv_z = 1.0 / z_safe
        _jacobian_rows(rot, fx, fy, inv_z, tx, ty, jr)
        qw, qx, qy, qz, q_norm, qn = _unit_rotation(quats, i, rq)
        a, b, c = _footprint_factor(jr, rq, scales, i, m)
        cr0, cr1, cr2 = _cross_rows(m)
        det = cr0 * cr0 + cr1 * cr1 + cr2 * cr2 + eps2d * (a + c) + eps2d * eps2d
        nondegenerate = det > 0
        _conic_backward(m, a, b, c, eps2d, np.float64(d_conics[i, 0]), np.float64(d_conics[i, 1]),
                        np.float64(d_conics[i, 2]), det if nondegenerate else 1.0, nondegenerate, d_m)
        # ---- M = V·diag(s), V = JR·R(q̂): ∂R(q̂) = JRᵀ·dV, ∂JR = dV·R(q̂)ᵀ
        for k in range(3):
            v0 = jr[0, 0] * rq[0, k] + jr[0, 1] * rq[1, k] + jr[0, 2] * rq[2, k]
            v1 = jr[1, 0] * rq[0, k] + jr[1, 1] * rq[1, k] + jr[1, 2] * rq[2, k]
            d_scales[i, k] = d_m[0, k] * v0 + d_m[1, k] * v1
            d_v[0, k] = d_m[0, k] * scales[i, k]
            d_v[1, k] = d_m[1, k] * scales[i, k]
        for r in range(3):
            for k in range(3):
                g[r, k] = jr[0, r] * d_v[0, k] + jr[1, r] * d_v[1, k]
        _quaternion_backward(qw, qx, qy, qz, q_norm, qn, g, d_quats, i)
        for r in range(2):
            for k in range(3):
                d_jr[r, k] = d_v[r, 0] * rq[k, 0] + d_v[r, 1] * rq[k, 1] + d_v[r, 2] * rq[k, 2]
        # ---- JR = J·R_cam: ∂J = ∂JR·R_camᵀ (only the non-zero entries of J)
        d_j00 = d_jr[0, 0] * rot[0, 0] + d_jr[0, 1] * rot[0, 1] + d_jr[0, 2] * rot[0, 2]
        d_j02 = d_jr[0, 0] * rot[2, 0] + d_jr[0, 1] * rot[2, 1] + d_jr[0, 2] * rot[2, 2]
        d_j11 = d_jr[1, 0] * rot[1, 0] + d_jr[1, 1] * rot[1, 1] + d_jr[1, 2] * rot[1, 2]
        d_j12 = d_jr[1, 0] * rot[2, 0] + d_jr[1, 1] * rot[2, 1] + d_jr[1, 2] * rot[2, 2]
        # ---- J(x/z, y/z) and the means: u = fx·x/z + cx, v = fy·y/z + cy
        d_inv_z = fx * d_j00 - fx * tx * d_j02 + fy * d_j11 - fy * ty * d_j12
        d_xz = fx * g_u
        d_yz = fy * g_v
        if -lim_x_neg <= x_over_z <= lim_x_pos:
            d_xz -= fx * inv_z * d_j02
        if -lim_y_neg <= y_over_z <= lim_y_pos:
            d_yz -= fy * inv_z * d_j12
        d_pc0 = d_xz * inv_z
        d_pc1 = d_yz * inv_z
        d_zs = -(d_xz * x_over_z + d_yz * y_over_z) * inv_z - d_inv_z * inv_z * inv_z
        d_pz = g_z + (d_zs if in_range else 0.0)
        for k in range(3):
            d_means[i, k] = rot[0, k] * d_pc0 + rot[1, k] * d_pc1 + rot[2, k] * d_pz


if numba is not None:
    _inline = numba.njit(nogil=True, cache=JIT_CACHE, inline="always")
    _fov_limits = _inline(_fov_limits_py)
    _to_camera = _inline(_to_camera_py)
    _unit_rotation = _inline(_unit_rotation_py)
    _footprint_factor = _inline(_footprint_factor_py)
    _cross_rows = _inline(_cross_rows_py)
    _jacobian_rows = _inline(_jacobian_rows_py)
    _pixel_bounds = _inline(_pixel_bounds_py)
    _conic_backward = _inline(_conic_backward_py)
    _quaternion_backward = _inline(_quaternion_backward_py)
    _project = numba.njit(nogil=True, cache=JIT_CACHE)(_project_py)
    _project_backward = numba.njit(nogil=True, cache=JIT_CACHE)(_project_backward_py)
else:  # pragma: no cover
    _project = _project_backward = None


def project_gaussians_fused(means: torch.Tensor, rotations: torch.Tensor, log_scales: torch.Tensor,
                            opacity_logits: torch.Tensor, camera: Camera, options: RasterOptions,
                            dtype: torch.dtype) -> Projected:
    """:func:`~.projection.project_gaussians` as one fused pass forward and one backward (same
    arguments and result; CPU tensors). Gradients reach means, rotations, log_scales (through torch's
    exp/clamp) and opacity_logits (through torch's sigmoid) when they are tracked.

    Args:
        means (N,3), rotations (N,4), log_scales (N,3), opacity_logits (N,): CPU tensors.
    Returns:
        :class:`~.projection.Projected` with means2d (N,2), conics (N,3), depths (N,) and opacities (N,)
        in ``dtype``, visible (N,) bool and bounds (N,4) int64.
    """
    if numba is None:
        raise RuntimeError("numba is not installed; the fused projection is unavailable")
    f64 = torch.float64
    opacities = torch.sigmoid(opacity_logits.to(dtype))
    # the same expressions as project_gaussians, vectorized by torch (and differentiated by it)
    scales = torch.exp(log_scales.to(f64).clamp(max=MAX_LOG_SCALE))
    with torch.no_grad():
        log_reach = torch.log(opacities.detach().to(f64).clamp_min(1e-300) / options.alpha_min)
    means2d, conics, depths, visible, bounds = _FusedProjection.apply(
        means, rotations, scales, opacities.detach(), log_reach, camera, options, dtype)
    return Projected(means2d=means2d, conics=conics, depths=depths, opacities=opacities, visible=visible,
                     bounds=bounds)


class _FusedProjection(torch.autograd.Function):
    """(means (N,3), rotations (N,4), scales (N,3) float64) -> means2d (N,2), conics (N,3), depths (N,)
    in the working dtype, and the non-differentiable visible (N,) and bounds (N,4)."""

    @staticmethod
    def forward(ctx, means, rotations, scales, opacities, log_reach, camera, options, dtype):  # noqa: D401
        n = means.shape[0]
        w2c = np.asarray(camera.w2c, dtype=np.float64)
        rot, trans = np.ascontiguousarray(w2c[:3, :3]), np.ascontiguousarray(w2c[:3, 3])
        means2d = torch.empty(n, 2, dtype=dtype)
        conics = torch.empty(n, 3, dtype=dtype)
        depths = torch.empty(n, dtype=dtype)
        visible = torch.empty(n, dtype=torch.bool)
        bounds = torch.empty(n, 4, dtype=torch.int64)
        if n:
            _project(_numpy(means), _numpy(rotations), scales.detach().numpy(), opacities.numpy(), log_reach.numpy(),
                     rot, trans, camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height,
                     float(camera.near), float(camera.far), float(options.eps2d), float(options.fov_clamp),
                     float(options.alpha_min), options.extent == "opacity", means2d.numpy(), conics.numpy(),
                     depths.numpy(), visible.numpy(), bounds.numpy())
        ctx.camera_args = (rot, trans, camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height,
                           float(camera.near), float(camera.far), float(options.eps2d), float(options.fov_clamp))
        ctx.save_for_backward(means, rotations, scales)
        ctx.mark_non_differentiable(visible, bounds)
        return means2d, conics, depths, visible, bounds

    @staticmethod
    def backward(ctx, d_means2d, d_conics, d_depths, *_):
        means, rotations, scales = ctx.saved_tensors
        n = means.shape[0]
        zeros = lambda like, cols: torch.zeros(n, cols, dtype=like.dtype) if like is None else like  # noqa: E731
        d_means2d = zeros(d_means2d, 2).contiguous()
        d_conics = zeros(d_conics, 3).contiguous()
        d_depths = (torch.zeros(n, dtype=means.dtype) if d_depths is None else d_depths).contiguous()
        d_means = torch.empty(n, 3, dtype=torch.float64)
        d_quats = torch.empty(n, 4, dtype=torch.float64)
        d_scales = torch.empty(n, 3, dtype=torch.float64)
        if n:
            rot, trans, *cam = ctx.camera_args
            _project_backward(_numpy(means), _numpy(rotations), scales.detach().numpy(), rot, trans, *cam,
                              d_means2d.numpy(), d_conics.numpy(), d_depths.numpy(), d_means.numpy(),
                              d_quats.numpy(), d_scales.numpy())
        return (d_means.to(means.dtype), d_quats.to(rotations.dtype), d_scales, None, None, None, None, None)


def _numpy(t: torch.Tensor) -> np.ndarray:
    """A contiguous float32/float64 numpy view of a CPU tensor (copied only when it must be)."""
    t = t.detach()
    if t.dtype not in (torch.float32, torch.float64):
        t = t.to(torch.float64)
    return np.ascontiguousarray(t.numpy())
