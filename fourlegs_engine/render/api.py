"""The public rasterization entry points: :func:`rasterize` and :func:`render_frame`."""
from __future__ import annotations

from typing import Mapping, Sequence

import torch

from ..errors import InputError
from ..scene.camera import Camera
from .options import OUTPUT_NAMES, BlendWeights, RasterOptions


def rasterize(means: torch.Tensor, rotations: torch.Tensor, log_scales: torch.Tensor,
              opacity_logits: torch.Tensor, camera: Camera, *, colors: torch.Tensor | None = None,
              features: torch.Tensor | None = None, background: torch.Tensor | Sequence[float] | None = None,
              feature_background: torch.Tensor | Sequence[float] | None = None,
              outputs: Sequence[str] = ("rgb",), options: RasterOptions | None = None,
              backend: str = "auto") -> dict[str, torch.Tensor | BlendWeights]:
    """Render one view of one timestep's Gaussians.

    Args:
        means: (N,3) world positions; its dtype (float32 or float64) is the working dtype.
        rotations: (N,4) quaternions w,x,y,z (normalized here; zero length is an error).
        log_scales: (N,3) natural-log scales (−inf = scale 0 is allowed).
        opacity_logits: (N,) opacity = sigmoid(logit).
        camera: :class:`~fourlegs_engine.scene.Camera`; its width/height/near/far are used as is.
        colors: (N,3), needed for "rgb".
        features: (N,C) any C ≥ 1 (float16/bfloat16 allowed: blended in the working dtype), needed for
            "features".
        background: (3,) colour behind the Gaussians for "rgb" (default black). When only
            "features" are rendered (no "rgb"), it is the (C,) feature background instead.
        feature_background: (C,) background for "features" (default zeros); overrides the rule above.
        outputs: any of "rgb" (H,W,3), "features" (H,W,C), "depth" (H,W,1) expected camera-z depth
            Σwz/Σw (0 where alpha < 1e-6), "depth_median" (H,W,1) depth of the Gaussian where the
            accumulated weight reaches half of the pixel's alpha (0 where nothing is drawn), "alpha"
            (H,W,1), "weights" (:class:`BlendWeights`, detached). Only these are computed.
        options: :class:`RasterOptions` (defaults: 3DGS conventions).
        backend: "torch", "gsplat" (CUDA only) or "auto" (gsplat when the tensors are on CUDA, gsplat is
            installed and supports every requested output; torch otherwise).
    Returns:
        dict output name -> tensor in the working dtype (or :class:`BlendWeights` for "weights").
        Differentiable w.r.t. colors, features, opacity logits, means, log_scales and rotations.
    Raises:
        InputError: unknown output, missing colors/features, bad shapes, NaN/Inf input, invalid camera.
    """
    from .backends import select_backend

    options = (options or RasterOptions()).check()
    outputs = _check_outputs(outputs, colors, features)
    camera.validate()
    dtype = means.dtype if means.dtype in (torch.float32, torch.float64) else torch.float32
    if options.validate:
        _check_inputs(means, rotations, log_scales, opacity_logits,
                      colors if "rgb" in outputs else None, features if "features" in outputs else None)
    device = means.device
    bg_rgb, bg_feat = _backgrounds(background, feature_background, outputs, colors, features, dtype, device)
    impl = select_backend(backend, device, outputs)
    return impl(means.to(dtype), rotations, log_scales, opacity_logits, camera, colors=colors,
                features=features, bg_rgb=bg_rgb, bg_feat=bg_feat, outputs=outputs, options=options,
                dtype=dtype)


def splat(means: torch.Tensor, rotations: torch.Tensor, log_scales: torch.Tensor,
          opacity_logits: torch.Tensor, camera: Camera, pixel_values: torch.Tensor, *,
          options: RasterOptions | None = None, out: torch.Tensor | None = None) -> torch.Tensor:
    """The transpose of rendering features: per-Gaussian sums of per-pixel values weighted by α·T.

    ``splat(..., v)[i] = Σ_p w_i(p) v(p)`` with w_i(p) = α_i T_i the blending weights of Gaussian i
    at pixel p (the ``"weights"`` output), so ``<render(f), v> = <f, splat(v)>``. Computed in one
    front-to-back pass without materializing the weights (much cheaper than ``"weights"`` when only
    Σ_p w·v is needed; append a channel of ones to also get Σ_p w). Torch backend, no autograd.

    Args:
        means, rotations, log_scales, opacity_logits, camera: as for :func:`rasterize`.
        pixel_values: (H,W,S) values per pixel of ``camera``'s image (any float dtype).
        options: :class:`RasterOptions`.
        out: optional (N,S) tensor of the working dtype to add the sums to (accumulating several
            views without a temporary per view); it is returned.
    Returns:
        (N,S) in the working dtype (that of ``means``: float32 or float64).
    """
    from .torch_backend import splat_torch

    options = (options or RasterOptions()).check()
    camera.validate()
    dtype = means.dtype if means.dtype in (torch.float32, torch.float64) else torch.float32
    if options.validate:
        _check_inputs(means, rotations, log_scales, opacity_logits, None, None)
    if (not isinstance(pixel_values, torch.Tensor) or pixel_values.ndim != 3
            or tuple(pixel_values.shape[:2]) != (camera.height, camera.width)):
        raise InputError(f"must be ({camera.height}, {camera.width}, S), got {_shape(pixel_values)}",
                         field="pixel_values")
    if not _all_finite(pixel_values):
        raise InputError("contains NaN or Inf", field="pixel_values")
    if out is not None and (tuple(out.shape) != (means.shape[0], pixel_values.shape[2]) or out.dtype != dtype
                            or out.device != means.device):
        raise InputError(f"must be a ({means.shape[0]}, {pixel_values.shape[2]}) {dtype} tensor on {means.device}, "
                         f"got {_shape(out)}", field="out")
    return splat_torch(means.detach().to(dtype), rotations.detach(), log_scales.detach(), opacity_logits.detach(),
                       camera, pixel_values.detach().to(device=means.device, dtype=dtype), options, dtype, out)


