"""What a fit optimizes: the training frames of a timestep as tensors, the Gaussian model, its first
cloud (:mod:`.init`) and its render (rgb, segmentation colours, alpha) through the engine's rasterizer."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..errors import InputError
from ..render import rasterize
from ..render.options import RasterOptions
from ..scene.camera import Camera
from .clean_plate import CleanPlates
from .dataset import Capture
from .init import background_proxy, initial_cloud
from .options import FitOptions

SEG_FG = (1.0, 0.0, 0.0)
SEG_BG = (0.0, 0.0, 1.0)


class TrainingFrames:
    """The training images (and masks) of one timestep at the fit resolution, as tensors."""

    def __init__(self, capture: Capture, t: int, cams: list[int], size: tuple[int, int], device):
        self.images = [torch.from_numpy(capture.load_image("train", t, c, size)).to(device) for c in cams]
        self.masks = None
        if capture.has_masks:
            seg = []
            for c in cams:
                m = torch.from_numpy(capture.load_mask("train", t, c, size)).to(device)[..., None]
                seg.append(torch.cat([m, torch.zeros_like(m), 1.0 - m], dim=-1))
            self.masks = seg
        self.plates: list[torch.Tensor] | None = None
        self.plate_known: list[torch.Tensor] | None = None

    def add_clean_plates(self, plates: CleanPlates, device) -> None:
        self.plates = [torch.from_numpy(p).to(device) for p in plates.images]
        self.plate_known = [torch.from_numpy(k).to(device)[..., None].to(torch.float32) for k in plates.known]


@dataclass
class GaussianModel:
    """All parameters. Static: log_scales (N,3), opacity_logits (N,), colors (N,3), foreground (N,),
    cam_m/cam_c (C,3). Per timestep: means (N,3), rotations (N,4) unit."""

    means: torch.Tensor
    rotations: torch.Tensor
    log_scales: torch.Tensor
    opacity_logits: torch.Tensor
    colors: torch.Tensor
    foreground: torch.Tensor
    cam_m: torch.Tensor
    cam_c: torch.Tensor

    def seg_colors(self) -> torch.Tensor:
        fg = self.foreground[:, None].to(self.means.dtype)
        return fg * self.means.new_tensor(SEG_FG) + (1 - fg) * self.means.new_tensor(SEG_BG)


def raster_options() -> RasterOptions:
    """Auto tile size; inputs are the fit's own, so the per-call validation is skipped."""
    return RasterOptions(tile_size="auto", validate=False)


