"""Fit dynamic 3D Gaussians to a calibrated multiview video (the method of Dynamic 3D Gaussians,
Luiten et al., 3DV 2024), resumable per timestep.

Per timestep, in order:

* first timestep: a static 3DGS fit of every parameter (centres, rotations, scales, opacities, colours,
  per-camera colour correction) with densification (clone small / split large Gaussians whose
  screen-space gradient is high, prune transparent and huge ones). Loss: image 0.8·L1 + 0.2·D-SSIM on
  the colour-corrected render (``exp(cam_m)·img + cam_c``) plus the same on the rendered segmentation
  colours (foreground red, background blue) against the masks; optionally (``clean_plate_samples``) an
  L1 term on the background Gaussians rendered alone against each camera's clean plate
  (:mod:`.clean_plate`: the median of its background pixels over timesteps spread across the fitted
  range), whose pixels also seed background points where the people hide it at the first timestep.
* later timesteps: start from a constant-velocity forecast of centres and rotations; optimize only the
  foreground centres and rotations (colours, opacities, scales, colour correction fixed) under the
  image and segmentation losses plus local rigidity, rotation similarity and long-term isometry over
  the 20 nearest foreground neighbours of the first timestep, and a floor term. Background Gaussians
  are held exactly still (the limit of the paper's heavily weighted background term), which makes
  the background's contribution a fixed image per camera: each view blends the foreground alone over
  that image (exact while the foreground is in front of the background along every ray).

Finished timesteps are written to a work directory beside the output (``.NAME.fit/``); a killed fit
resumes from there and produces the identical bundle (every random choice is seeded per timestep).
"""
from __future__ import annotations

import hashlib
import json
import math
import shutil
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from ..errors import ConfigMismatchError, InputError, OutputExistsError
from ..fileio import atomic_path, read_json, write_json_atomic
from ..render import rasterize
from ..render.options import RasterOptions
from ..scene.camera import Camera, CameraRig
from ..scene.gaussians import GaussianSequence, quaternion_to_matrix
from ..scene.scene import Scene
from .dataset import Capture
from .clean_plate import CleanPlates, clean_plates, sample_timesteps
from .init import INIT_METHODS, background_proxy, initial_cloud
from .losses import Priors, image_loss, psnr

WORK_VERSION = 1
SEG_FG = (1.0, 0.0, 0.0)
SEG_BG = (0.0, 0.0, 1.0)