def render_frame(frame, camera: Camera, outputs: Sequence[str] = ("rgb",), features: torch.Tensor | None = None,
                 **kw) -> dict[str, torch.Tensor | BlendWeights]:
    """Render a :class:`~fourlegs_engine.scene.GaussianFrame` (colours from ``frame.colors``, or its SH
    evaluated for this camera). ``features`` (N,C) defaults to ``frame.latents`` when "features" is
    requested. Other keyword arguments go to :func:`rasterize`."""
    from .sh import frame_colors

    colors = None
    if "rgb" in outputs:
        colors = frame_colors(frame, camera)
    if "features" in outputs and features is None:
        features = frame.latents
    return rasterize(frame.means, frame.rotations, frame.log_scales, frame.opacity_logits, camera,
                     colors=colors, features=features, outputs=outputs, **kw)


# ------------------------------------------------------------------------------------------ checks
def _check_outputs(outputs: Sequence[str], colors, features) -> tuple[str, ...]:
    if isinstance(outputs, str):
        outputs = (outputs,)
    outs = tuple(dict.fromkeys(outputs))
    unknown = [o for o in outs if o not in OUTPUT_NAMES]
    if unknown:
        raise InputError(f"unknown output(s) {unknown}; choose from {OUTPUT_NAMES}", field="outputs")
    if "rgb" in outs and colors is None:
        raise InputError('"rgb" was requested but no colors were given', field="colors")
    if "features" in outs and features is None:
        raise InputError('"features" was requested but no features were given', field="features")
    return outs


def _check_inputs(means, rotations, log_scales, opacity_logits, colors, features) -> None:
    if not isinstance(means, torch.Tensor) or means.ndim != 2 or means.shape[1] != 3:
        raise InputError(f"must be an (N,3) tensor, got {_shape(means)}", field="means")
    N = means.shape[0]
    expect: Mapping[str, tuple] = {"rotations": (N, 4), "log_scales": (N, 3), "opacity_logits": (N,)}
    tensors = {"rotations": rotations, "log_scales": log_scales, "opacity_logits": opacity_logits}
    for name, t in tensors.items():
        if not isinstance(t, torch.Tensor) or tuple(t.shape) != expect[name]:
            raise InputError(f"must have shape {expect[name]}, got {_shape(t)}", field=name)
    if colors is not None and (not isinstance(colors, torch.Tensor) or tuple(colors.shape) != (N, 3)):
        raise InputError(f"must have shape ({N}, 3), got {_shape(colors)}", field="colors")
    if features is not None and (not isinstance(features, torch.Tensor) or features.ndim != 2
                                 or features.shape[0] != N or features.shape[1] < 1):
        raise InputError(f"must have shape ({N}, C) with C >= 1, got {_shape(features)}", field="features")
    for name, t in (("means", means), ("rotations", rotations), ("colors", colors), ("features", features)):
        if t is not None and not _all_finite(t):
            raise InputError("contains NaN or Inf", field=name)
    if log_scales.numel():
        lo, hi = torch.aminmax(log_scales.detach())
        if torch.isnan(hi) or hi == float("inf"):
            raise InputError("contains NaN or +Inf (an infinite scale); −Inf (scale 0) is allowed",
                             field="log_scales")
    if torch.isnan(opacity_logits).any():
        raise InputError("contains NaN", field="opacity_logits")
    if N and (rotations.detach().norm(dim=-1) <= 1e-12).any():
        raise InputError("contains a zero-length quaternion; the rotation is undefined", field="rotations")


def _all_finite(t: torch.Tensor) -> bool:
    """One pass, no temporaries: min and max propagate NaN, and are finite iff every entry is."""
    if t.numel() == 0:
        return True
    lo, hi = torch.aminmax(t.detach())
    return bool(torch.isfinite(lo) & torch.isfinite(hi))


def _shape(t) -> str:
    return str(tuple(t.shape)) if isinstance(t, torch.Tensor) else type(t).__name__


def _as_background(value, channels: int, name: str, dtype, device) -> torch.Tensor:
    bg = torch.as_tensor(value, dtype=dtype, device=device).reshape(-1)
    if bg.numel() == 1 and channels != 1:
        bg = bg.expand(channels)
    if bg.shape[0] != channels:
        raise InputError(f"has {bg.shape[0]} channels, expected {channels}", field=name)
    if not torch.isfinite(bg).all():
        raise InputError("contains NaN or Inf", field=name)
    return bg


def _backgrounds(background, feature_background, outputs, colors, features, dtype, device):
    bg_rgb = bg_feat = None
    if "rgb" in outputs:
        bg_rgb = (_as_background(background, 3, "background", dtype, device) if background is not None
                  else torch.zeros(3, dtype=dtype, device=device))
    if "features" in outputs:
        C = features.shape[1]
        if feature_background is not None:
            bg_feat = _as_background(feature_background, C, "feature_background", dtype, device)
        elif background is not None and "rgb" not in outputs:
            bg_feat = _as_background(background, C, "background", dtype, device)
        else:
            bg_feat = torch.zeros(C, dtype=dtype, device=device)
    return bg_rgb, bg_feat
