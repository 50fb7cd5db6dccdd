"""Crop pyramid geometry and the per-pixel interpolation of crop features (paper §3.1, eq. 1-2).

For each scale ``r`` the crop side is ``k = floor(r * H)`` pixels, crops are laid on a sliding window
with stride ``s = floor(k / 2)`` (the paper's; ``stride_fraction`` f gives ``s = floor(f * k)``) over the
image zero-padded by ``p = k // 2`` on every side. Crop
``(iy, ix)`` covers pixel rows ``iy*s - p .. iy*s - p + k - 1`` (columns likewise), so its centre sits
at pixel-index coordinate ``c0 + s*i`` with ``c0 = (k - 1)/2 - p``. At 640x360 with ratios
0.15..0.6 in 5 steps this gives 336 + 112 + 60 + 40 + 24 = 572 crops per camera.

A pixel's feature at one scale is the bilinear interpolation of the features of the 4 crops whose
centres surround it (clamped to the outermost crops at the border); the pixel feature is the mean over
scales, not re-normalized. Coordinates here are pixel *indices* (pixel ``x`` has its centre at ``x``).

Crop order inside one camera's feature array: scale by scale, each scale row-major ``(iy, ix)``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import InputError
from .plans import PAPER_CROP_STRIDE as DEFAULT_STRIDE_FRACTION

DEFAULT_RATIOS = (0.15, 0.6)
DEFAULT_STEPS = 5
TUBE_OFFSETS = tuple(range(-4, 4))  # t-4 .. t+3: 8 frames, as ViCLIP expects
CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)


#: the most pyramid scales (the paper uses 5); more only repeats nearly equal crop sizes
MAX_PYRAMID_STEPS = 32


def pyramid_ratios(low: float = DEFAULT_RATIOS[0], high: float = DEFAULT_RATIOS[1],
                   steps: int = DEFAULT_STEPS) -> tuple[float, ...]:
    """``steps`` crop ratios evenly spaced from ``low`` to ``high`` (fractions of the image height)."""
    if not 1 <= steps <= MAX_PYRAMID_STEPS or not (0 < low <= high <= 1.0):
        raise InputError(f"need 0 < low <= high <= 1 and 1 <= steps <= {MAX_PYRAMID_STEPS}, got {low}, {high}, "
                         f"{steps}", field="ratios")
    return tuple(float(r) for r in np.linspace(low, high, steps))


@dataclass(frozen=True)
class ScaleGrid:
    """The sliding-window crops of one scale on one image size.

    Attributes:
        ratio: crop side as a fraction of the image height.
        kernel: crop side in pixels.
        stride: distance between neighbouring crop centres in pixels.
        padding: zero padding on every side of the image.
        nx, ny: number of crops along x and y.
        offset: index of this scale's first crop in the camera's crop list.
    """

    ratio: float
    kernel: int
    stride: int
    padding: int
    nx: int
    ny: int
    offset: int

    @property
    def num_crops(self) -> int:
        return self.nx * self.ny

    @property
    def first_center(self) -> float:
        return (self.kernel - 1) / 2.0 - self.padding

    def centers_x(self) -> np.ndarray:
        """(nx,) crop centre x coordinates (pixel indices)."""
        return self.first_center + self.stride * np.arange(self.nx, dtype=np.float64)

    def centers_y(self) -> np.ndarray:
        """(ny,) crop centre y coordinates (pixel indices)."""
        return self.first_center + self.stride * np.arange(self.ny, dtype=np.float64)


@dataclass(frozen=True)
class PyramidLayout:
    """All crops of one camera image: ``scales`` in order, ``num_crops`` in total."""

    width: int
    height: int
    scales: tuple[ScaleGrid, ...]

    @property
    def num_crops(self) -> int:
        return sum(s.num_crops for s in self.scales)

    def to_dict(self) -> dict:
        return {"width": self.width, "height": self.height,
                "scales": [{"ratio": s.ratio, "kernel": s.kernel, "stride": s.stride, "padding": s.padding,
                            "nx": s.nx, "ny": s.ny} for s in self.scales]}


def crop_layout(width: int, height: int, ratios: Sequence[float],
                stride_fraction: float = DEFAULT_STRIDE_FRACTION) -> PyramidLayout:
    """The crop pyramid of a ``width`` x ``height`` image for the given ratios; neighbouring crops of a
    scale are ``floor(stride_fraction * k)`` pixels apart (0.5: the paper's half-crop overlap)."""
    if width < 1 or height < 1:
        raise InputError(f"image size must be positive, got {width}x{height}", field="image size")
    if not 0 < stride_fraction <= 1:
        raise InputError(f"must be in (0, 1], got {stride_fraction}", field="crop stride")
    scales = []
    offset = 0
    for r in ratios:
        kernel = int(math.floor(r * height + 1e-9))
        if kernel < 2:
            raise InputError(f"crop ratio {r} gives a crop of {kernel} px on a {height} px high image",
                             field="ratios")
        stride = max(1, int(math.floor(stride_fraction * kernel + 1e-9)))
        padding = kernel // 2
        nx = (width + 2 * padding - kernel) // stride + 1
        ny = (height + 2 * padding - kernel) // stride + 1
        scales.append(ScaleGrid(float(r), kernel, stride, padding, nx, ny, offset))
        offset += nx * ny
    return PyramidLayout(int(width), int(height), tuple(scales))


# ---------------------------------------------------------------------------------------- crops
def tube_indices(t: int, num_timesteps: int, offsets: Sequence[int] = TUBE_OFFSETS) -> list[int]:
    """Frame indices of the temporal tube around ``t``; edges repeat the first/last frame."""
    return [min(max(t + o, 0), num_timesteps - 1) for o in offsets]


def scale_crops(tube: torch.Tensor, grid: ScaleGrid) -> torch.Tensor:
    """Cut one scale's crops out of a frame tube.

    Args:
        tube: (L,C,H,W) frames (zero padding is applied here, in the frames' own value space).
        grid: the scale.
    Returns:
        (n, L, C, k, k) crops, ``n = grid.num_crops`` in row-major (iy, ix) order.
    """
    L, C, H, W = tube.shape
    k, s, p = grid.kernel, grid.stride, grid.padding
    padded = F.pad(tube, (p, p, p, p))
    cols = F.unfold(padded, kernel_size=k, stride=s)  # (L, C*k*k, n)
    n = cols.shape[-1]
    if n != grid.num_crops:
        raise AssertionError(f"unfold produced {n} crops, layout says {grid.num_crops}")
    return cols.view(L, C, k, k, n).permute(4, 0, 1, 2, 3)


def resize_crops(crops: torch.Tensor, size: int | None, *, clip_normalize: bool) -> torch.Tensor:
    """(n,L,C,k,k) -> (n,L,C,size,size), antialiased bilinear; CLIP mean/std for RGB encoders."""
    n, L, C, k, _ = crops.shape
    x = crops.reshape(n * L, C, k, k)
    if size is not None and size != k:
        x = F.interpolate(x, size=(size, size), mode="bilinear", align_corners=False, antialias=size < k)
    if clip_normalize:
        if C != 3:
            raise InputError(f"CLIP normalization needs 3 channels, got {C}", field="frames")
        mean = x.new_tensor(CLIP_MEAN).view(1, 3, 1, 1)
        std = x.new_tensor(CLIP_STD).view(1, 3, 1, 1)
        x = (x - mean) / std
    return x.view(n, L, C, x.shape[-2], x.shape[-1])


# ------------------------------------------------------------------------------ interpolation
def lerp_coefficients(centers_first: float, step: float, count: int,
                      queries: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Two-tap linear interpolation on a regular 1-D grid, clamped at both ends.

    Args:
        centers_first, step, count: grid positions ``centers_first + step * i``, i < count.
        queries: (m,) query coordinates (float64 or float32).
    Returns:
        lower index (m,) int64 in [0, count-2] (0 if count == 1), weight of the upper neighbour (m,) in [0,1].
    """
    if count == 1:
        return (torch.zeros(queries.shape, dtype=torch.long, device=queries.device),
                torch.zeros_like(queries))
    u = (queries - centers_first) / step
    i0 = torch.clamp(torch.floor(u), 0, count - 2).long()
    w = torch.clamp(u - i0.to(u.dtype), 0.0, 1.0)
    return i0, w


def lerp_matrix(centers_first: float, step: float, count: int, queries: torch.Tensor,
                dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """The interpolation of :func:`lerp_coefficients` as a dense (m, count) matrix (two taps per row).

    Interpolating along an axis is then one matrix product, which BLAS runs far faster than
    gathering both neighbours of every query (the grids here have at most a few dozen nodes).
    """
    i0, w = lerp_coefficients(centers_first, step, count, queries)
    m = queries.shape[0]
    mat = torch.zeros(m, count, dtype=torch.float64, device=queries.device)
    rows = torch.arange(m, device=queries.device)
    mat.index_put_((rows, i0), 1.0 - w, accumulate=True)
    mat.index_put_((rows, torch.clamp(i0 + 1, max=count - 1)), w, accumulate=True)
    return mat.to(dtype)


def interpolate_grid(layout: PyramidLayout, crop_features: torch.Tensor, xs: torch.Tensor,
                     ys: torch.Tensor) -> torch.Tensor:
    """Per-pixel features on a rectilinear grid of pixel positions.

    Args:
        layout: the camera's crop pyramid.
        crop_features: (num_crops, D) features of that camera's crops.
        xs: (m_x,) pixel x coordinates (pixel indices, may be fractional); ys: (m_y,).
    Returns:
        (m_y, m_x, D): mean over scales of the bilinearly interpolated crop features.
    """
    _check_features(layout, crop_features)
    dtype, D = crop_features.dtype, crop_features.shape[1]
    along_x, row_weights = [], []
    for g in layout.scales:
        feats = crop_features[g.offset:g.offset + g.num_crops].view(g.ny, g.nx, D)
        wx = lerp_matrix(g.first_center, g.stride, g.nx, xs.to(torch.float64), dtype)       # (m_x, nx)
        along_x.append(torch.matmul(wx, feats))                                              # (ny, m_x, D)
        row_weights.append(lerp_matrix(g.first_center, g.stride, g.ny, ys.to(torch.float64), dtype))
    # every scale's y-interpolation and the mean over scales in one product: (m_y, Σny) @ (Σny, m_x·D)
    rows = torch.cat(row_weights, dim=1) / len(layout.scales)
    stacked = torch.cat(along_x, dim=0)
    return torch.matmul(rows, stacked.view(stacked.shape[0], -1)).view(ys.shape[0], xs.shape[0], D)


def interpolate_points(layout: PyramidLayout, crop_features: torch.Tensor, xs: torch.Tensor,
                       ys: torch.Tensor) -> torch.Tensor:
    """Per-pixel features at scattered pixel positions: (m,), (m,) -> (m, D)."""
    _check_features(layout, crop_features)
    out = None
    for g in layout.scales:
        base = g.offset
        iy, wy = lerp_coefficients(g.first_center, g.stride, g.ny, ys.to(torch.float64))
        ix, wx = lerp_coefficients(g.first_center, g.stride, g.nx, xs.to(torch.float64))
        iy1 = torch.clamp(iy + 1, max=g.ny - 1)
        ix1 = torch.clamp(ix + 1, max=g.nx - 1)
        f = crop_features
        wy = wy.to(f.dtype)[:, None]
        wx = wx.to(f.dtype)[:, None]
        top = f[base + iy * g.nx + ix] * (1 - wx) + f[base + iy * g.nx + ix1] * wx
        bot = f[base + iy1 * g.nx + ix] * (1 - wx) + f[base + iy1 * g.nx + ix1] * wx
        val = top * (1 - wy) + bot * wy
        out = val if out is None else out + val
    return out / len(layout.scales)


def pixel_features(layout: PyramidLayout, crop_features: torch.Tensor, stride: int = 1) -> torch.Tensor:
    """Per-pixel features of the whole image (``stride`` 1) or of every ``stride``-th pixel.

    With ``stride > 1`` the sample positions are the centres of ``stride`` x ``stride`` blocks
    (``x = stride*j + (stride-1)/2``), which :func:`upsample_to_pixels` maps back to full resolution.

    Returns:
        (ceil(H/stride), ceil(W/stride), D).
    """
    xs, ys = sample_positions(layout.width, stride), sample_positions(layout.height, stride)
    return interpolate_grid(layout, crop_features, xs, ys)


def sample_positions(size: int, stride: int) -> torch.Tensor:
    """(ceil(size/stride),) float64 block-centre pixel coordinates."""
    n = -(-size // stride)
    return torch.arange(n, dtype=torch.float64) * stride + (stride - 1) / 2.0


def upsample_to_pixels(values: torch.Tensor, width: int, height: int, stride: int) -> torch.Tensor:
    """Bilinearly upsample (h, w, C) values sampled by :func:`pixel_features` to (height, width, C)."""
    if stride == 1:
        return values
    h, w, C = values.shape
    first = (stride - 1) / 2.0
    wy = lerp_matrix(first, stride, h, torch.arange(height, dtype=torch.float64), values.dtype)   # (H, h)
    wx = lerp_matrix(first, stride, w, torch.arange(width, dtype=torch.float64), values.dtype)    # (W, w)
    along_x = torch.matmul(wx, values)                                                            # (h, W, C)
    return torch.matmul(wy, along_x.view(h, -1)).view(height, width, C)


def _check_features(layout: PyramidLayout, crop_features: torch.Tensor) -> None:
    if crop_features.dim() != 2 or crop_features.shape[0] != layout.num_crops:
        raise InputError(f"crop features have shape {tuple(crop_features.shape)}, expected "
                         f"({layout.num_crops}, D) for a {layout.width}x{layout.height} pyramid",
                         field="crop features")