@dataclass(frozen=True)
class FitOptions:
    """Knobs of :func:`fit_capture` (defaults: 2 CPU cores at 320×180).

    Attributes:
        resolution_scale: images and intrinsics are scaled by this (0.5: 640×360 → 320×180).
        timesteps: (a, b) half-open range of timesteps to fit (None: all).
        cameras: training camera ids to use (None: every training camera).
        first_iterations: optimization steps of the first (static) timestep (the paper's code: 10,000).
        iterations: steps of every later timestep (the paper's code: 2,000).
        max_gaussians: densification never grows the model past this.
        init: how the initial Gaussians are made: "hull" (visual hull + background proxy), "features"
            (triangulated feature matches, needs OpenCV) or "hull+features" (:mod:`.init`).
        init_foreground, init_background: caps on the initial foreground / background points.
        voxel: visual-hull voxel side (m). background_stride: pixel stride of the background proxy samples.
        densify: clone/split/prune during the first timestep.
        clean_plate_samples: timesteps (spread over the fitted range) whose background pixels make each
            training camera's clean plate, the target of the background-only render at the first
            timestep and the source of background points hidden by the people there (0: neither; off by
            default: no gain measured on the Panoptic capture, docs/benchmarks_fit.md).
        grad_threshold: densify Gaussians whose mean screen-space gradient (NDC units, as in 3DGS)
            exceeds this.
        knn: neighbours per foreground Gaussian for the priors.
        knn_lambda: neighbour weight exp(−λ d²) (d in metres).
        weights: loss weights (im, seg, rigid, rot, iso, floor, plate).
        lr_means: centre learning rate as a fraction of the scene radius (first timestep).
        lr_means_later: the same for later timesteps (fewer steps than the paper, so larger).
        lr_colors, lr_rotations, lr_opacities, lr_scales, lr_camera: Adam learning rates.
        seed: every random choice derives from it.
        device: "auto" (CUDA when available), "cpu" or "cuda".
    """

    resolution_scale: float = 0.5
    timesteps: tuple[int, int] | None = None
    cameras: tuple[str, ...] | None = None
    first_iterations: int = 150
    iterations: int = 30
    max_gaussians: int = 60_000
    init: str = "hull"
    init_foreground: int = 30_000
    init_background: int = 30_000
    voxel: float = 0.02
    background_stride: int = 6
    densify: bool = True
    clean_plate_samples: int = 0
    grad_threshold: float = 0.0002
    knn: int = 20
    knn_lambda: float = 2000.0
    weights: dict[str, float] = field(default_factory=lambda: {
        "im": 1.0, "seg": 3.0, "rigid": 4.0, "rot": 4.0, "iso": 2.0, "floor": 2.0, "plate": 1.0})
    lr_means: float = 0.00016
    lr_means_later: float = 0.0016
    lr_colors: float = 0.01
    lr_rotations: float = 0.001
    lr_rotations_later: float = 0.004
    lr_opacities: float = 0.05
    lr_scales: float = 0.005
    lr_camera: float = 0.001
    seed: int = 0
    device: str = "auto"

    def check(self) -> "FitOptions":
        if not 0 < self.resolution_scale <= 4:
            raise InputError(f"must be in (0, 4], got {self.resolution_scale}", field="resolution_scale")
        if int(self.clean_plate_samples) < 0:
            raise InputError(f"must be 0 or more, got {self.clean_plate_samples}", field="clean_plate_samples")
        for name in ("first_iterations", "iterations", "max_gaussians", "init_foreground", "init_background",
                     "knn", "background_stride"):
            if int(getattr(self, name)) < (0 if name.endswith("iterations") else 1):
                raise InputError(f"must be a positive integer, got {getattr(self, name)}", field=name)
        if self.init not in INIT_METHODS:
            raise InputError(f"must be one of {', '.join(INIT_METHODS)}, got {self.init!r}", field="init")
        if self.init != "hull":
            from .features import require_cv2

            require_cv2()
        if self.device not in ("auto", "cpu", "cuda"):
            raise InputError(f"must be auto, cpu or cuda, got {self.device!r}", field="device")
        if self.device == "cuda" and not torch.cuda.is_available():
            raise InputError("CUDA was requested but no CUDA device is available", field="device")
        return self

    def fingerprint(self) -> dict[str, Any]:
        """Everything that changes the result (the device is left out: CPU and CUDA differ anyway)."""
        d = asdict(self)
        d.pop("device")
        # knobs at their "off" value are left out, so fits started before these knobs existed still resume
        if d["init"] == "hull":
            d.pop("init")
        if d["clean_plate_samples"] == 0:
            d.pop("clean_plate_samples")
            d["weights"] = {k: v for k, v in d["weights"].items() if k != "plate"}
        d["timesteps"] = list(d["timesteps"]) if d["timesteps"] is not None else None
        d["cameras"] = list(d["cameras"]) if d["cameras"] is not None else None
        return d


@dataclass
class FitEvent:
    """What a progress callback receives: ``kind`` is "iteration" (one optimization step) or "timestep"
    (a timestep finished, or ``resumed`` from the work directory)."""

    kind: str
    timestep: int
    index: int = 0
    total: int = 0
    loss: float = float("nan")
    train_psnr: float = float("nan")
    resumed: bool = False


# ---------------------------------------------------------------------------------------------- state
class _Frames:
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
class _Model:
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


def _raster_options() -> RasterOptions:
    return RasterOptions(tile_size="auto", validate=False)


