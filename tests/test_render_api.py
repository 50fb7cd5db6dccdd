"""The rasterize / render_frame contract: requested outputs only, weights, backgrounds, SH, backends."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from _render_helpers import random_scene, view_cameras
from fourlegs_engine.errors import InputError
from fourlegs_engine.render import BlendWeights, RasterOptions, rasterize, render_frame
from fourlegs_engine.scene import GaussianFrame
from fourlegs_engine.scene.gaussians import SH_C0

GEOM = ("means", "rotations", "log_scales", "opacity_logits")


def _geom(scene):
    return [scene[k] for k in GEOM]


@pytest.mark.parametrize("outputs", [("rgb",), ("features",), ("alpha",), ("depth", "alpha"),
                                     ("depth_median",), ("weights",), ("rgb", "features", "depth")])
def test_returns_exactly_the_requested_outputs(outputs):
    scene = random_scene(80, 0, dtype=torch.float32)
    cam = view_cameras()[0]
    out = rasterize(*_geom(scene), cam, colors=scene["colors"], features=scene["features"], outputs=outputs)
    assert set(out) == set(outputs)
    shapes = {"rgb": (24, 32, 3), "features": (24, 32, 4), "depth": (24, 32, 1), "depth_median": (24, 32, 1),
              "alpha": (24, 32, 1)}
    for k in outputs:
        if k == "weights":
            assert isinstance(out[k], BlendWeights)
        else:
            assert out[k].shape == shapes[k] and out[k].dtype == torch.float32


def test_unrequested_inputs_are_never_read():
    """Channels that were not asked for are not touched: NaN features do not matter for an RGB render."""
    scene = random_scene(80, 1, dtype=torch.float32)
    cam = view_cameras()[0]
    poisoned = torch.full_like(scene["features"], float("nan"))
    out = rasterize(*_geom(scene), cam, colors=scene["colors"], features=poisoned, outputs=("rgb", "alpha"))
    assert torch.isfinite(out["rgb"]).all()
    with pytest.raises(InputError, match="features"):
        rasterize(*_geom(scene), cam, colors=scene["colors"], features=poisoned, outputs=("features",))


def test_weights_reproduce_the_image_and_support_a_lift():
    scene = random_scene(120, 2)
    cam = view_cameras()[0]
    bg = torch.tensor([0.2, 0.3, 0.4], dtype=torch.float64)
    out = rasterize(*_geom(scene), cam, colors=scene["colors"], background=bg, outputs=("rgb", "alpha", "weights"))
    w = out["weights"]
    assert w.width == 32 and w.height == 24 and not w.weight.requires_grad
    assert (w.pixel[1:] >= w.pixel[:-1]).all()  # grouped by pixel
    assert (w.weight > 0).all()
    HW = 24 * 32
    img = torch.zeros(HW, 3, dtype=torch.float64).index_add_(0, w.pixel, w.weight[:, None] * scene["colors"][w.gaussian])
    alpha = torch.zeros(HW, dtype=torch.float64).index_add_(0, w.pixel, w.weight)
    img = img + (1 - alpha)[:, None] * bg
    assert torch.allclose(img.reshape(24, 32, 3), out["rgb"], atol=1e-12)
    assert torch.allclose(alpha.reshape(24, 32, 1), out["alpha"], atol=1e-12)
    # learning-free lift: a per-Gaussian weighted average of a constant map returns that constant
    target = torch.full((HW,), 0.7, dtype=torch.float64)
    num = torch.zeros(120, dtype=torch.float64).index_add_(0, w.gaussian, w.weight * target[w.pixel])
    den = torch.zeros(120, dtype=torch.float64).index_add_(0, w.gaussian, w.weight)
    seen = den > 0
    assert seen.sum() > 50 and torch.allclose(num[seen] / den[seen], torch.tensor(0.7, dtype=torch.float64))


def test_backgrounds_per_channel():
    scene = random_scene(50, 3)
    cam = view_cameras()[0]
    args = (*_geom(scene), cam)
    out = rasterize(*args, colors=scene["colors"], features=scene["features"], background=[1.0, 0.5, 0.25],
                    feature_background=[1.0, 2.0, 3.0, 4.0], outputs=("rgb", "features", "alpha"))
    empty = out["alpha"][..., 0] == 0
    assert empty.any() and (~empty).any()
    assert torch.equal(out["rgb"][empty], torch.tensor([1.0, 0.5, 0.25], dtype=torch.float64).expand(int(empty.sum()), 3))
    assert torch.equal(out["features"][empty][:, 3], torch.full((int(empty.sum()),), 4.0, dtype=torch.float64))
    plain = rasterize(*args, features=scene["features"], outputs=("features", "alpha"))
    only_feat = rasterize(*args, features=scene["features"], background=[1.0, 2.0, 3.0, 4.0], outputs=("features",))
    expected = plain["features"] + (1 - plain["alpha"]) * torch.tensor([1.0, 2.0, 3.0, 4.0], dtype=torch.float64)
    assert torch.allclose(only_feat["features"], expected, atol=1e-12)


def test_any_channel_count():
    scene = random_scene(60, 4)
    cam = view_cameras()[0]
    base = rasterize(*_geom(scene), cam, features=scene["features"], outputs=("features",))["features"]
    for c in (1, 7, 130):
        feats = scene["features"][:, :1].repeat(1, c) * torch.arange(1, c + 1, dtype=torch.float64)
        out = rasterize(*_geom(scene), cam, features=feats, outputs=("features",))["features"]
        assert out.shape == (24, 32, c)
        assert torch.allclose(out[..., -1], base[..., 0] * c, atol=1e-12)


def test_render_frame_colors_sh_and_latents():
    scene = random_scene(60, 5, dtype=torch.float32)
    cam = view_cameras()[0]
    frame = GaussianFrame(means=scene["means"], rotations=scene["rotations"], log_scales=scene["log_scales"],
                          opacity_logits=scene["opacity_logits"], colors=scene["colors"],
                          latents=scene["features"])
    out = render_frame(frame, cam, outputs=("rgb", "features"))
    direct = rasterize(*_geom(scene), cam, colors=scene["colors"], features=scene["features"],
                       outputs=("rgb", "features"))
    assert torch.equal(out["rgb"], direct["rgb"]) and torch.equal(out["features"], direct["features"])
    # degree-0 SH: view independent, RGB = 0.5 + C0·dc
    dc = (scene["colors"] - 0.5) / SH_C0
    sh_frame = GaussianFrame(means=scene["means"], rotations=scene["rotations"], log_scales=scene["log_scales"],
                             opacity_logits=scene["opacity_logits"], colors=None, sh=dc[:, None, :])
    assert torch.allclose(render_frame(sh_frame, cam)["rgb"], direct["rgb"], atol=1e-6)


def test_sh_degree_one_is_view_dependent_and_matches_hand_evaluation():
    from fourlegs_engine.render.sh import eval_sh
    cam = view_cameras()[0]
    means = torch.tensor([[0.0, 0.0, 0.0]], dtype=torch.float64)
    sh = torch.zeros(1, 4, 3, dtype=torch.float64)
    sh[0, 3, 0] = 1.0  # the −C1·x term, red channel
    rgb = eval_sh(sh, means, cam)
    d = means[0].numpy() - cam.center
    d = d / np.linalg.norm(d)
    assert rgb[0, 0].item() == pytest.approx(max(0.0, 0.5 - 0.4886025119029199 * d[0]), abs=1e-12)


def test_backend_selection_on_cpu():
    scene = random_scene(20, 6, dtype=torch.float32)
    cam = view_cameras()[0]
    auto = rasterize(*_geom(scene), cam, colors=scene["colors"], backend="auto")
    torch_ = rasterize(*_geom(scene), cam, colors=scene["colors"], backend="torch")
    assert torch.equal(auto["rgb"], torch_["rgb"])
    with pytest.raises(InputError, match="CUDA|gsplat"):
        rasterize(*_geom(scene), cam, colors=scene["colors"], backend="gsplat")


def test_options_are_validated():
    for bad in (RasterOptions(extent="4sigma"), RasterOptions(alpha_min=0.0), RasterOptions(chunk=0),
                RasterOptions(transmittance_min=1.5), RasterOptions(eps2d=-1.0)):
        with pytest.raises(InputError):
            bad.check()
