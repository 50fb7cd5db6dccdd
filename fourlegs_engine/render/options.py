"""Options and small result types of the rasterizer.

Conventions (3DGS / EWA splatting, see docs/CONTRACTS.md "render"): pixel centres at (x+0.5, y+0.5);
α = min(alpha_max, o·exp(−½ dᵀ Σ₂D⁻¹ d)); fragments with α < alpha_min are skipped; blending stops
before the transmittance would fall below ``transmittance_min`` (the crossing Gaussian is not blended).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch

from ..errors import InputError

#: every output name ``rasterize`` understands
OUTPUT_NAMES = ("rgb", "features", "depth", "depth_median", "alpha", "weights")
#: how far a Gaussian's footprint reaches
EXTENTS = ("opacity", "3sigma")
#: generations of the fused CPU kernels
KERNELS = ("v1", "v2")


@dataclass(frozen=True)
class RasterOptions:
    """Knobs of the rasterizer. The defaults reproduce the 3DGS conventions exactly.

    Attributes:
        tile_size: side of the square pixel tiles Gaussians are binned into (speed only: every tile
            size gives the same image up to float rounding), or ``"auto"``: chosen per view from the
            projected footprints (:func:`~fourlegs_engine.render.binning.choose_tile_size`), small
            tiles for small splats, larger ones where large overlapping splats would make the
            tile–Gaussian pairs explode.
        extent: ``"opacity"`` (default): the footprint is the ellipse where o·G ≥ alpha_min, i.e.
            dᵀΣ⁻¹d ≤ 2 ln(o/alpha_min) (= sqrt(2 ln(255 o)) σ), bounded by its axis-aligned box; no pixel
            that would blend is dropped. ``"3sigma"``: a square of half-side 3·sqrt(λ_max) (the
            classic 3DGS bound; drops the faint tails of opaque Gaussians, faster for them).
        eps2d: low-pass added to the 2D covariance diagonal, px².
        alpha_min: fragments with smaller α are skipped (1/255).
        alpha_max: α is capped here (0.99), so transmittance never reaches 0 in one step.
        transmittance_min: blending stops before T would fall below this (1e-4).
        fov_clamp: the projection Jacobian is evaluated at x/z, y/z clamped to ``fov_clamp`` times the
            half field of view (1.3): the EWA approximation stays bounded far outside the frustum.
        batch_elements: the rasterizer works on batches of tiles holding about this many
            (pixel × Gaussian) pairs; it bounds the working memory (≈ 40 bytes per element).
        chunk: each tile's list is blended ``chunk`` Gaussians at a time, front to back; tiles whose
            pixels are all saturated (T < transmittance_min) stop early.
        validate: check inputs for NaN/Inf and shapes (one pass over the data; turn off in tight loops
            whose inputs are known to be good).
        cpu_kernel: on the CPU, when numba is installed, render (rgb, features, depth, alpha) and
            :func:`~fourlegs_engine.render.splat` through the fused kernels chosen by ``kernel``;
            ``False`` forces the batched torch path (the reference the kernels are tested against; it
            also serves "depth_median" and "weights").
        kernel: which fused CPU kernels ``cpu_kernel`` uses. ``"v2"`` (default): the fused projection,
            per-tile lists built from the exact footprint ellipses and the SIMD lane kernels of
            :mod:`.blend_kernels`, forward and backward (gradients included, except for float16/bfloat16
            features that need a gradient, which the torch path widens chunk by chunk). ``"v1"``: the
            previous generation — torch projection and binning, the per-tile kernels of
            :mod:`.cpu_kernels` for passes without gradients, the torch path for gradients (kept for
            side-by-side benchmarks).
    """

    tile_size: int | str = "auto"
    extent: str = "opacity"
    eps2d: float = 0.3
    alpha_min: float = 1.0 / 255.0
    alpha_max: float = 0.99
    transmittance_min: float = 1e-4
    fov_clamp: float = 1.3
    batch_elements: int = 1 << 21
    chunk: int = 32
    validate: bool = True
    cpu_kernel: bool = True
    kernel: str = "v2"

    def check(self) -> "RasterOptions":
        if self.tile_size != "auto" and not (isinstance(self.tile_size, int) and not isinstance(self.tile_size, bool)
                                             and 1 <= self.tile_size <= 256):
            raise InputError(f"must be \"auto\" or an integer in 1..256, got {self.tile_size!r}",
                             field="options.tile_size")
        if self.extent not in EXTENTS:
            raise InputError(f"must be one of {EXTENTS}, got {self.extent!r}", field="options.extent")
        if not self.eps2d >= 0:
            raise InputError(f"must be >= 0, got {self.eps2d}", field="options.eps2d")
        if not 0 < self.alpha_min < self.alpha_max < 1:
            raise InputError(f"need 0 < alpha_min < alpha_max < 1, got {self.alpha_min}, {self.alpha_max}",
                             field="options.alpha_min/alpha_max")
        if not 0 < self.transmittance_min < 1:
            raise InputError(f"must be in (0, 1), got {self.transmittance_min}", field="options.transmittance_min")
        if not self.fov_clamp > 0:
            raise InputError(f"must be > 0, got {self.fov_clamp}", field="options.fov_clamp")
        if self.kernel not in KERNELS:
            raise InputError(f"must be one of {KERNELS}, got {self.kernel!r}", field="options.kernel")
        if not (isinstance(self.chunk, int) and self.chunk >= 1):
            raise InputError(f"must be a positive integer, got {self.chunk!r}", field="options.chunk")
        if not self.batch_elements >= 1024:
            raise InputError(f"must be >= 1024, got {self.batch_elements}", field="options.batch_elements")
        return self


class BlendWeights(NamedTuple):
    """Per-fragment blending weights of one rendered view (the ``"weights"`` output).

    Row m says Gaussian ``gaussian[m]`` contributed ``weight[m]`` = α·T to pixel ``pixel[m]``; a pixel's
    colour is Σ weight·colour + (1 − Σ weight)·background. Rows are sorted by pixel, front to back
    within a pixel. Weights are detached (no autograd).

    Attributes:
        pixel: (M,) int64 flat pixel index y·W + x.
        gaussian: (M,) int64 index into the Gaussians passed to ``rasterize``.
        weight: (M,) α·T, in the working dtype.
        width, height: image size (so ``pixel`` can be unflattened).
    """

    pixel: torch.Tensor
    gaussian: torch.Tensor
    weight: torch.Tensor
    width: int
    height: int