def render_views(model: GaussianModel, camera: Camera, *, with_seg: bool = True, means=None, rotations=None,
                 colors=None, subset: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Render rgb (and seg colours, alpha) of ``model`` (or of its ``subset`` of Gaussians, with
    overriding ``means``/``rotations``/``colors`` for that subset) without colour correction, black background."""
    idx = subset
    pick = (lambda t: t) if idx is None else (lambda t: t.index_select(0, idx))
    m = pick(model.means) if means is None else means
    r = pick(model.rotations) if rotations is None else rotations
    outputs = ("rgb", "features", "alpha") if with_seg else ("rgb", "alpha")
    seg = pick(model.seg_colors()) if with_seg else None
    col = pick(model.colors) if colors is None else colors
    return rasterize(m, r, pick(model.log_scales), pick(model.opacity_logits), camera, colors=col,
                     features=seg, outputs=outputs, options=raster_options())


def correct_colours(rgb: torch.Tensor, model: GaussianModel, c: int) -> torch.Tensor:
    """Camera ``c``'s colour correction of a render: exp(cam_m)·rgb + cam_c."""
    return torch.exp(model.cam_m[c]) * rgb + model.cam_c[c]


def average_camera_colours(colors: np.ndarray, cam_m: np.ndarray, cam_c: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The Gaussian colours as the average training camera sees them, and the corrections re-expressed.

    A fit learns colours and, per training camera, a correction exp(m_c)·render + c_c; how a gain splits
    between the two is free. A camera the fit never saw (a test view, a shot's virtual camera) renders the
    colours as they are, so they should be the average training camera's: with ḡ = exp(mean_c m_c) and
    c̄ = mean_c c_c,

        colours' = clip(ḡ·colours + c̄, 0, 1),   m'_c = m_c − ln ḡ,   c'_c = c_c − exp(m'_c)·c̄,

    which leaves every training camera's corrected render unchanged wherever the pixel's accumulated
    opacity is 1 (everywhere a capture's background is fitted) and the colours stay within [0, 1].

    Args:
        colors: (N, 3) or per timestep (T, N, 3) in [0, 1]. cam_m, cam_c: (C, 3) log-gains and offsets of
            the training cameras.
    Returns:
        (colours', m', c') as float32 arrays of the same shapes (unchanged when C = 0).
    """
    colors = np.asarray(colors)
    cam_m = np.asarray(cam_m, np.float64)
    cam_c = np.asarray(cam_c, np.float64)
    if cam_m.shape[0] == 0:
        return colors.astype(np.float32), cam_m.astype(np.float32), cam_c.astype(np.float32)
    log_gain = cam_m.mean(0)
    offset = cam_c.mean(0)
    new_m = cam_m - log_gain
    new_colors = np.empty(colors.shape, np.float32)
    # one timestep at a time: a (T,N,3) sequence in float64 at once would be several GB
    for src, dst in zip(colors.reshape(-1, *colors.shape[-2:]), new_colors.reshape(-1, *colors.shape[-2:])):
        dst[:] = np.clip(np.exp(log_gain) * src.astype(np.float64) + offset, 0.0, 1.0)
    new_c = cam_c - np.exp(new_m) * offset
    return new_colors, new_m.astype(np.float32), new_c.astype(np.float32)


def to_numpy(t: torch.Tensor) -> np.ndarray:
    """A tensor as a numpy array (floats as float32), for the work directory."""
    a = t.detach().cpu().numpy()
    return a.astype(np.float32) if a.dtype.kind == "f" else a


def model_from_arrays(means: np.ndarray, rotations: np.ndarray, s: dict[str, np.ndarray], device) -> GaussianModel:
    """The model of a timestep from the work directory: its centres and rotations, the static arrays ``s``."""
    tt = lambda a: torch.from_numpy(np.ascontiguousarray(a)).to(device)  # noqa: E731
    return GaussianModel(tt(means), tt(rotations), tt(s["log_scales"]), tt(s["opacity_logits"]), tt(s["colors"]),
                  tt(s["foreground"].astype(bool)), tt(s["cam_m"]), tt(s["cam_c"]))


def initial_model(frames: TrainingFrames, cameras: list[Camera], opts: FitOptions, device) -> tuple[GaussianModel, float | None]:
    """The first timestep's model from the initial cloud (``opts.init``), and the floor height found (or None)."""
    images = [im.cpu().numpy() for im in frames.images]
    masks = [m[..., 0].cpu().numpy() for m in frames.masks] if frames.masks is not None else None
    cloud = initial_cloud(cameras, images, masks, voxel=opts.voxel, bg_stride=opts.background_stride,
                          max_foreground=opts.init_foreground, max_background=opts.init_background, seed=opts.seed,
                          method=opts.init)
    if frames.plates is not None and masks is not None:
        _add_hidden_background(cloud, cameras, frames, masks, opts)
    N = cloud.points.shape[0]
    if N == 0:
        raise InputError("the initialisation produced no points (empty masks and images?)", field="dataset")
    f32 = torch.float32
    rot = torch.zeros(N, 4, dtype=f32)
    rot[:, 0] = 1.0
    model = GaussianModel(
        means=torch.as_tensor(cloud.points, dtype=f32, device=device),
        rotations=rot.to(device),
        log_scales=torch.as_tensor(np.log(np.maximum(cloud.scales, 1e-6)), dtype=f32, device=device)[:, None].repeat(1, 3).contiguous(),
        opacity_logits=torch.full((N,), 2.0, dtype=f32, device=device),
        colors=torch.as_tensor(cloud.colors, dtype=f32, device=device),
        foreground=torch.as_tensor(cloud.foreground, device=device),
        cam_m=torch.zeros(len(cameras), 3, dtype=f32, device=device),
        cam_c=torch.zeros(len(cameras), 3, dtype=f32, device=device))
    return model, cloud.floor_y


def _add_hidden_background(cloud, cameras: list[Camera], frames: TrainingFrames, masks: list[np.ndarray],
                           opts: FitOptions) -> None:
    """Append background points, coloured by the clean plates, for the pixels the first timestep's masks
    hide but the plates know (cast onto the same dome/floor proxy as the other background points; not
    counted against ``init_background``)."""
    hidden = [np.where((m >= 0.5) & k[..., 0].cpu().numpy().astype(bool), 0.0, 1.0)
              for m, k in zip(masks, frames.plate_known)]
    plates = [p.cpu().numpy() for p in frames.plates]
    pts, col, scl = background_proxy(cameras, plates, hidden, stride=opts.background_stride,
                                     dome_center=cloud.dome_center, dome_radius=cloud.dome_radius,
                                     floor_y=cloud.floor_y)
    cloud.points = np.concatenate([cloud.points, pts])
    cloud.colors = np.concatenate([cloud.colors, col]).astype(np.float32)
    cloud.scales = np.concatenate([cloud.scales, scl])
    cloud.foreground = np.concatenate([cloud.foreground, np.zeros(len(pts), bool)])
