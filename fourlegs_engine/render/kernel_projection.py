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


def _project_py(means, quats, log_scales, opacities, rot, trans, fx, fy, cx, cy, width, height, near, far,
                eps2d, fov_clamp, alpha_min, opacity_extent, out_means2d, out_conics, out_depths, out_visible,
                out_bounds):  # pragma: no cover - compiled by numba
    """Project every Gaussian; see :func:`project_gaussians_fused` for the arrays.

    means (N,3), quats (N,4), log_scales (N,3): any float dtype; opacities (N,) float64 (the sigmoid
    in the working dtype, widened); rot (3,3), trans (3,) float64 world-to-camera.
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
        s0 = math.exp(min(np.float64(log_scales[i, 0]), MAX_LOG_SCALE))
        s1 = math.exp(min(np.float64(log_scales[i, 1]), MAX_LOG_SCALE))
        s2 = math.exp(min(np.float64(log_scales[i, 2]), MAX_LOG_SCALE))
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
        o = opacities[i]
        if opacity_extent:
            q = 2.0 * math.log(max(o, 1e-300) / alpha_min)
            visible = q > 0
            q = max(q, 0.0)
            rx = math.sqrt(q * a_lp)
            ry = math.sqrt(q * c_lp)
        else:
            lam_max = 0.5 * (a_lp + c_lp) + math.sqrt(max(0.25 * (a_lp - c_lp) ** 2 + b * b, 0.0))
            rx = 3.0 * math.sqrt(lam_max)
            ry = rx
            visible = o >= alpha_min
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


_project = numba.njit(nogil=True, cache=True)(_project_py) if numba is not None else None


def project_gaussians_fused(means: torch.Tensor, rotations: torch.Tensor, log_scales: torch.Tensor,
                            opacity_logits: torch.Tensor, camera: Camera, options: RasterOptions,
                            dtype: torch.dtype) -> Projected:
    """The no-gradient twin of :func:`~.projection.project_gaussians` (same arguments and result; CPU
    tensors; nothing is tracked by autograd).

    Args:
        means (N,3), rotations (N,4), log_scales (N,3), opacity_logits (N,): CPU tensors.
    Returns:
        :class:`~.projection.Projected` with means2d (N,2), conics (N,3), depths (N,) and opacities (N,)
        in ``dtype``, visible (N,) bool and bounds (N,4) int64.
    """
    if numba is None:
        raise RuntimeError("numba is not installed; the fused projection is unavailable")
    n = means.shape[0]
    with torch.no_grad():
        opacities = torch.sigmoid(opacity_logits.detach().to(dtype))
        w2c = np.asarray(camera.w2c, dtype=np.float64)
        means2d = np.empty((n, 2), dtype=np.float64)
        conics = np.empty((n, 3), dtype=np.float64)
        depths = np.empty(n, dtype=np.float64)
        visible = np.empty(n, dtype=np.bool_)
        bounds = np.empty((n, 4), dtype=np.int64)
        if n:
            _project(_numpy(means), _numpy(rotations), _numpy(log_scales),
                     np.ascontiguousarray(opacities.to(torch.float64).numpy()), np.ascontiguousarray(w2c[:3, :3]),
                     np.ascontiguousarray(w2c[:3, 3]), camera.fx, camera.fy, camera.cx, camera.cy, camera.width,
                     camera.height, float(camera.near), float(camera.far), float(options.eps2d),
                     float(options.fov_clamp), float(options.alpha_min), options.extent == "opacity", means2d,
                     conics, depths, visible, bounds)
    return Projected(means2d=torch.from_numpy(means2d).to(dtype), conics=torch.from_numpy(conics).to(dtype),
                     depths=torch.from_numpy(depths).to(dtype), opacities=opacities,
                     visible=torch.from_numpy(visible), bounds=torch.from_numpy(bounds))


def _numpy(t: torch.Tensor) -> np.ndarray:
    """A contiguous float32/float64 numpy view of a CPU tensor (copied only when it must be)."""
    t = t.detach()
    if t.dtype not in (torch.float32, torch.float64):
        t = t.to(torch.float64)
    return np.ascontiguousarray(t.numpy())
