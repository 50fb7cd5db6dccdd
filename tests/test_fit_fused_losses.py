"""The fused SSIM and priors kernels against their torch formulations (float64 oracles): values,
gradients, finite differences, and the edges (flat images, images smaller than the window, coincident
neighbours, isometry exactly met)."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from fourlegs_engine.fit import fused_losses
from fourlegs_engine.fit.fused_losses import FusedImageLoss, FusedPriors, FusedSSIM
from fourlegs_engine.fit.losses import (SSIM_C1, SSIM_C2, Priors, _window_1d, image_loss, image_loss_reference, ssim,
                                       ssim_reference)

pytestmark = pytest.mark.skipif(fused_losses.numba is None, reason="numba not installed")


def _fused_ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return FusedSSIM.apply(a, b, _window_1d(a.dtype, a.device), SSIM_C1, SSIM_C2)


def _pair(h: int, w: int, c: int, seed: int, dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    target = torch.rand(h, w, c, generator=g, dtype=dtype)
    render = (target + 0.15 * torch.randn(h, w, c, generator=g, dtype=dtype)).clamp(0, 1)
    return render, target


def _value_and_grad(fn, render: torch.Tensor, target: torch.Tensor) -> tuple[float, torch.Tensor]:
    a = render.clone().requires_grad_()
    value = fn(a, target)
    return float(value.detach()), torch.autograd.grad(value, a)[0]


@pytest.mark.parametrize("shape", [(37, 53, 3), (12, 7, 1), (4, 30, 2), (1, 1, 3), (64, 96, 3)])
def test_fused_ssim_equals_the_torch_ssim_in_float64(shape):
    render, target = _pair(*shape, seed=sum(shape))
    fused, fused_grad = _value_and_grad(_fused_ssim, render, target)
    ref, ref_grad = _value_and_grad(ssim_reference, render, target)
    assert abs(fused - ref) < 1e-13
    assert fused_grad.shape == render.shape
    torch.testing.assert_close(fused_grad, ref_grad, rtol=1e-10, atol=1e-16)


def test_fused_ssim_in_float32_agrees_with_the_float64_oracle():
    render, target = _pair(48, 80, 3, seed=3)
    fused, fused_grad = _value_and_grad(_fused_ssim, render.float(), target.float())
    ref, ref_grad = _value_and_grad(ssim_reference, render, target)
    assert fused_grad.dtype == torch.float32
    assert abs(fused - ref) < 2e-6
    torch.testing.assert_close(fused_grad.double(), ref_grad, rtol=1e-3, atol=1e-9)


def test_fused_ssim_gradient_matches_finite_differences():
    render, target = _pair(9, 11, 2, seed=5)
    a = render.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda x: _fused_ssim(x, target), (a,), eps=1e-6, atol=1e-8, rtol=1e-5)


@settings(max_examples=40, deadline=None)
@given(h=st.integers(1, 14), w=st.integers(1, 14), c=st.integers(1, 3), seed=st.integers(0, 2 ** 16),
       kind=st.sampled_from(["random", "flat", "black", "white", "binary", "identical"]))
def test_fused_ssim_stays_finite_and_equal_to_the_oracle_on_hard_images(h, w, c, seed, kind):
    g = torch.Generator().manual_seed(seed)
    target = torch.rand(h, w, c, generator=g, dtype=torch.float64)
    render = {"random": lambda: torch.rand(h, w, c, generator=g, dtype=torch.float64),
              "flat": lambda: torch.full((h, w, c), 0.37, dtype=torch.float64),
              "black": lambda: torch.zeros(h, w, c, dtype=torch.float64),
              "white": lambda: torch.ones(h, w, c, dtype=torch.float64),
              "binary": lambda: (torch.rand(h, w, c, generator=g, dtype=torch.float64) > 0.5).double(),
              "identical": lambda: target.clone()}[kind]()
    if kind in ("flat", "black", "white"):
        target = render.clone()  # zero variance on both sides: SSIM is exactly 1
    fused, fused_grad = _value_and_grad(_fused_ssim, render, target)
    ref, ref_grad = _value_and_grad(ssim_reference, render, target)
    assert np.isfinite(fused) and torch.isfinite(fused_grad).all()
    assert abs(fused - ref) < 1e-12
    torch.testing.assert_close(fused_grad, ref_grad, rtol=1e-9, atol=1e-14)
    if kind in ("flat", "black", "white", "identical"):
        assert abs(fused - 1.0) < 1e-12


def test_ssim_dispatches_to_the_fused_kernel_only_where_it_applies():
    render, target = _pair(10, 12, 3, seed=1)
    assert ssim(render.requires_grad_(), target).grad_fn.name() == "FusedSSIMBackward"
    both = ssim(render, target.clone().requires_grad_())  # a gradient for the target: the torch formulation
    assert both.grad_fn.name() != "FusedSSIMBackward"
    # a non-contiguous view is read correctly
    wide = torch.rand(3, 10, 12, dtype=torch.float64)
    assert abs(float(ssim(wide.permute(1, 2, 0), target)) - float(ssim_reference(wide.permute(1, 2, 0), target))) < 1e-13


@pytest.mark.parametrize("l1_weight", [0.8, 0.0, 1.0])
def test_fused_image_loss_equals_l1_plus_dssim_in_torch(l1_weight):
    render, target = _pair(23, 31, 3, seed=11)
    render[:4] = target[:4]  # pixels where |a − b| has its kink
    fused, fused_grad = _value_and_grad(lambda a, b: image_loss(a, b, l1_weight), render, target)
    ref, ref_grad = _value_and_grad(lambda a, b: image_loss_reference(a, b, l1_weight), render, target)
    assert abs(fused - ref) < 1e-13
    torch.testing.assert_close(fused_grad, ref_grad, rtol=1e-10, atol=1e-16)


def test_fused_image_loss_gradient_matches_finite_differences():
    render, target = _pair(8, 10, 3, seed=13)
    a = render.clone().requires_grad_()
    window = _window_1d(torch.float64, "cpu")
    assert torch.autograd.gradcheck(lambda x: FusedImageLoss.apply(x, target, window, SSIM_C1, SSIM_C2, 0.8), (a,),
                                    eps=1e-6, atol=1e-8, rtol=1e-5)


def test_two_losses_in_flight_keep_their_own_partials():
    """A fit step takes the rgb and the segmentation loss before one backward pass."""
    (r1, t1), (r2, t2) = _pair(20, 24, 3, seed=1), _pair(20, 24, 3, seed=2)
    a1, a2 = r1.clone().requires_grad_(), r2.clone().requires_grad_()
    (image_loss(a1, t1) + 3.0 * image_loss(a2, t2)).backward()
    b1, b2 = r1.clone().requires_grad_(), r2.clone().requires_grad_()
    (image_loss_reference(b1, t1) + 3.0 * image_loss_reference(b2, t2)).backward()
    torch.testing.assert_close(a1.grad, b1.grad, rtol=1e-10, atol=1e-16)
    torch.testing.assert_close(a2.grad, b2.grad, rtol=1e-10, atol=1e-16)


# ---------------------------------------------------------------------------------------------- priors
def _scene(n: int, k: int, seed: int, dtype=torch.float64, coincident: bool = False):
    from scipy.spatial import cKDTree

    g = torch.Generator().manual_seed(seed)
    x0 = torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.05
    if coincident:
        x0[1] = x0[0]  # two Gaussians at one place: zero-length offsets
    q0 = torch.nn.functional.normalize(torch.randn(n, 4, generator=g, dtype=torch.float64), dim=-1)
    dist, nb = cKDTree(x0.numpy()).query(x0.numpy(), k=k + 1)
    priors = Priors(torch.from_numpy(nb[:, 1:]), torch.from_numpy(np.exp(-300 * dist[:, 1:] ** 2)).to(dtype),
                    torch.from_numpy(dist[:, 1:]).to(dtype))
    x1 = x0 + 0.01 * torch.randn(n, 3, generator=g, dtype=torch.float64)
    if coincident:
        x1[1] = x1[0]
    q1 = torch.nn.functional.normalize(q0 + 0.2 * torch.randn(n, 4, generator=g, dtype=torch.float64), dim=-1)
    return priors, x0.to(dtype), q0.to(dtype), x1.to(dtype), q1.to(dtype)


def _terms_and_grads(fn, x1, q1, x0, q0, weights=(1.3, 0.7, 2.1)):
    x = x1.clone().requires_grad_()
    q = q1.clone().requires_grad_()
    terms = fn(x, q, x0, q0)
    loss = sum(w * terms[k] for w, k in zip(weights, ("rigid", "rot", "iso")))
    gx, gq = torch.autograd.grad(loss, (x, q))
    return {k: float(v.detach()) for k, v in terms.items()}, gx, gq


@pytest.mark.parametrize("n,k,coincident", [(300, 8, False), (40, 20, False), (2, 1, False), (50, 6, True)])
def test_fused_priors_equal_the_torch_priors_in_float64(n, k, coincident):
    priors, x0, q0, x1, q1 = _scene(n, k, seed=n + k, coincident=coincident)
    fused, fgx, fgq = _terms_and_grads(priors, x1, q1, x0, q0)
    ref, rgx, rgq = _terms_and_grads(priors.reference, x1, q1, x0, q0)
    for name in ("rigid", "rot", "iso"):
        assert abs(fused[name] - ref[name]) <= 1e-13 * max(1.0, abs(ref[name])), name
    torch.testing.assert_close(fgx, rgx, rtol=1e-10, atol=1e-15)
    torch.testing.assert_close(fgq, rgq, rtol=1e-10, atol=1e-15)
    assert torch.isfinite(fgx).all() and torch.isfinite(fgq).all()


def test_fused_priors_gradient_matches_finite_differences():
    priors, x0, q0, x1, q1 = _scene(12, 4, seed=7)
    nb, w, d = priors.neighbors, priors.weights, priors.distances

    def loss(x, q):
        rigid, rot, iso = FusedPriors.apply(x, q, x0, q0, nb, w, d)
        return 1.3 * rigid + 0.7 * rot + 2.1 * iso

    x = x1.clone().requires_grad_()
    q = q1.clone().requires_grad_()
    assert torch.autograd.gradcheck(loss, (x, q), eps=1e-7, atol=1e-7, rtol=1e-5)


def test_fused_priors_in_float32_agree_with_the_float64_oracle():
    priors64, x0, q0, x1, q1 = _scene(200, 10, seed=2)
    priors32 = Priors(priors64.neighbors, priors64.weights.float(), priors64.distances.float())
    fused, fgx, fgq = _terms_and_grads(priors32, x1.float(), q1.float(), x0.float(), q0.float())
    ref, rgx, rgq = _terms_and_grads(priors64.reference, x1, q1, x0, q0)
    assert fgx.dtype == torch.float32 and fgq.dtype == torch.float32
    for name in ("rigid", "rot", "iso"):
        assert abs(fused[name] - ref[name]) <= 1e-5 * abs(ref[name]) + 1e-9, name
    torch.testing.assert_close(fgx.double(), rgx, rtol=2e-3, atol=1e-6 * float(rgx.abs().max()))
    torch.testing.assert_close(fgq.double(), rgq, rtol=2e-3, atol=1e-6 * float(rgq.abs().max()))


def test_priors_with_a_previous_timestep_that_needs_a_gradient_use_the_torch_formulation():
    priors, x0, q0, x1, q1 = _scene(30, 5, seed=4)
    fused = priors(x1.clone().requires_grad_(), q1, x0, q0)
    assert fused["rigid"].grad_fn.name() == "FusedPriorsBackward"
    x0g = x0.clone().requires_grad_()
    terms = priors(x1, q1, x0g, q0)
    assert terms["rigid"].grad_fn.name() != "FusedPriorsBackward"
    assert torch.autograd.grad(terms["rigid"], x0g)[0].abs().sum() > 0
