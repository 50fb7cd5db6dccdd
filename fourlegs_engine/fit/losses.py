"""Losses of the Dynamic 3D Gaussians fit: image (L1 + D-SSIM) and the physical priors.

On CPU tensors the SSIM and the priors run as the fused kernels of :mod:`.fused_losses` (one pass forward,
one backward); the torch formulations here (:func:`ssim_reference`, :meth:`Priors.reference`) are their
test oracles and serve every other device and dtype."""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from .fused_losses import FusedImageLoss, FusedPriors, FusedSSIM, fused_applies

#: SSIM window (11 px Gaussian, σ 1.5) and constants for images in [0, 1]
SSIM_WINDOW, SSIM_SIGMA = 11, 1.5
SSIM_C1, SSIM_C2 = 0.01 ** 2, 0.03 ** 2


def _window_1d(dtype: torch.dtype, device) -> torch.Tensor:
    """(SSIM_WINDOW,) normalized Gaussian: the 2D window is its outer product with itself."""
    x = torch.arange(SSIM_WINDOW, dtype=dtype, device=device) - SSIM_WINDOW // 2
    g = torch.exp(-x * x / (2 * SSIM_SIGMA ** 2))
    return g / g.sum()


def ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two (H,W,C) images (Gaussian window, zero padding as in 3DGS); scalar tensor.

    The fused kernel serves CPU float32/float64 images when ``b`` needs no gradient; otherwise
    :func:`ssim_reference`."""
    if a.dim() == 3 and not b.requires_grad and fused_applies(a, b):
        return FusedSSIM.apply(a, b, _window_1d(a.dtype, a.device), SSIM_C1, SSIM_C2)
    return ssim_reference(a, b)


def ssim_reference(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """:func:`ssim` as torch operations (any device, gradients to both images).

    The five local moments are blurred together, the separable window as a row pass and a column pass
    (2·11 instead of 11² multiply-adds per pixel; zero padding makes it equal to the 2D window)."""
    x = a.permute(2, 0, 1)[None]
    y = b.permute(2, 0, 1)[None]
    C = x.shape[1]
    g = _window_1d(x.dtype, x.device)
    pad = SSIM_WINDOW // 2
    moments = torch.cat([x, y, x * x, y * y, x * y], dim=1)  # (1, 5C, H, W)
    rows = g.view(1, 1, 1, SSIM_WINDOW).expand(5 * C, 1, 1, SSIM_WINDOW)
    cols = g.view(1, 1, SSIM_WINDOW, 1).expand(5 * C, 1, SSIM_WINDOW, 1)
    blurred = F.conv2d(F.conv2d(moments, rows, padding=(0, pad), groups=5 * C), cols, padding=(pad, 0), groups=5 * C)
    mu_x, mu_y, e_xx, e_yy, e_xy = blurred.split(C, dim=1)
    sxx = e_xx - mu_x ** 2
    syy = e_yy - mu_y ** 2
    sxy = e_xy - mu_x * mu_y
    num = (2 * mu_x * mu_y + SSIM_C1) * (2 * sxy + SSIM_C2)
    den = (mu_x ** 2 + mu_y ** 2 + SSIM_C1) * (sxx + syy + SSIM_C2)
    return (num / den).mean()


def image_loss(render: torch.Tensor, target: torch.Tensor, l1_weight: float = 0.8) -> torch.Tensor:
    """(1−λ_ssim)·L1 + λ_ssim·(1 − SSIM) with λ_ssim = 1 − ``l1_weight`` (one fused kernel on CPU when
    ``target`` needs no gradient)."""
    if render.dim() == 3 and not target.requires_grad and fused_applies(render, target):
        return FusedImageLoss.apply(render, target, _window_1d(render.dtype, render.device), SSIM_C1, SSIM_C2,
                                    l1_weight)
    return image_loss_reference(render, target, l1_weight)


def image_loss_reference(render: torch.Tensor, target: torch.Tensor, l1_weight: float = 0.8) -> torch.Tensor:
    """:func:`image_loss` as torch operations."""
    return l1_weight * (render - target).abs().mean() + (1.0 - l1_weight) * (1.0 - ssim_reference(render, target))


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    """PSNR in dB of images in [0, 1] (a is clipped to [0, 1] first)."""
    mse = float(((a.clamp(0, 1) - b) ** 2).mean())
    return 100.0 if mse <= 1e-10 else -10.0 * math.log10(mse)


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product of (...,4) quaternions w,x,y,z."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz,
                        aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw], dim=-1)


def quat_conjugate(q: torch.Tensor) -> torch.Tensor:
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def _weighted_norm(diff: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """Mean over (N,K) of weight·‖diff‖ with a smooth square root (finite gradient at 0)."""
    return (torch.sqrt((diff * diff).sum(-1) + 1e-20) * weight).mean()


class Priors:
    """Local rigidity, rotation similarity and long-term isometry over kNN neighbours fixed at the
    first timestep (Luiten et al. §4).

    Args:
        neighbors: (N,K) int64 neighbour indices among the foreground Gaussians.
        weights: (N,K) exp(−λ d²) of the first-timestep distances.
        distances: (N,K) first-timestep distances (for isometry).
    """

    def __init__(self, neighbors: torch.Tensor, weights: torch.Tensor, distances: torch.Tensor):
        self.neighbors, self.weights, self.distances = neighbors, weights, distances

    def __call__(self, means: torch.Tensor, rotations: torch.Tensor, prev_means: torch.Tensor,
                 prev_rotations: torch.Tensor) -> dict[str, torch.Tensor]:
        """Loss terms for the current (N,3) means, (N,4) unit rotations against the previous timestep's
        (the fused kernel on CPU when the previous timestep needs no gradient, else :meth:`reference`).

        Returns:
            {"rigid", "rot", "iso"} scalar tensors.
        """
        if (not prev_means.requires_grad and not prev_rotations.requires_grad
                and fused_applies(means, rotations, prev_means, prev_rotations, self.weights, self.distances)):
            rigid, rot, iso = FusedPriors.apply(means, rotations, prev_means, prev_rotations, self.neighbors,
                                                self.weights, self.distances)
            return {"rigid": rigid, "rot": rot, "iso": iso}
        return self.reference(means, rotations, prev_means, prev_rotations)

    def reference(self, means: torch.Tensor, rotations: torch.Tensor, prev_means: torch.Tensor,
                  prev_rotations: torch.Tensor) -> dict[str, torch.Tensor]:
        """:meth:`__call__` as torch operations (any device, gradients to every input)."""
        from ..scene.gaussians import quaternion_to_matrix

        rel = quat_multiply(rotations, quat_conjugate(prev_rotations))  # R_t R_{t-1}^{-1}
        R = quaternion_to_matrix(rel)  # (N,3,3)
        nb = self.neighbors
        offset = means[nb] - means[:, None]  # (N,K,3)
        prev_offset = prev_means[nb] - prev_means[:, None]
        # the neighbour offsets of t, rotated back by the Gaussian's own rotation change, should equal t−1's
        back = torch.einsum("nji,nkj->nki", R, offset)
        rigid = _weighted_norm(back - prev_offset, self.weights)
        rot = _weighted_norm(rel[nb] - rel[:, None], self.weights)
        iso = (torch.sqrt((offset * offset).sum(-1) + 1e-20) - self.distances).abs().mul(self.weights).mean()
        return {"rigid": rigid, "rot": rot, "iso": iso}
