"""EWA projection of 3D Gaussians to screen-space ellipses, vectorized over all Gaussians.

The projection runs in float64 whatever the working dtype (it is O(N) and cheap next to the
rasterization) so huge, tiny and grazing Gaussians keep an exact, finite 2D covariance; the results
are cast back to the working dtype. Everything here is differentiable by torch autograd; nothing that
feeds the gradient divides by a camera depth outside [near, far] (those Gaussians are culled and
their depths replaced by 1 before any division), so culled Gaussians get zero, never NaN, gradients.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ..scene.camera import Camera
from ..scene.gaussians import quaternion_to_matrix
from .options import RasterOptions

#: log-scales above this are clamped (e^30 m ≈ 1e13 m: already larger than any scene; keeps squares finite)
MAX_LOG_SCALE = 30.0
#: the pixel bounds are widened by this many pixels so float32 rounding at the ellipse border never
#: drops a fragment that the float64 evaluation would keep
BOUND_MARGIN_PX = 1e-3


@dataclass
class Projected:
    """Screen-space Gaussians (all tensors on the input device).

    Attributes:
        means2d: (N,2) pixel coordinates of the centres (pixel centres at +0.5), working dtype.
        conics: (N,3) (a, b, c) of the inverse 2D covariance: dᵀΣ⁻¹d = a dx² + 2 b dx dy + c dy².
        depths: (N,) camera-space z, working dtype.
        opacities: (N,) sigmoid of the logits, working dtype.
        visible: (N,) bool: in front of the camera within [near, far], non-degenerate, touching at
            least one pixel with α ≥ alpha_min.
        bounds: (N,4) int64 inclusive pixel bounds x0, x1, y0, y1 (clipped to the image; meaningful
            where visible).
    """

    means2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    opacities: torch.Tensor
    visible: torch.Tensor
    bounds: torch.Tensor


def camera_tensors(camera: Camera, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """(3,3) world-to-camera rotation and (3,) translation as float64 tensors on ``device``."""
    w2c = torch.as_tensor(camera.w2c, dtype=torch.float64, device=device)
    return w2c[:3, :3], w2c[:3, 3]


def project_gaussians(means: torch.Tensor, rotations: torch.Tensor, log_scales: torch.Tensor,
                      opacity_logits: torch.Tensor, camera: Camera, options: RasterOptions,
                      dtype: torch.dtype) -> Projected:
    """Project Gaussians with the EWA approximation.

    Args:
        means: (N,3) world positions. rotations: (N,4) quaternions w,x,y,z (any non-zero norm).
        log_scales: (N,3) (−inf means scale 0). opacity_logits: (N,).
        camera: the view; its near/far bound the camera z of the Gaussians that are drawn.
        options: eps2d, fov_clamp, extent, alpha_min are used.
        dtype: working dtype of the outputs.
    Returns:
        :class:`Projected`.
    """
    device = means.device
    f64 = torch.float64
    R, t = camera_tensors(camera, device)
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    W, H = camera.width, camera.height

    p_cam = means.to(f64) @ R.T + t
    z = p_cam[:, 2]
    in_range = (z >= camera.near) & (z <= camera.far)
    z_safe = torch.where(in_range, z, torch.ones_like(z))
    x_over_z = p_cam[:, 0] / z_safe
    y_over_z = p_cam[:, 1] / z_safe
    means2d = torch.stack([fx * x_over_z + cx, fy * y_over_z + cy], dim=-1)

    # Jacobian of the perspective map, evaluated at a clamped direction (EWA is only locally valid)
    extra = options.fov_clamp - 1.0
    lim_x_pos, lim_x_neg = (W - cx) / fx + extra * W / (2 * fx), cx / fx + extra * W / (2 * fx)
    lim_y_pos, lim_y_neg = (H - cy) / fy + extra * H / (2 * fy), cy / fy + extra * H / (2 * fy)
    tx = x_over_z.clamp(-lim_x_neg, lim_x_pos)
    ty = y_over_z.clamp(-lim_y_neg, lim_y_pos)
    inv_z = 1.0 / z_safe
    zeros = torch.zeros_like(z)
    J = torch.stack([
        torch.stack([fx * inv_z, zeros, -fx * tx * inv_z], dim=-1),
        torch.stack([zeros, fy * inv_z, -fy * ty * inv_z], dim=-1),
    ], dim=-2)  # (N,2,3)

    rot = quaternion_to_matrix(rotations.to(f64))  # (N,3,3)
    scales = torch.exp(log_scales.to(f64).clamp(max=MAX_LOG_SCALE))  # (N,3)
    M = (J @ R) @ rot * scales[:, None, :]  # (N,2,3): Σ₂D = M Mᵀ
    m0, m1 = M[:, 0], M[:, 1]
    a = (m0 * m0).sum(-1)
    b = (m0 * m1).sum(-1)
    c = (m1 * m1).sum(-1)
    # det(M Mᵀ) = |m0 × m1|² (Cauchy–Binet): no cancellation for needles; then add the low-pass
    det_raw = (torch.linalg.cross(m0, m1) ** 2).sum(-1)
    eps = options.eps2d
    a_lp, c_lp = a + eps, c + eps
    det = det_raw + eps * (a + c) + eps * eps
    nondegenerate = det > 0
    det_safe = torch.where(nondegenerate, det, torch.ones_like(det))
    conics = torch.stack([c_lp / det_safe, -b / det_safe, a_lp / det_safe], dim=-1)

    opacities = torch.sigmoid(opacity_logits.to(dtype))
    with torch.no_grad():
        visible, bounds = _pixel_bounds(means2d, a_lp, b, c_lp, opacities.to(f64), options, W, H)
        visible &= in_range & nondegenerate & torch.isfinite(det)

    return Projected(means2d=means2d.to(dtype), conics=conics.to(dtype), depths=z.to(dtype),
                     opacities=opacities, visible=visible, bounds=bounds)


def _pixel_bounds(means2d: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor,
                  opacities: torch.Tensor, options: RasterOptions, W: int, H: int
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Inclusive pixel bounds of each footprint and whether it touches the image.

    Args: means2d (N,2); a, b, c (N,) the 2D covariance (low-pass included); opacities (N,) float64.
    Returns: visible (N,) bool, bounds (N,4) int64 x0, x1, y0, y1.
    """
    if options.extent == "opacity":
        # α ≥ alpha_min  ⇔  dᵀΣ⁻¹d ≤ 2 ln(o / alpha_min); that ellipse's box has half-sides sqrt(q·Σxx), sqrt(q·Σyy)
        q = 2.0 * torch.log(opacities.clamp_min(1e-300) / options.alpha_min)
        visible = q > 0
        q = q.clamp_min(0)
        rx, ry = torch.sqrt(q * a), torch.sqrt(q * c)
    else:
        lam_max = 0.5 * (a + c) + torch.sqrt((0.25 * (a - c) ** 2 + b * b).clamp_min(0))
        rx = ry = 3.0 * torch.sqrt(lam_max)
        visible = opacities >= options.alpha_min
    rx = rx + BOUND_MARGIN_PX
    ry = ry + BOUND_MARGIN_PX
    mx, my = means2d[:, 0].detach(), means2d[:, 1].detach()
    # pixel i (centre i + 0.5) is inside when |i + 0.5 − m| ≤ r; clamp before the integer conversion
    x0 = torch.ceil((mx - rx - 0.5).clamp(-1, W + 1)).long().clamp_min(0)
    x1 = torch.floor((mx + rx - 0.5).clamp(-2, W)).long().clamp_max(W - 1)
    y0 = torch.ceil((my - ry - 0.5).clamp(-1, H + 1)).long().clamp_min(0)
    y1 = torch.floor((my + ry - 0.5).clamp(-2, H)).long().clamp_max(H - 1)
    finite = torch.isfinite(mx) & torch.isfinite(my) & ~torch.isnan(rx) & ~torch.isnan(ry)
    visible = visible & finite & (x0 <= x1) & (y0 <= y1)
    return visible, torch.stack([x0, x1, y0, y1], dim=-1)

