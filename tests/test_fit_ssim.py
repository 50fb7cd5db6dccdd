"""The fit's SSIM (separable Gaussian window) against a direct 2D-window evaluation, value and gradient."""
from __future__ import annotations

import torch
import torch.nn.functional as F

from fourlegs_engine.fit.losses import SSIM_C1, SSIM_C2, SSIM_SIGMA, SSIM_WINDOW, ssim


def _ssim_2d(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """SSIM with the 11×11 window as one depthwise 2D convolution (the 3DGS formulation)."""
    x, y = a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None]
    C = x.shape[1]
    r = torch.arange(SSIM_WINDOW, dtype=a.dtype) - SSIM_WINDOW // 2
    g = torch.exp(-r * r / (2 * SSIM_SIGMA ** 2))
    g = g / g.sum()
    w = (g[:, None] * g[None, :]).expand(C, 1, SSIM_WINDOW, SSIM_WINDOW)
    blur = lambda t: F.conv2d(t, w, padding=SSIM_WINDOW // 2, groups=C)  # noqa: E731
    mu_x, mu_y = blur(x), blur(y)
    sxx, syy, sxy = blur(x * x) - mu_x ** 2, blur(y * y) - mu_y ** 2, blur(x * y) - mu_x * mu_y
    return ((2 * mu_x * mu_y + SSIM_C1) * (2 * sxy + SSIM_C2)
            / ((mu_x ** 2 + mu_y ** 2 + SSIM_C1) * (sxx + syy + SSIM_C2))).mean()


def test_separable_ssim_equals_the_2d_window():
    g = torch.Generator().manual_seed(0)
    target = torch.rand(37, 53, 3, generator=g, dtype=torch.float64)
    render = (target + 0.1 * torch.randn(37, 53, 3, generator=g, dtype=torch.float64)).clamp(0, 1)
    a = render.clone().requires_grad_()
    b = render.clone().requires_grad_()
    fast, ref = ssim(a, target), _ssim_2d(b, target)
    assert 0.3 < ref.item() < 0.99
    torch.testing.assert_close(fast, ref, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(torch.autograd.grad(fast, a)[0], torch.autograd.grad(ref, b)[0], rtol=1e-9, atol=1e-15)
    assert ssim(target, target).item() == 1.0 or abs(ssim(target, target).item() - 1.0) < 1e-12
