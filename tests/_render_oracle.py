"""Float64 brute-force rasterization oracle, written independently of fourlegs_engine.render.

Every pixel × every Gaussian, Gaussians blended one at a time front to back (stable depth sort), no
tiles, no footprint bounds, plain numpy. Conventions (docs/CONTRACTS.md "render"): EWA with the
Jacobian at x/z, y/z clamped to 1.3·tan(half fov) (principal-point aware), 0.3 px² low-pass, pixel
centres at +0.5, α = min(0.99, o·exp(−½dᵀΣ⁻¹d)), α < 1/255 skipped, stop before T < 1e-4.
"""
from __future__ import annotations

import numpy as np


def quat_to_rot(q: np.ndarray) -> np.ndarray:
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], axis=1)


def project(means, quats, log_scales, camera, eps2d=0.3, fov_clamp=1.3):
    """Returns uv (N,2), cov2d (N,2,2) with low-pass, z (N,), in_range (N,) bool."""
    R, t = camera.w2c[:3, :3], camera.w2c[:3, 3]
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    W, H = camera.width, camera.height
    pc = means @ R.T + t
    z = pc[:, 2]
    in_range = (z >= camera.near) & (z <= camera.far)
    zs = np.where(in_range, z, 1.0)
    u = fx * pc[:, 0] / zs + cx
    v = fy * pc[:, 1] / zs + cy
    ex = fov_clamp - 1.0
    tx = np.clip(pc[:, 0] / zs, -(cx / fx + ex * W / (2 * fx)), (W - cx) / fx + ex * W / (2 * fx))
    ty = np.clip(pc[:, 1] / zs, -(cy / fy + ex * H / (2 * fy)), (H - cy) / fy + ex * H / (2 * fy))
    J = np.zeros((len(z), 2, 3))
    J[:, 0, 0] = fx / zs
    J[:, 0, 2] = -fx * tx / zs
    J[:, 1, 1] = fy / zs
    J[:, 1, 2] = -fy * ty / zs
    Rq = quat_to_rot(quats)
    S = np.exp(log_scales)
    cov3 = np.einsum("nij,nj,nkj->nik", Rq, S * S, Rq)
    cov_cam = R @ cov3 @ R.T
    cov2 = J @ cov_cam @ np.transpose(J, (0, 2, 1)) + eps2d * np.eye(2)
    return np.stack([u, v], -1), cov2, z, in_range


def render(means, quats, log_scales, opacity_logits, camera, values, *, background=None):
    """Brute-force render.

    Args: numpy float64 arrays means (N,3), quats (N,4), log_scales (N,3), opacity_logits (N,),
        values (N,C). background (C,) or None.
    Returns: dict with "color" (H,W,C), "alpha" (H,W), "depth" (H,W) expected z, "depth_median" (H,W),
        "weights" (H*W, N) dense α·T.
    """
    means, quats, log_scales = (np.asarray(a, np.float64) for a in (means, quats, log_scales))
    values = np.asarray(values, np.float64)
    W, H = camera.width, camera.height
    N, C = values.shape
    uv, cov2, z, in_range = project(means, quats, log_scales, camera)
    opac = 1.0 / (1.0 + np.exp(-np.asarray(opacity_logits, np.float64)))
    xs, ys = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    px, py = xs.reshape(-1), ys.reshape(-1)
    T = np.ones(H * W)
    done = np.zeros(H * W, bool)
    color = np.zeros((H * W, C))
    weights = np.zeros((H * W, N))
    order = [i for i in np.argsort(z, kind="stable") if in_range[i]]
    for i in order:
        inv = np.linalg.inv(cov2[i])
        dx, dy = px - uv[i, 0], py - uv[i, 1]
        power = -0.5 * (inv[0, 0] * dx * dx + inv[1, 1] * dy * dy) - inv[0, 1] * dx * dy
        alpha = np.minimum(0.99, opac[i] * np.exp(power))
        live = (~done) & (alpha >= 1.0 / 255.0)
        test_T = T * (1.0 - alpha)
        stop = live & (test_T < 1e-4)
        done |= stop
        blend = live & ~stop
        w = np.where(blend, alpha * T, 0.0)
        weights[:, i] = w
        color += w[:, None] * values[i]
        T = np.where(blend, test_T, T)
    alpha_img = 1.0 - T
    if background is not None:
        color += T[:, None] * np.asarray(background, np.float64)
    zsum = weights @ np.where(in_range, z, 0.0)
    depth = np.where(alpha_img > 1e-6, zsum / np.where(alpha_img > 1e-6, alpha_img, 1.0), 0.0)
    median = np.zeros(H * W)
    for p in range(H * W):
        if alpha_img[p] <= 0:
            continue
        ws = weights[p, order]
        cum = np.cumsum(ws)
        k = int(np.argmax((cum >= 0.5 * alpha_img[p]) & (ws > 0)))
        median[p] = z[order[k]]
    return {"color": color.reshape(H, W, C), "alpha": alpha_img.reshape(H, W),
            "depth": depth.reshape(H, W), "depth_median": median.reshape(H, W), "weights": weights}