def render_views(model: _Model, camera: Camera, *, with_seg: bool = True, means=None, rotations=None,
                 subset: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Render rgb (and seg colours, alpha) of ``model`` (or of its ``subset`` of Gaussians, with
    overriding ``means``/``rotations`` for that subset) without colour correction, black background."""
    idx = subset
    pick = (lambda t: t) if idx is None else (lambda t: t.index_select(0, idx))
    m = pick(model.means) if means is None else means
    r = pick(model.rotations) if rotations is None else rotations
    outputs = ("rgb", "features", "alpha") if with_seg else ("rgb", "alpha")
    seg = pick(model.seg_colors()) if with_seg else None
    return rasterize(m, r, pick(model.log_scales), pick(model.opacity_logits), camera, colors=pick(model.colors),
                     features=seg, outputs=outputs, options=_raster_options())


def _correct(rgb: torch.Tensor, model: _Model, c: int) -> torch.Tensor:
    return torch.exp(model.cam_m[c]) * rgb + model.cam_c[c]


# ------------------------------------------------------------------------------------- first timestep
def _fit_first(model: _Model, frames: _Frames, cameras: list[Camera], opts: FitOptions, scene_radius: float,
               generator: torch.Generator, progress: Callable[[FitEvent], None], t: int) -> tuple[_Model, float]:
    w = opts.weights
    params = {"means": model.means, "rotations": model.rotations, "log_scales": model.log_scales,
              "opacity_logits": model.opacity_logits, "colors": model.colors}
    lrs = {"means": opts.lr_means * scene_radius, "rotations": opts.lr_rotations, "log_scales": opts.lr_scales,
           "opacity_logits": opts.lr_opacities, "colors": opts.lr_colors}
    for p in params.values():
        p.requires_grad_(True)
    cam_m = model.cam_m.requires_grad_(True)
    cam_c = model.cam_c.requires_grad_(True)

    def make_optimizer():
        groups = [{"params": [params[k]], "lr": lrs[k], "name": k} for k in params]
        groups += [{"params": [cam_m], "lr": opts.lr_camera}, {"params": [cam_c], "lr": opts.lr_camera}]
        return torch.optim.Adam(groups, lr=0.0, eps=1e-15)

    optimizer = make_optimizer()
    n_iter = opts.first_iterations
    dens_start, dens_stop = int(0.1 * n_iter), int(0.7 * n_iter)
    dens_every = max(10, n_iter // 12)
    grad_accum = torch.zeros(model.means.shape[0], dtype=torch.float64)
    grad_count = torch.zeros_like(grad_accum)
    order: list[int] = []
    last_loss, last_psnr = float("nan"), float("nan")
    for it in range(n_iter):
        if not order:
            order = torch.randperm(len(cameras), generator=generator).tolist()
        c = order.pop()
        cam = cameras[c]
        cur = _Model(params["means"], params["rotations"], params["log_scales"], params["opacity_logits"],
                     params["colors"], model.foreground, cam_m, cam_c)
        out = render_views(cur, cam, with_seg=frames.masks is not None)
        rgb = _correct(out["rgb"], cur, c)
        loss = w["im"] * image_loss(rgb, frames.images[c])
        if frames.masks is not None:
            loss = loss + w["seg"] * image_loss(out["features"], frames.masks[c])
        if frames.plates is not None and w.get("plate", 0.0) > 0:
            loss = loss + w["plate"] * _plate_loss(cur, cam, c, frames)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if opts.densify and it < dens_stop:
            _accumulate_screen_grad(params["means"], cam, grad_accum, grad_count)
        optimizer.step()
        with torch.no_grad():
            params["rotations"].data = torch.nn.functional.normalize(params["rotations"].data, dim=-1)
        last_loss = float(loss.detach())
        if it % 25 == 0 or it == n_iter - 1:
            last_psnr = psnr(rgb.detach(), frames.images[c])
        progress(FitEvent("iteration", t, it + 1, n_iter, last_loss, last_psnr))
        if opts.densify and dens_start <= it < dens_stop and (it + 1) % dens_every == 0:
            with torch.no_grad():
                params, fg = _densify(params, model.foreground, grad_accum / grad_count.clamp_min(1), scene_radius,
                                      opts, generator, prune_big=it >= 0.3 * n_iter)
            model.foreground = fg
            for p in params.values():
                p.requires_grad_(True)
            optimizer = make_optimizer()
            grad_accum = torch.zeros(params["means"].shape[0], dtype=torch.float64)
            grad_count = torch.zeros_like(grad_accum)
    with torch.no_grad():
        out_model = _Model(params["means"].detach(), torch.nn.functional.normalize(params["rotations"].detach(), dim=-1),
                           params["log_scales"].detach(), params["opacity_logits"].detach(),
                           params["colors"].detach().clamp(0, 1), model.foreground, cam_m.detach(), cam_c.detach())
    return out_model, last_psnr


def _plate_loss(model: _Model, cam: Camera, c: int, frames: _Frames) -> torch.Tensor:
    """Mean L1 between the colour-corrected render of the background Gaussians alone and camera ``c``'s
    clean plate, over the pixels the plate knows."""
    bg_idx = torch.nonzero(~model.foreground).squeeze(1)
    rgb = _correct(render_views(model, cam, with_seg=False, subset=bg_idx)["rgb"], model, c)
    known = frames.plate_known[c]
    return ((rgb - frames.plates[c]).abs() * known).sum() / (3 * known.sum()).clamp_min(1.0)


def _accumulate_screen_grad(means: torch.Tensor, cam: Camera, accum: torch.Tensor, count: torch.Tensor) -> None:
    """Add each visible Gaussian's screen-space position gradient (NDC units) to ``accum``.

    The rasterizer returns ∂L/∂(world centre); in camera coordinates ∂L/∂x_cam = R ∂L/∂x_world, and the
    pixel gradient is ∂L/∂u = ∂L/∂x_cam,xy · z / f (the direct path through the projection).
    """
    if means.grad is None:
        return
    with torch.no_grad():
        R = torch.as_tensor(cam.w2c[:3, :3], dtype=torch.float64, device=means.device)
        t = torch.as_tensor(cam.w2c[:3, 3], dtype=torch.float64, device=means.device)
        g_cam = means.grad.double() @ R.T
        z = (means.detach().double() @ R.T + t)[:, 2]
        g_px = torch.stack([g_cam[:, 0] * z / cam.fx, g_cam[:, 1] * z / cam.fy], -1)
        g_ndc = g_px * torch.tensor([0.5 * cam.width, 0.5 * cam.height], dtype=torch.float64, device=means.device)
        seen = (means.grad.abs().sum(-1) > 0) & (z > cam.near)
        accum += torch.where(seen, g_ndc.norm(dim=-1), torch.zeros_like(z)).cpu()
        count += seen.cpu().double()


def _densify(params: dict[str, torch.Tensor], foreground: torch.Tensor, grads: torch.Tensor, scene_radius: float,
             opts: FitOptions, generator: torch.Generator, prune_big: bool):
    """Clone small, split large high-gradient Gaussians; prune transparent (and huge) ones."""
    p = {k: v.detach() for k, v in params.items()}
    dev = p["means"].device
    grads = grads.to(dev)
    scale_max = p["log_scales"].exp().amax(-1)
    high = grads >= opts.grad_threshold
    room = max(0, opts.max_gaussians - p["means"].shape[0])
    if int(high.sum()) > room // 2:  # keep the largest gradients that fit under the cap
        keep_n = room // 2
        idx = torch.argsort(grads, descending=True)[:keep_n]
        high = torch.zeros_like(high)
        high[idx] = True
    small = scale_max <= 0.01 * scene_radius
    clone, split = high & small, high & ~small
    new: dict[str, list[torch.Tensor]] = {k: [v] for k, v in p.items()}
    fg_parts = [foreground]
    for k, v in p.items():
        new[k].append(v[clone])
    fg_parts.append(foreground[clone])
    if bool(split.any()):
        n = 2
        std = p["log_scales"][split].exp().repeat(n, 1)
        noise = torch.randn(std.shape, generator=generator, dtype=std.dtype).to(dev) * std
        R = quaternion_to_matrix(p["rotations"][split]).repeat(n, 1, 1)
        for k, v in p.items():
            rep = v[split].repeat(n, *([1] * (v.ndim - 1)))
            if k == "means":
                rep = rep + torch.einsum("nij,nj->ni", R, noise)
            elif k == "log_scales":
                rep = rep - math.log(0.8 * n)
            new[k].append(rep)
        fg_parts.append(foreground[split].repeat(n))
    out = {k: torch.cat(v, 0) for k, v in new.items()}
    fg = torch.cat(fg_parts, 0)
    n_old = p["means"].shape[0]
    remove = torch.zeros(out["means"].shape[0], dtype=torch.bool, device=dev)
    remove[:n_old] = split
    remove |= torch.sigmoid(out["opacity_logits"]) < 0.005
    if prune_big:
        remove |= out["log_scales"].exp().amax(-1) > 0.1 * scene_radius
    keep = ~remove
    return {k: v[keep].contiguous() for k, v in out.items()}, fg[keep].contiguous()


# ------------------------------------------------------------------------------------- later timesteps
class _Tracker:
    """State for the later timesteps: the fixed background images, the kNN priors, the floor."""

    def __init__(self, model: _Model, cameras: list[Camera], opts: FitOptions, floor_y: float | None):
        from scipy.spatial import cKDTree

        self.fg_idx = torch.nonzero(model.foreground).squeeze(1)
        self.bg_idx = torch.nonzero(~model.foreground).squeeze(1)
        self.floor_y = floor_y
        dev = model.means.device
        fg_means = model.means[self.fg_idx].double().cpu().numpy()
        k = min(opts.knn, max(0, fg_means.shape[0] - 1))
        if k > 0:
            dist, nb = cKDTree(fg_means).query(fg_means, k=k + 1)
            dist, nb = dist[:, 1:], nb[:, 1:]
        else:
            dist, nb = np.zeros((fg_means.shape[0], 0)), np.zeros((fg_means.shape[0], 0), np.int64)
        dt = model.means.dtype
        self.priors = Priors(torch.as_tensor(nb, dtype=torch.int64, device=dev),
                             torch.as_tensor(np.exp(-opts.knn_lambda * dist ** 2), dtype=dt, device=dev),
                             torch.as_tensor(dist, dtype=dt, device=dev))
        self.backgrounds = []
        with torch.no_grad():
            for cam in cameras:
                out = render_views(model, cam, subset=self.bg_idx)
                self.backgrounds.append((out["rgb"], out["features"]))


def _fit_later(model: _Model, tracker: _Tracker, frames: _Frames, cameras: list[Camera], opts: FitOptions,
               scene_radius: float, prev: tuple[torch.Tensor, torch.Tensor], prev2: tuple[torch.Tensor, torch.Tensor],
               generator: torch.Generator, progress: Callable[[FitEvent], None], t: int
               ) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Optimize the foreground centres/rotations of one timestep. Returns full (N,3) means, (N,4)
    rotations and the last training PSNR."""
    w = opts.weights
    fi = tracker.fg_idx
    prev_m, prev_r = prev[0][fi], prev[1][fi]
    prev2_m, prev2_r = prev2[0][fi], prev2[1][fi]
    means = (2 * prev_m - prev2_m).clone().requires_grad_(True)
    rots = torch.nn.functional.normalize(2 * prev_r - prev2_r, dim=-1).clone().requires_grad_(True)
    optimizer = torch.optim.Adam([{"params": [means], "lr": opts.lr_means_later * scene_radius},
                                  {"params": [rots], "lr": opts.lr_rotations_later}], lr=0.0, eps=1e-15)
    order: list[int] = []
    last_psnr = float("nan")
    for it in range(opts.iterations):
        if not order:
            order = torch.randperm(len(cameras), generator=generator).tolist()
        c = order.pop()
        unit = torch.nn.functional.normalize(rots, dim=-1)
        out = render_views(model, cameras[c], subset=fi, means=means, rotations=unit)
        bg_rgb, bg_seg = tracker.backgrounds[c]
        trans = 1.0 - out["alpha"]
        rgb = _correct(out["rgb"] + trans * bg_rgb, model, c)
        loss = w["im"] * image_loss(rgb, frames.images[c])
        if frames.masks is not None:
            loss = loss + w["seg"] * image_loss(out["features"] + trans * bg_seg, frames.masks[c])
        if fi.numel() > 1 and tracker.priors.neighbors.shape[1]:
            terms = tracker.priors(means, unit, prev_m, prev_r)
            loss = loss + w["rigid"] * terms["rigid"] + w["rot"] * terms["rot"] + w["iso"] * terms["iso"]
        if tracker.floor_y is not None and fi.numel():
            loss = loss + w["floor"] * torch.clamp(means[:, 1] - tracker.floor_y, min=0).mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if it % 10 == 0 or it == opts.iterations - 1:
            last_psnr = psnr(rgb.detach(), frames.images[c])
        progress(FitEvent("iteration", t, it + 1, opts.iterations, float(loss.detach()), last_psnr))
    with torch.no_grad():
        full_m = prev[0].clone()
        full_r = prev[1].clone()
        full_m[fi] = means.detach()
        full_r[fi] = torch.nn.functional.normalize(rots.detach(), dim=-1)
    return full_m, full_r, last_psnr


# ------------------------------------------------------------------------------------- orchestration
def _work_dir(output: Path) -> Path:
    return output.parent / f".{output.name}.fit"


def _save_npz(path: Path, **arrays: np.ndarray) -> None:
    with atomic_path(path, overwrite=True) as tmp:
        np.savez(tmp, **arrays)


def _load_npz(path: Path) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise InputError(f"unreadable checkpoint ({exc}); delete it to refit that timestep", file=path) from None


def _generator(seed: int, t: int) -> torch.Generator:
    g = torch.Generator()
    g.manual_seed(int.from_bytes(hashlib.sha256(f"{seed}:{t}".encode()).digest()[:8], "little") & ((1 << 63) - 1))
    return g


def _tqdm_progress(total_timesteps: int):
    from tqdm.auto import tqdm

    bars: dict[str, Any] = {"outer": tqdm(total=total_timesteps, desc="fit", unit="timestep"), "inner": None}

    def callback(ev: FitEvent) -> None:
        if ev.kind == "iteration":
            if bars["inner"] is None:
                bars["inner"] = tqdm(total=ev.total, desc=f"timestep {ev.timestep}", unit="it", leave=False)
            bars["inner"].update(1)
            if ev.index % 10 == 0 or ev.index == ev.total:
                bars["inner"].set_postfix(loss=f"{ev.loss:.4f}", psnr=f"{ev.train_psnr:.2f}")
        elif ev.kind == "timestep":
            if bars["inner"] is not None:
                bars["inner"].close()
                bars["inner"] = None
            bars["outer"].update(1)
            bars["outer"].set_postfix(t=ev.timestep, psnr=f"{ev.train_psnr:.2f}",
                                      **({"resumed": "yes"} if ev.resumed else {}))

    callback.close = lambda: [b.close() for b in bars.values() if b is not None]  # type: ignore[attr-defined]
    return callback


def fit_capture(dataset: str | Path | Capture, output: str | Path, options: FitOptions | None = None, *,
                overwrite: bool = False, progress: bool | Callable[[FitEvent], None] = True) -> Path:
    """Fit dynamic Gaussians to a capture and write the native bundle at ``output``.

    Args:
        dataset: directory in the Dynamic 3D Gaussians layout (or an opened :class:`Capture`).
        output: bundle directory to write (refused when it exists unless ``overwrite``).
        options: :class:`FitOptions`.
        overwrite: replace an existing bundle, and restart a partial fit made with other options.
        progress: True for tqdm bars, False for silence, or a callable receiving :class:`FitEvent`.
    Returns:
        the bundle path. Per-Gaussian foreground flags, the per-camera colour correction and per-timestep
        training PSNR are stored in the bundle (``foreground.npy``; ``metadata.fit``).
    Raises:
        InputError: a malformed dataset (missing frames, bad calibration, mismatched sizes) or options.
        OutputExistsError: ``output`` exists and ``overwrite`` is False.
        ConfigMismatchError: a partial fit with different options exists and ``overwrite`` is False.
    """
    opts = (options or FitOptions()).check()
    output = Path(output)
    if output.exists() and not overwrite:
        raise OutputExistsError(output)
    capture = dataset if isinstance(dataset, Capture) else Capture(dataset)
    steps = capture.timestep_range(opts.timesteps)
    cams_idx = capture.camera_indices("train", opts.cameras)
    capture.check_frames("train", steps, cams_idx, masks=capture.has_masks)
    device = torch.device("cuda" if opts.device == "cuda" or (opts.device == "auto" and torch.cuda.is_available())
                          else "cpu")
    a = steps.start
    full_cams = [capture.train.cameras[a][c] for c in cams_idx]
    cameras = [c.scaled(opts.resolution_scale) for c in full_cams]
    size = (cameras[0].width, cameras[0].height)
    centers = np.stack([c.center for c in full_cams])
    scene_radius = 1.1 * float(np.linalg.norm(centers - centers.mean(0), axis=1).max())

    work = _work_dir(output)
    config = {"version": WORK_VERSION, "dataset": str(capture.root.resolve()), "options": opts.fingerprint(),
              "timesteps": [steps.start, steps.stop], "cameras": [capture.train.cam_ids[a][c] for c in cams_idx]}
    if work.exists():
        try:
            old = read_json(work / "config.json")
        except InputError:
            old = None
        if old != json.loads(json.dumps(config)):
            if not overwrite:
                raise ConfigMismatchError(f"{work}: a partial fit with other options or data is there; pass "
                                          "--overwrite / overwrite=True to start again")
            shutil.rmtree(work)
    work.mkdir(parents=True, exist_ok=True)
    write_json_atomic(work / "config.json", config)

    report = progress if callable(progress) else (_tqdm_progress(len(steps)) if progress else (lambda ev: None))
    try:
        history = _run(capture, steps, cams_idx, cameras, size, opts, device, scene_radius, work, report)
    finally:
        if hasattr(report, "close"):
            report.close()

    static = _load_npz(work / "static.npz")
    T = len(steps)
    means = np.empty((T, static["colors"].shape[0], 3), np.float32)
    rotations = np.empty((T, static["colors"].shape[0], 4), np.float32)
    for i, t in enumerate(steps):
        z = _load_npz(work / f"t{t:06d}.npz")
        means[i], rotations[i] = z["means"], z["rotations"]
    g = GaussianSequence(means=means, rotations=rotations, log_scales=static["log_scales"],
                         opacity_logits=static["opacity_logits"], colors=static["colors"],
                         foreground=static["foreground"].astype(bool), source=str(capture.root))
    test_idx = capture.camera_indices("test", None)
    rig = CameraRig.static(full_cams, [capture.test.cameras[a][c] for c in test_idx], T)
    metadata = {"source_format": "dynamic3dgs-capture", "source": str(capture.root.resolve()),
                "first_timestep": a,
                "color_correction": {"cam_m": static["cam_m"].tolist(), "cam_c": static["cam_c"].tolist()},
                "fit": {"options": opts.fingerprint(), "train_psnr": history,
                        "floor_y": float(static["floor_y"][0]) if static["floor_y"].size else None}}
    from ..scene.bundle import write_bundle

    write_bundle(Scene(gaussians=g, cameras=rig, name=capture.root.name, fps=30.0, metadata=metadata), output,
                 overwrite=overwrite)
    shutil.rmtree(work, ignore_errors=True)
    return output


def _run(capture: Capture, steps: range, cams_idx: list[int], cameras: list[Camera], size: tuple[int, int],
         opts: FitOptions, device, scene_radius: float, work: Path, report) -> list[float]:
    """Fit (or resume) every timestep of ``steps`` into ``work``; returns training PSNR per timestep."""
    a = steps.start
    history_path = work / "history.json"
    history: dict[str, float] = read_json(history_path) if history_path.is_file() else {}
    static_path = work / "static.npz"
    if static_path.is_file() and (work / f"t{a:06d}.npz").is_file():
        s = _load_npz(static_path)
        z = _load_npz(work / f"t{a:06d}.npz")
        model = _model_from_arrays(z["means"], z["rotations"], s, device)
        floor_y = float(s["floor_y"][0]) if s["floor_y"].size else None
        report(FitEvent("timestep", a, train_psnr=history.get(str(a), float("nan")), resumed=True))
    else:
        frames = _Frames(capture, a, cams_idx, size, device)
        if capture.has_masks and opts.clean_plate_samples > 0:
            frames.add_clean_plates(clean_plates(capture, cams_idx, sample_timesteps(steps, opts.clean_plate_samples),
                                                 size), device)
        model, floor_y = _initial_model(frames, cameras, opts, device)
        model, last = _fit_first(model, frames, cameras, opts, scene_radius, _generator(opts.seed, a), report, a)
        _save_npz(static_path, log_scales=_np(model.log_scales), opacity_logits=_np(model.opacity_logits),
                  colors=_np(model.colors), foreground=_np(model.foreground), cam_m=_np(model.cam_m),
                  cam_c=_np(model.cam_c), floor_y=np.asarray([] if floor_y is None else [floor_y], np.float64))
        # the model continues from its float32 round trip, exactly as a resumed run would
        s = _load_npz(static_path)
        _save_npz(work / f"t{a:06d}.npz", means=_np(model.means), rotations=_np(model.rotations))
        z = _load_npz(work / f"t{a:06d}.npz")
        model = _model_from_arrays(z["means"], z["rotations"], s, device)
        history[str(a)] = last
        write_json_atomic(history_path, history)
        report(FitEvent("timestep", a, train_psnr=last))
    if len(steps) == 1:
        return [history[str(a)]]
    tracker = _Tracker(model, cameras, opts, floor_y)
    prev2 = prev = (model.means, model.rotations)
    for t in steps[1:]:
        path = work / f"t{t:06d}.npz"
        if path.is_file():
            z = _load_npz(path)
            cur = (torch.from_numpy(z["means"]).to(device), torch.from_numpy(z["rotations"]).to(device))
            report(FitEvent("timestep", t, train_psnr=history.get(str(t), float("nan")), resumed=True))
        else:
            frames = _Frames(capture, t, cams_idx, size, device)
            m, r, last = _fit_later(model, tracker, frames, cameras, opts, scene_radius, prev, prev2,
                                    _generator(opts.seed, t), report, t)
            _save_npz(path, means=_np(m), rotations=_np(r))
            z = _load_npz(path)
            cur = (torch.from_numpy(z["means"]).to(device), torch.from_numpy(z["rotations"]).to(device))
            history[str(t)] = last if math.isfinite(last) else None  # no step taken (iterations=0)
            write_json_atomic(history_path, history)
            report(FitEvent("timestep", t, train_psnr=last))
        prev2, prev = prev, cur
    return [history.get(str(t), float("nan")) for t in steps]


def _np(t: torch.Tensor) -> np.ndarray:
    a = t.detach().cpu().numpy()
    return a.astype(np.float32) if a.dtype.kind == "f" else a


def _model_from_arrays(means: np.ndarray, rotations: np.ndarray, s: dict[str, np.ndarray], device) -> _Model:
    tt = lambda a: torch.from_numpy(np.ascontiguousarray(a)).to(device)  # noqa: E731
    return _Model(tt(means), tt(rotations), tt(s["log_scales"]), tt(s["opacity_logits"]), tt(s["colors"]),
                  tt(s["foreground"].astype(bool)), tt(s["cam_m"]), tt(s["cam_c"]))


def _initial_model(frames: _Frames, cameras: list[Camera], opts: FitOptions, device) -> tuple[_Model, float | None]:
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
    model = _Model(
        means=torch.as_tensor(cloud.points, dtype=f32, device=device),
        rotations=rot.to(device),
        log_scales=torch.as_tensor(np.log(np.maximum(cloud.scales, 1e-6)), dtype=f32, device=device)[:, None].repeat(1, 3).contiguous(),
        opacity_logits=torch.full((N,), 2.0, dtype=f32, device=device),
        colors=torch.as_tensor(cloud.colors, dtype=f32, device=device),
        foreground=torch.as_tensor(cloud.foreground, device=device),
        cam_m=torch.zeros(len(cameras), 3, dtype=f32, device=device),
        cam_c=torch.zeros(len(cameras), 3, dtype=f32, device=device))
    return model, cloud.floor_y


def _add_hidden_background(cloud, cameras: list[Camera], frames: _Frames, masks: list[np.ndarray],
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
