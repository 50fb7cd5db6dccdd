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

from ..scene.camera import Camera
from .options import RasterOptions
from .projection import BOUND_MARGIN_PX, MAX_LOG_SCALE, Projected

try:  # pragma: no cover - exercised when numba is missing
    import numba
except ImportError:  # pragma: no cover
    numba = None


def _project_py(means, quats, scales, opacities, log_reach, rot, trans, fx, fy, cx, cy, width, height, near, far,
                eps2d, fov_clamp, alpha_min, opacity_extent, out_means2d, out_conics, out_depths, out_visible,
                out_bounds):  # pragma: no cover - compiled by numba
    """Project every Gaussian; see :func:`project_gaussians_fused` for the arrays.

    means (N,3), quats (N,4): any float dtype; scales (N,3) float64 = exp(min(log_scale, MAX_LOG_SCALE));
    opacities (N,) (the sigmoid in the working dtype); log_reach (N,) float64 = ln(o / alpha_min) (the
    transcendental functions come vectorized from torch); rot (3,3), trans (3,) float64 world-to-camera;
    the outputs are written in their own dtypes.
    """
    n = means.shape[0]
    extra = fov_clamp - 1.0
    lim_x_pos = (width - cx) / fx + extra * width / (2 * fx)
    lim_x_neg = cx / fx + extra * width / (2 * fx)
    lim_y_pos = (height - cy) / fy + extra * height / (2 * fy)
    lim_y_neg = cy / fy + extra * height / (2 * fy)
    for i in range(n):
        mx_w = np.float64(means[i, 0])
        my_w = np.float64(means[i, 1])
        mz_w = np.float64(means[i, 2])
        pc0 = rot[0, 0] * mx_w + rot[0, 1] * my_w + rot[0, 2] * mz_w + trans[0]
        pc1 = rot[1, 0] * mx_w + rot[1, 1] * my_w + rot[1, 2] * mz_w + trans[1]
        z = rot[2, 0] * mx_w + rot[2, 1] * my_w + rot[2, 2] * mz_w + trans[2]
        in_range = z >= near and z <= far
        z_safe = z if in_range else 1.0
        x_over_z = pc0 / z_safe
        y_over_z = pc1 / z_safe
        u = fx * x_over_z + cx
        v = fy * y_over_z + cy
        tx = min(max(x_over_z, -lim_x_neg), lim_x_pos)
        ty = min(max(y_over_z, -lim_y_neg), lim_y_pos)
        inv_z = 1.0 / z_safe
        j00 = fx * inv_z
        j02 = -fx * tx * inv_z
        j11 = fy * inv_z
        j12 = -fy * ty * inv_z
        # quaternion -> rotation (normalized, norm clamped as in quaternion_to_matrix)
        qw = np.float64(quats[i, 0])
        qx = np.float64(quats[i, 1])
        qy = np.float64(quats[i, 2])
        qz = np.float64(quats[i, 3])
        qn = max(math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz), 1e-12)
        qw /= qn
        qx /= qn
        qy /= qn
        qz /= qn
        r00 = 1 - 2 * (qy * qy + qz * qz)
        r01 = 2 * (qx * qy - qw * qz)
        r02 = 2 * (qx * qz + qw * qy)
        r10 = 2 * (qx * qy + qw * qz)
        r11 = 1 - 2 * (qx * qx + qz * qz)
        r12 = 2 * (qy * qz - qw * qx)
        r20 = 2 * (qx * qz - qw * qy)
        r21 = 2 * (qy * qz + qw * qx)
        r22 = 1 - 2 * (qx * qx + qy * qy)
        s0 = scales[i, 0]
        s1 = scales[i, 1]
        s2 = scales[i, 2]
        # JR = J @ R (2x3)
        jr00 = j00 * rot[0, 0] + j02 * rot[2, 0]
        jr01 = j00 * rot[0, 1] + j02 * rot[2, 1]
        jr02 = j00 * rot[0, 2] + j02 * rot[2, 2]
        jr10 = j11 * rot[1, 0] + j12 * rot[2, 0]
        jr11 = j11 * rot[1, 1] + j12 * rot[2, 1]
        jr12 = j11 * rot[1, 2] + j12 * rot[2, 2]
        # M = JR @ rot(q) * scales (2x3): Σ₂D = M Mᵀ
        m00 = (jr00 * r00 + jr01 * r10 + jr02 * r20) * s0
        m01 = (jr00 * r01 + jr01 * r11 + jr02 * r21) * s1
        m02 = (jr00 * r02 + jr01 * r12 + jr02 * r22) * s2
        m10 = (jr10 * r00 + jr11 * r10 + jr12 * r20) * s0
        m11 = (jr10 * r01 + jr11 * r11 + jr12 * r21) * s1
        m12 = (jr10 * r02 + jr11 * r12 + jr12 * r22) * s2
        a = m00 * m00 + m01 * m01 + m02 * m02
        b = m00 * m10 + m01 * m11 + m02 * m12
        c = m10 * m10 + m11 * m11 + m12 * m12
        cr0 = m01 * m12 - m02 * m11
        cr1 = m02 * m10 - m00 * m12
        cr2 = m00 * m11 - m01 * m10
        det_raw = cr0 * cr0 + cr1 * cr1 + cr2 * cr2
        a_lp = a + eps2d
        c_lp = c + eps2d
        det = det_raw + eps2d * (a + c) + eps2d * eps2d
        nondegenerate = det > 0
        det_safe = det if nondegenerate else 1.0
        out_means2d[i, 0] = u
        out_means2d[i, 1] = v
        out_conics[i, 0] = c_lp / det_safe
        out_conics[i, 1] = -b / det_safe
        out_conics[i, 2] = a_lp / det_safe
        out_depths[i] = z
        # pixel bounds of the footprint (as projection._pixel_bounds)
        if opacity_extent:
            q = 2.0 * log_reach[i]
            visible = q > 0
            q = max(q, 0.0)
            rx = math.sqrt(q * a_lp)
            ry = math.sqrt(q * c_lp)
        else:
            lam_max = 0.5 * (a_lp + c_lp) + math.sqrt(max(0.25 * (a_lp - c_lp) ** 2 + b * b, 0.0))
            rx = 3.0 * math.sqrt(lam_max)
            ry = rx
            visible = np.float64(opacities[i]) >= alpha_min
        rx += BOUND_MARGIN_PX
        ry += BOUND_MARGIN_PX
        finite = math.isfinite(u) and math.isfinite(v) and not math.isnan(rx) and not math.isnan(ry)
        x0 = x1 = y0 = y1 = 0
        if finite:
            x0 = max(int(math.ceil(min(max(u - rx - 0.5, -1.0), width + 1.0))), 0)
            x1 = min(int(math.floor(min(max(u + rx - 0.5, -2.0), float(width)))), width - 1)
            y0 = max(int(math.ceil(min(max(v - ry - 0.5, -1.0), height + 1.0))), 0)
            y1 = min(int(math.floor(min(max(v + ry - 0.5, -2.0), float(height)))), height - 1)
        out_bounds[i, 0] = x0
        out_bounds[i, 1] = x1
        out_bounds[i, 2] = y0
        out_bounds[i, 3] = y1
        out_visible[i] = (visible and finite and x0 <= x1 and y0 <= y1 and in_range and nondegenerate
                          and math.isfinite(det))


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
    n = means.shape[0]
    extra = fov_clamp - 1.0
    lim_x_pos = (width - cx) / fx + extra * width / (2 * fx)
    lim_x_neg = cx / fx + extra * width / (2 * fx)
    lim_y_pos = (height - cy) / fy + extra * height / (2 * fy)
    lim_y_neg = cy / fy + extra * height / (2 * fy)
    jr = np.empty((2, 3))
    rq = np.empty((3, 3))
    v = np.empty((2, 3))
    d_v = np.empty((2, 3))
    d_m0 = np.empty(3)
    d_m1 = np.empty(3)
    d_jr0 = np.empty(3)
    d_jr1 = np.empty(3)
    for i in range(n):
        g_u = np.float64(d_means2d[i, 0])
        g_v = np.float64(d_means2d[i, 1])
        g_ca = np.float64(d_conics[i, 0])
        g_cb = np.float64(d_conics[i, 1])
        g_cc = np.float64(d_conics[i, 2])
        g_z = np.float64(d_depths[i])
        if g_u == 0.0 and g_v == 0.0 and g_ca == 0.0 and g_cb == 0.0 and g_cc == 0.0 and g_z == 0.0:
            for k in range(3):
                d_means[i, k] = 0.0
                d_scales[i, k] = 0.0
            for k in range(4):
                d_quats[i, k] = 0.0
            continue
        # ---- forward, as _project_py
        mx_w = np.float64(means[i, 0])
        my_w = np.float64(means[i, 1])
        mz_w = np.float64(means[i, 2])
        pc0 = rot[0, 0] * mx_w + rot[0, 1] * my_w + rot[0, 2] * mz_w + trans[0]
        pc1 = rot[1, 0] * mx_w + rot[1, 1] * my_w + rot[1, 2] * mz_w + trans[1]
        z = rot[2, 0] * mx_w + rot[2, 1] * my_w + rot[2, 2] * mz_w + trans[2]
        in_range = z >= near and z <= far
        z_safe = z if in_range else 1.0
        x_over_z = pc0 / z_safe
        y_over_z = pc1 / z_safe
        tx = min(max(x_over_z, -lim_x_neg), lim_x_pos)
        ty = min(max(y_over_z, -lim_y_neg), lim_y_pos)
        inv_z = 1.0 / z_safe
        j00 = fx * inv_z
        j02 = -fx * tx * inv_z
        j11 = fy * inv_z
        j12 = -fy * ty * inv_z
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
        for k in range(3):
            jr[0, k] = j00 * rot[0, k] + j02 * rot[2, k]
            jr[1, k] = j11 * rot[1, k] + j12 * rot[2, k]
        for r in range(2):
            for k in range(3):
                v[r, k] = jr[r, 0] * rq[0, k] + jr[r, 1] * rq[1, k] + jr[r, 2] * rq[2, k]
        s0 = scales[i, 0]
        s1 = scales[i, 1]
        s2 = scales[i, 2]
        m00, m01, m02 = v[0, 0] * s0, v[0, 1] * s1, v[0, 2] * s2
        m10, m11, m12 = v[1, 0] * s0, v[1, 1] * s1, v[1, 2] * s2
        a = m00 * m00 + m01 * m01 + m02 * m02
        b = m00 * m10 + m01 * m11 + m02 * m12
        c = m10 * m10 + m11 * m11 + m12 * m12
        cr0 = m01 * m12 - m02 * m11
        cr1 = m02 * m10 - m00 * m12
        cr2 = m00 * m11 - m01 * m10
        det = cr0 * cr0 + cr1 * cr1 + cr2 * cr2 + eps2d * (a + c) + eps2d * eps2d
        nondegenerate = det > 0
        det_safe = det if nondegenerate else 1.0
        # ---- conic = ((c + eps)/det, −b/det, (a + eps)/det)
        inv_det = 1.0 / det_safe
        d_a = g_cc * inv_det
        d_b = -g_cb * inv_det
        d_c = g_ca * inv_det
        d_m0[:] = 0.0
        d_m1[:] = 0.0
        if nondegenerate:
            d_det = -((c + eps2d) * g_ca - b * g_cb + (a + eps2d) * g_cc) * inv_det * inv_det
            d_a += d_det * eps2d
            d_c += d_det * eps2d
            # |m0 × m1|²: ∂/∂m0 = 2(m1 × (m0 × m1)), ∂/∂m1 = 2((m0 × m1) × m0)
            d_m0[0] += 2.0 * d_det * (m11 * cr2 - m12 * cr1)
            d_m0[1] += 2.0 * d_det * (m12 * cr0 - m10 * cr2)
            d_m0[2] += 2.0 * d_det * (m10 * cr1 - m11 * cr0)
            d_m1[0] += 2.0 * d_det * (cr1 * m02 - cr2 * m01)
            d_m1[1] += 2.0 * d_det * (cr2 * m00 - cr0 * m02)
            d_m1[2] += 2.0 * d_det * (cr0 * m01 - cr1 * m00)
        d_m0[0] += 2.0 * d_a * m00 + d_b * m10
        d_m0[1] += 2.0 * d_a * m01 + d_b * m11
        d_m0[2] += 2.0 * d_a * m02 + d_b * m12
        d_m1[0] += 2.0 * d_c * m10 + d_b * m00
        d_m1[1] += 2.0 * d_c * m11 + d_b * m01
        d_m1[2] += 2.0 * d_c * m12 + d_b * m02
        # ---- M = V·diag(s)
        d_scales[i, 0] = d_m0[0] * v[0, 0] + d_m1[0] * v[1, 0]
        d_scales[i, 1] = d_m0[1] * v[0, 1] + d_m1[1] * v[1, 1]
        d_scales[i, 2] = d_m0[2] * v[0, 2] + d_m1[2] * v[1, 2]
        for k in range(3):
            d_v[0, k] = d_m0[k] * scales[i, k]
            d_v[1, k] = d_m1[k] * scales[i, k]
        # ---- V = JR·R(q̂): ∂R(q̂) = JRᵀ·dV, ∂JR = dV·R(q̂)ᵀ
        g00 = jr[0, 0] * d_v[0, 0] + jr[1, 0] * d_v[1, 0]
        g01 = jr[0, 0] * d_v[0, 1] + jr[1, 0] * d_v[1, 1]
        g02 = jr[0, 0] * d_v[0, 2] + jr[1, 0] * d_v[1, 2]
        g10 = jr[0, 1] * d_v[0, 0] + jr[1, 1] * d_v[1, 0]
        g11 = jr[0, 1] * d_v[0, 1] + jr[1, 1] * d_v[1, 1]
        g12 = jr[0, 1] * d_v[0, 2] + jr[1, 1] * d_v[1, 2]
        g20 = jr[0, 2] * d_v[0, 0] + jr[1, 2] * d_v[1, 0]
        g21 = jr[0, 2] * d_v[0, 1] + jr[1, 2] * d_v[1, 1]
        g22 = jr[0, 2] * d_v[0, 2] + jr[1, 2] * d_v[1, 2]
        d_qw = 2.0 * (-qz * g01 + qy * g02 + qz * g10 - qx * g12 - qy * g20 + qx * g21)
        d_qx = 2.0 * (qy * g01 + qz * g02 + qy * g10 - 2.0 * qx * g11 - qw * g12 + qz * g20 + qw * g21 - 2.0 * qx * g22)
        d_qy = 2.0 * (-2.0 * qy * g00 + qx * g01 + qw * g02 + qx * g10 + qz * g12 - qw * g20 + qz * g21 - 2.0 * qy * g22)
        d_qz = 2.0 * (-2.0 * qz * g00 - qw * g01 + qx * g02 + qw * g10 - 2.0 * qz * g11 + qy * g12 + qx * g20 + qy * g21)
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
        for k in range(3):
            d_jr0[k] = d_v[0, 0] * rq[k, 0] + d_v[0, 1] * rq[k, 1] + d_v[0, 2] * rq[k, 2]
            d_jr1[k] = d_v[1, 0] * rq[k, 0] + d_v[1, 1] * rq[k, 1] + d_v[1, 2] * rq[k, 2]
        # ---- JR = J·R_cam: ∂J = ∂JR·R_camᵀ (only the non-zero entries of J)
        d_j00 = d_jr0[0] * rot[0, 0] + d_jr0[1] * rot[0, 1] + d_jr0[2] * rot[0, 2]
        d_j02 = d_jr0[0] * rot[2, 0] + d_jr0[1] * rot[2, 1] + d_jr0[2] * rot[2, 2]
        d_j11 = d_jr1[0] * rot[1, 0] + d_jr1[1] * rot[1, 1] + d_jr1[2] * rot[1, 2]
        d_j12 = d_jr1[0] * rot[2, 0] + d_jr1[1] * rot[2, 1] + d_jr1[2] * rot[2, 2]
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
    _project = numba.njit(nogil=True, cache=True)(_project_py)
    _project_backward = numba.njit(nogil=True, cache=True)(_project_backward_py)
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
