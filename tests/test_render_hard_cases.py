"""Numerical edge cases: outputs and gradients stay finite, and the results are the right ones."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from _render_oracle import render as oracle_render
from fourlegs_engine.errors import InputError
from fourlegs_engine.render import RasterOptions, rasterize
from fourlegs_engine.scene import Camera

ALL_DIFF = ("rgb", "features", "depth", "alpha")
CAM = Camera.look_at((0, -4, 0), (0, 0, 0), width=24, height=16, focal=20.0, near=0.01, far=100.0)


def make(means, log_scales=None, logits=None, dtype=torch.float64, channels=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    means = torch.as_tensor(means, dtype=dtype).reshape(-1, 3)
    n = means.shape[0]
    return {
        "means": means,
        "rotations": torch.randn(n, 4, generator=g, dtype=torch.float64).to(dtype),
        "log_scales": (torch.full((n, 3), math.log(0.05), dtype=dtype) if log_scales is None
                       else torch.as_tensor(log_scales, dtype=dtype).reshape(n, 3)),
        "opacity_logits": (torch.full((n,), 2.0, dtype=dtype) if logits is None
                           else torch.as_tensor(logits, dtype=dtype).reshape(n)),
        "colors": torch.rand(n, 3, generator=g, dtype=torch.float64).to(dtype),
        "features": torch.randn(n, channels, generator=g, dtype=torch.float64).to(dtype),
    }


def render_with_grads(scene, cam=CAM, outputs=ALL_DIFF, options=None):
    """Render, backprop a loss touching every output, and check everything is finite."""
    leaves = {k: v.clone().requires_grad_() for k, v in scene.items()}
    out = rasterize(leaves["means"], leaves["rotations"], leaves["log_scales"], leaves["opacity_logits"], cam,
                    colors=leaves["colors"], features=leaves["features"], background=[0.1, 0.2, 0.3],
                    outputs=outputs, options=options)
    for k in outputs:
        assert torch.isfinite(out[k]).all(), k
    loss = sum((out[k] * (1.0 + torch.arange(out[k].numel(), dtype=out[k].dtype).reshape(out[k].shape) % 7)).sum()
               for k in outputs)
    if loss.requires_grad:
        grads = torch.autograd.grad(loss, list(leaves.values()), allow_unused=True)
        for name, g in zip(leaves, grads):
            assert g is None or torch.isfinite(g).all(), name
        return {k: v.detach() for k, v in out.items()}, dict(zip(leaves, grads))
    return {k: v.detach() for k, v in out.items()}, {}


def oracle(scene, cam=CAM):
    s = {k: v.detach().double().numpy() for k, v in scene.items()}
    return oracle_render(s["means"], s["rotations"], s["log_scales"], s["opacity_logits"], cam, s["colors"],
                         background=[0.1, 0.2, 0.3])


def test_behind_the_camera_is_not_drawn():
    front = make([[0, 0, 0], [0.2, 0, 0.1]])
    behind = make([[0, -6, 0], [0.1, -5, 0]])  # camera at y=-4 looks along +y
    both = {k: torch.cat([front[k], behind[k]]) for k in front}
    out_front, _ = render_with_grads(front)
    out_both, grads = render_with_grads(both)
    for k in ("rgb", "alpha", "depth"):
        assert torch.equal(out_front[k], out_both[k])
    assert out_both["alpha"].max() > 0.5
    assert grads["means"][2:].abs().max() == 0 and grads["colors"][2:].abs().max() == 0


def test_on_the_near_plane_is_drawn_and_no_hidden_near_cull():
    on_plane = make([[0, -4 + 0.05, 0]], log_scales=[[math.log(0.002)] * 3])
    just_before = make([[0, -4 + 0.0499, 0]], log_scales=[[math.log(0.002)] * 3])
    z = float(CAM.project(on_plane["means"].numpy())[1][0])
    cam = Camera(K=CAM.K, w2c=CAM.w2c, width=24, height=16, near=z)  # the near plane through the mean
    out, grads = render_with_grads(on_plane, cam)
    assert out["alpha"].max() > 0.5  # z == near is drawn
    assert out["depth"].max().item() == pytest.approx(z)
    assert grads["means"].abs().sum() > 0
    out, _ = render_with_grads(just_before, cam)
    assert out["alpha"].max() == 0
    # a close-up Gaussian at z = 0.1 (a hard-coded z ≤ 0.2 cull would drop it) is drawn with near = 0.01
    close = make([[0, -3.9, 0]], log_scales=[[math.log(0.003)] * 3])
    out, _ = render_with_grads(close, CAM)
    assert out["alpha"].max() > 0.5


def test_exactly_at_the_camera_centre():
    scene = make([[0, -4, 0], [0, 0, 0]])
    out, grads = render_with_grads(scene)
    ref = oracle(scene)
    assert np.abs(out["rgb"].numpy() - ref["color"]).max() < 1e-9
    assert grads["means"][0].abs().max() == 0


@pytest.mark.parametrize("log_scale", [-math.inf, math.log(1e-8)])
def test_zero_and_tiny_scales(log_scale):
    """Scale 0 and 1e-8 in all axes (points), in one axis (discs), in two axes (needles): the low-pass
    keeps each a ~0.55 px blob, exactly like the oracle."""
    ls = np.full((3, 3), math.log(0.2))
    ls[0, :] = log_scale
    ls[1, 0] = log_scale
    ls[2, :2] = log_scale
    scene = make([[0, 0, 0], [0.5, 0, 0.3], [-0.5, 0, -0.3]], log_scales=ls)
    out, grads = render_with_grads(scene)
    ref = oracle(scene)
    assert np.abs(out["rgb"].numpy() - ref["color"]).max() < 1e-9
    assert out["alpha"].max() > 0.3


def test_huge_scale_fills_the_screen():
    scene = make([[0, 0, 0]], log_scales=[[math.log(1e3)] * 3], logits=[0.0])
    out, grads = render_with_grads(scene)
    assert torch.allclose(out["alpha"], torch.full_like(out["alpha"], 0.5), atol=1e-6)
    assert grads["opacity_logits"].abs().item() > 0


@pytest.mark.parametrize("logit", [100.0, -100.0])
def test_extreme_opacity_logits(logit):
    scene = make([[0, 0, 0], [0, 1, 0]], log_scales=[[math.log(2.0)] * 3] * 2, logits=[logit, logit])
    out, grads = render_with_grads(scene)
    if logit > 0:
        assert out["alpha"].max().item() == pytest.approx(1 - 0.01 * 0.01, abs=1e-9)  # α capped at 0.99
    else:
        assert out["alpha"].max() == 0
    assert torch.isfinite(grads["opacity_logits"]).all()


def test_ten_thousand_gaussians_stacked_on_one_pixel():
    n = 10_000
    g = torch.Generator().manual_seed(3)
    means = torch.zeros(n, 3, dtype=torch.float64)
    means[:, 1] = torch.rand(n, generator=g, dtype=torch.float64) * 2  # same ray, different depths
    scene = make(means, log_scales=torch.full((n, 3), math.log(0.01)), logits=torch.full((n,), -2.0))
    cam = Camera.look_at((0, -4, 0), (0, 0, 0), width=6, height=4, focal=20.0)
    out, grads = render_with_grads(scene, cam, options=RasterOptions(chunk=64))
    ref = oracle(scene, cam)
    assert np.abs(out["rgb"].detach().numpy() - ref["color"]).max() < 1e-9
    assert ref["alpha"].max() > 0.999  # saturated: the stop rule was exercised
    used = (grads["colors"].abs().sum(1) > 0).sum().item()
    assert 0 < used < n  # Gaussians behind the saturation point get no gradient


def test_no_gaussians():
    scene = make(np.zeros((0, 3)))
    out = rasterize(scene["means"], scene["rotations"], scene["log_scales"], scene["opacity_logits"], CAM,
                    colors=scene["colors"], features=scene["features"], background=[0.1, 0.2, 0.3],
                    outputs=("rgb", "features", "depth", "depth_median", "alpha", "weights"))
    assert torch.allclose(out["rgb"], torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64).expand(16, 24, 3))
    assert out["alpha"].abs().max() == 0 and out["depth"].abs().max() == 0 and out["features"].abs().max() == 0
    assert out["weights"].pixel.numel() == 0


def test_one_gaussian():
    scene = make([[0.1, 0.2, -0.1]])
    out, grads = render_with_grads(scene)
    ref = oracle(scene)
    assert np.abs(out["rgb"].numpy() - ref["color"]).max() < 1e-9
    assert all(g.abs().sum() > 0 for g in grads.values())


def test_everything_off_screen():
    scene = make([[30, 0, 0], [-30, 1, 0], [0, 0, 25]])
    out, grads = render_with_grads(scene)
    assert out["alpha"].max() == 0
    assert all(g is None or g.abs().max() == 0 for g in grads.values())


def test_grazing_views_and_far_outside_the_frustum():
    """Flat discs seen edge-on, and large Gaussians far off-axis (the Jacobian clamp bounds them)."""
    n = 40
    g = torch.Generator().manual_seed(5)
    means = torch.stack([torch.rand(n, generator=g) * 6 - 3, torch.rand(n, generator=g) * 8 - 3.5,
                         torch.full((n,), -0.2)], -1).double()
    ls = torch.tensor([math.log(0.3), math.log(0.3), math.log(1e-4)]).double().expand(n, 3)
    scene = make(means, log_scales=ls)
    scene["rotations"] = torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).expand(n, 4).clone()
    far = make([[40, 0.5, 0], [-25, 1, 3]], log_scales=[[math.log(3.0)] * 3] * 2, seed=1)
    both = {k: torch.cat([scene[k], far[k]]) for k in scene}
    cam = Camera.look_at((0, -4, -0.19), (0, 0, -0.2), width=24, height=16, focal=20.0)
    out, _ = render_with_grads(both, cam)
    ref = oracle(both, cam)
    assert np.abs(out["rgb"].numpy() - ref["color"]).max() < 1e-9
    assert out["alpha"].max() > 0.1


def test_float16_features():
    scene = make(np.random.default_rng(0).normal(size=(50, 3)) * 0.5, dtype=torch.float32, channels=16)
    f16 = scene["features"].half().requires_grad_()
    out = rasterize(scene["means"], scene["rotations"], scene["log_scales"], scene["opacity_logits"], CAM,
                    features=f16, outputs=("features",))
    ref = rasterize(scene["means"], scene["rotations"], scene["log_scales"], scene["opacity_logits"], CAM,
                    features=f16.detach().float(), outputs=("features",), options=RasterOptions(cpu_kernel=False))
    assert out["features"].dtype == torch.float32  # blended in the working dtype
    assert torch.equal(out["features"], ref["features"])
    # without a gradient to track, the fused CPU kernel widens float16 the same way
    fused = rasterize(scene["means"], scene["rotations"], scene["log_scales"], scene["opacity_logits"], CAM,
                      features=f16.detach(), outputs=("features",))
    assert fused["features"].dtype == torch.float32
    torch.testing.assert_close(fused["features"], ref["features"], rtol=1e-4, atol=1e-5)
    out["features"].square().sum().backward()
    assert f16.grad.dtype == torch.float16 and torch.isfinite(f16.grad).all() and f16.grad.abs().sum() > 0


@pytest.mark.parametrize("field,bad", [("means", "nan"), ("means", "inf"), ("rotations", "zero"),
                                       ("log_scales", "nan"), ("log_scales", "inf"), ("colors", "nan"),
                                       ("opacity_logits", "nan")])
def test_invalid_values_raise_input_error(field, bad):
    scene = make([[0, 0, 0], [0.1, 0.1, 0]])
    t = scene[field]
    if bad == "zero":
        t[0] = 0
    else:
        t.view(-1)[0] = float(bad)
    with pytest.raises(InputError, match=field):
        rasterize(scene["means"], scene["rotations"], scene["log_scales"], scene["opacity_logits"], CAM,
                  colors=scene["colors"], outputs=("rgb",))


def test_invalid_camera_and_arguments_raise_input_error():
    scene = make([[0, 0, 0]])
    args = (scene["means"], scene["rotations"], scene["log_scales"], scene["opacity_logits"])
    K = CAM.K.copy()
    K[0, 0] = 0.0
    bad_cam = Camera(K=K, w2c=CAM.w2c, width=24, height=16)
    with pytest.raises(InputError, match="focal"):
        rasterize(*args, bad_cam, colors=scene["colors"])
    K[0, 0] = -20.0
    with pytest.raises(InputError, match="focal"):
        rasterize(*args, Camera(K=K, w2c=CAM.w2c, width=24, height=16), colors=scene["colors"])
    with pytest.raises(InputError, match="outputs"):
        rasterize(*args, CAM, colors=scene["colors"], outputs=("rgb", "normals"))
    with pytest.raises(InputError, match="colors"):
        rasterize(*args, CAM, outputs=("rgb",))
    with pytest.raises(InputError, match="features"):
        rasterize(*args, CAM, features=torch.zeros(2, 4, dtype=torch.float64), outputs=("features",))
    with pytest.raises(InputError, match="background"):
        rasterize(*args, CAM, colors=scene["colors"], background=[0, 0])
    with pytest.raises(InputError, match="backend"):
        rasterize(*args, CAM, colors=scene["colors"], backend="vulkan")
    with pytest.raises(InputError, match="tile_size"):
        rasterize(*args, CAM, colors=scene["colors"], options=RasterOptions(tile_size=0))


from hypothesis import given, settings, strategies as st  # noqa: E402


@settings(max_examples=25)
@given(log_scale=st.floats(min_value=math.log(1e-8), max_value=math.log(1e3)),
       logit=st.floats(min_value=-100, max_value=100),
       y=st.floats(min_value=-8.0, max_value=6.0),
       x=st.floats(min_value=-30.0, max_value=30.0),
       aniso=st.floats(min_value=-8.0, max_value=8.0))
def test_property_finite_and_consistent(log_scale, logit, y, x, aniso):
    """Any scale, opacity and position (behind, at, beside or in front of the camera): finite outputs
    and gradients, alpha in [0, 1), and the blending weights add up to alpha."""
    means = [[x, y, 0.1], [0.0, 0.0, 0.0], [0.05, y + 0.5, -0.05]]
    ls = [[log_scale, log_scale + aniso, log_scale], [math.log(0.05)] * 3, [log_scale, log_scale, log_scale - aniso]]
    scene = make(means, log_scales=np.clip(ls, math.log(1e-9), math.log(2e3)), logits=[logit, 0.0, logit])
    out, grads = render_with_grads(scene, outputs=("rgb", "depth", "alpha"))
    assert (out["alpha"] >= 0).all() and (out["alpha"] < 1).all()
    w = rasterize(scene["means"], scene["rotations"], scene["log_scales"], scene["opacity_logits"], CAM,
                  outputs=("weights",))["weights"]
    total = torch.zeros(16 * 24, dtype=torch.float64).index_add_(0, w.pixel, w.weight)
    assert torch.allclose(total.reshape(16, 24, 1), out["alpha"], atol=1e-12)
