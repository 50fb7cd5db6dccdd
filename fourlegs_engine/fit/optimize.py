"""The per-timestep optimizations of a fit: the static first timestep (all parameters, densified) and
the later timesteps (foreground centres and rotations under the physical priors); see :mod:`.fitter`."""
from __future__ import annotations

import math
from typing import Callable

import numpy as np
import torch

from ..scene.camera import Camera
from ..scene.gaussians import quaternion_to_matrix
from .clusters import motion_parts, rigid_part_motion
from .effort import moving_residual
from .losses import Priors, image_loss, psnr
from .model import GaussianModel, TrainingFrames, correct_colours, render_views
from .options import FitEvent, FitOptions


# ------------------------------------------------------------------------------------- first timestep
def fit_first_timestep(model: GaussianModel, frames: TrainingFrames, cameras: list[Camera], opts: FitOptions, scene_radius: float,
               generator: torch.Generator, progress: Callable[[FitEvent], None], t: int) -> tuple[GaussianModel, float]:
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
        cur = GaussianModel(params["means"], params["rotations"], params["log_scales"], params["opacity_logits"],
                     params["colors"], model.foreground, cam_m, cam_c)
        out = render_views(cur, cam, with_seg=frames.masks is not None)
        rgb = correct_colours(out["rgb"], cur, c)
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
        out_model = GaussianModel(params["means"].detach(), torch.nn.functional.normalize(params["rotations"].detach(), dim=-1),
                           params["log_scales"].detach(), params["opacity_logits"].detach(),
                           params["colors"].detach().clamp(0, 1), model.foreground, cam_m.detach(), cam_c.detach())
    return out_model, last_psnr


def _plate_loss(model: GaussianModel, cam: Camera, c: int, frames: TrainingFrames) -> torch.Tensor:
    """Mean L1 between the colour-corrected render of the background Gaussians alone and camera ``c``'s
    clean plate, over the pixels the plate knows."""
    bg_idx = torch.nonzero(~model.foreground).squeeze(1)
    rgb = correct_colours(render_views(model, cam, with_seg=False, subset=bg_idx)["rgb"], model, c)
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
class Tracker:
    """State for the later timesteps: the fixed background images, the kNN priors, the floor."""

    def __init__(self, model: GaussianModel, cameras: list[Camera], opts: FitOptions, floor_y: float | None):
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
        self.parts: torch.Tensor | None = None  # (F,) part of each foreground Gaussian
        self.free_parts: torch.Tensor | None = None  # (P,) whole connected components
        if opts.part_extent > 0:
            labels, free = motion_parts(fg_means, nb, dist, opts.part_extent)
            self.parts, self.free_parts = torch.as_tensor(labels, device=dev), torch.as_tensor(free, device=dev)
        self.priors = Priors(torch.as_tensor(nb, dtype=torch.int64, device=dev),
                             torch.as_tensor(np.exp(-opts.knn_lambda * dist ** 2), dtype=dt, device=dev),
                             torch.as_tensor(dist, dtype=dt, device=dev))
        self.model = model
        self.cameras = cameras
        self.backgrounds = self._background_images(cameras)
        self._scaled: dict[float, tuple[list[Camera], list[tuple[torch.Tensor, torch.Tensor]]]] = {}

    def _background_images(self, cameras: list[Camera]) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Per camera, the background Gaussians' rgb (H,W,3) and seg colours (H,W,3), rendered alone."""
        images = []
        with torch.no_grad():
            for cam in cameras:
                out = render_views(self.model, cam, subset=self.bg_idx)
                images.append((out["rgb"], out["features"]))
        return images

    def scaled_views(self, scale: float) -> tuple[list[Camera], list[tuple[torch.Tensor, torch.Tensor]]]:
        """The training cameras at ``scale`` times the fit resolution and their background images (cached)."""
        if scale == 1.0:
            return self.cameras, self.backgrounds
        if scale not in self._scaled:
            cams = [cam.scaled(scale) for cam in self.cameras]
            self._scaled[scale] = (cams, self._background_images(cams))
        return self._scaled[scale]


def downsample(image: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """(H,W,C) → (height,width,C) by area averaging (each output pixel the mean of the input pixels it covers)."""
    if image.shape[0] == height and image.shape[1] == width:
        return image
    out = torch.nn.functional.interpolate(image.permute(2, 0, 1)[None], size=(height, width), mode="area")
    return out[0].permute(1, 2, 0).contiguous()


def _forecast(fi: torch.Tensor, prev: tuple[torch.Tensor, torch.Tensor], prev2: tuple[torch.Tensor, torch.Tensor]
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """Constant-velocity forecast of the foreground centres (F,3) and unit rotations (F,4)."""
    means = 2 * prev[0][fi] - prev2[0][fi]
    rots = torch.nn.functional.normalize(2 * prev[1][fi] - prev2[1][fi], dim=-1)
    return means, rots


def _composite(model: GaussianModel, tracker: Tracker, cameras: list[Camera], c: int, means: torch.Tensor,
               unit_rotations: torch.Tensor, backgrounds: list[tuple[torch.Tensor, torch.Tensor]] | None = None,
               colors: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Camera ``c``'s colour-corrected rgb (H,W,3) and seg colours (H,W,3): the foreground at ``means``/
    ``unit_rotations`` (with ``colors`` (F,3), default the model's) blended over the fixed background image
    (``backgrounds``, default the tracker's)."""
    out = render_views(model, cameras[c], subset=tracker.fg_idx, means=means, rotations=unit_rotations, colors=colors)
    bg_rgb, bg_seg = (tracker.backgrounds if backgrounds is None else backgrounds)[c]
    trans = 1.0 - out["alpha"]
    return correct_colours(out["rgb"] + trans * bg_rgb, model, c), out["features"] + trans * bg_seg


def forecast_residual(model: GaussianModel, tracker: Tracker, frames: TrainingFrames, previous: TrainingFrames,
                      cameras: list[Camera], prev: tuple[torch.Tensor, torch.Tensor],
                      prev2: tuple[torch.Tensor, torch.Tensor], colors: torch.Tensor | None = None) -> tuple[float, int]:
    """The forecast's mean absolute error on the pixels that moved since ``previous`` (every training
    camera) and their count: what :func:`.effort.iterations_for` sizes a later timestep by. ``colors``:
    (N,3) the previous timestep's colours (default the model's)."""
    means, rots = _forecast(tracker.fg_idx, prev, prev2)
    fg_colors = None if colors is None else colors[tracker.fg_idx]
    with torch.no_grad():
        renders = [_composite(model, tracker, cameras, c, means, rots, colors=fg_colors)[0] for c in range(len(cameras))]
    return moving_residual(renders, frames.images, previous.images)


def motion_step_scale(prev_means: torch.Tensor, prev2_means: torch.Tensor, step_range: float) -> torch.Tensor:
    """(F,) each foreground centre's step scale: its speed (F,3 displacement between the two previous
    timesteps) over the median speed, clamped to [1 / ``step_range``, ``step_range``]; all ones when
    ``step_range`` is 1 or nothing moved."""
    ones = torch.ones(prev_means.shape[0], dtype=prev_means.dtype, device=prev_means.device)
    if step_range <= 1.0 or prev_means.shape[0] == 0:
        return ones
    speed = torch.linalg.vector_norm(prev_means - prev2_means, dim=1)
    typical = float(speed.median())
    if not typical > 0.0 or not np.isfinite(typical):
        return ones
    return torch.nan_to_num(speed / typical, nan=1.0).clamp(1.0 / step_range, step_range)


def fit_later_timestep(model: GaussianModel, tracker: Tracker, frames: TrainingFrames, cameras: list[Camera], opts: FitOptions,
               scene_radius: float, prev: tuple[torch.Tensor, torch.Tensor], prev2: tuple[torch.Tensor, torch.Tensor],
               generator: torch.Generator, progress: Callable[[FitEvent], None], t: int, iterations: int,
               colors: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, float]:
    """Optimize the foreground centres/rotations of one timestep for ``iterations`` steps, after the part
    steps of :func:`move_parts` when ``opts.part_extent`` > 0 (``part_fraction`` × ``iterations`` of them,
    every part, at the first later timestep, recognised by ``prev2`` being ``prev``; ``free_part_fraction`` ×
    ``iterations``, free parts only, later). With ``opts.lr_colors_later`` > 0 the foreground colours are
    optimized too, starting from ``colors`` ((N,3), the previous timestep's; default the model's).
    Returns full (N,3) means, (N,4) rotations, (N,3) colours in [0, 1] and the last training PSNR."""
    w = opts.weights
    fi = tracker.fg_idx
    prev_m, prev_r = prev[0][fi], prev[1][fi]
    full_colors = model.colors if colors is None else colors
    fg_colors = full_colors[fi]
    forecast_m, forecast_r = _forecast(fi, prev, prev2)
    if tracker.parts is not None:
        first = prev2[0] is prev[0]  # no velocity known yet: the forecast is the previous timestep
        fraction = opts.part_fraction if first else opts.free_part_fraction
        part_steps = int(round(fraction * iterations))
        if part_steps and fi.numel() and (first or bool(tracker.free_parts.any())):
            forecast_m, forecast_r = move_parts(model, tracker, frames, opts, scene_radius, forecast_m, forecast_r,
                                                generator, part_steps, only_free=not first, colors=fg_colors)
    # the centres are the forecast plus a per-Gaussian step scale times what Adam moves: Adam's steps are
    # about its learning rate whatever the gradient's size, so the scale sets each centre's step
    step = motion_step_scale(prev_m, prev2[0][fi], opts.motion_step_range)[:, None]
    offset = torch.zeros_like(forecast_m).requires_grad_(True)
    rots = forecast_r.clone().requires_grad_(True)
    groups = [{"params": [offset], "lr": opts.lr_means_later * scene_radius},
              {"params": [rots], "lr": opts.lr_rotations_later}]
    if opts.lr_colors_later > 0:
        fg_colors = fg_colors.clone().requires_grad_(True)
        groups.append({"params": [fg_colors], "lr": opts.lr_colors_later})
    optimizer = torch.optim.Adam(groups, lr=0.0, eps=1e-15)
    order: list[int] = []
    last_psnr = float("nan")
    for it in range(iterations):
        if not order:
            order = torch.randperm(len(cameras), generator=generator).tolist()
        c = order.pop()
        means = forecast_m + step * offset
        unit = torch.nn.functional.normalize(rots, dim=-1)
        rgb, seg = _composite(model, tracker, cameras, c, means, unit, colors=fg_colors)
        loss = w["im"] * image_loss(rgb, frames.images[c])
        if frames.masks is not None:
            loss = loss + w["seg"] * image_loss(seg, frames.masks[c])
        if fi.numel() > 1 and tracker.priors.neighbors.shape[1]:
            terms = tracker.priors(means, unit, prev_m, prev_r)
            loss = loss + w["rigid"] * terms["rigid"] + w["rot"] * terms["rot"] + w["iso"] * terms["iso"]
        if tracker.floor_y is not None and fi.numel():
            loss = loss + w["floor"] * torch.clamp(means[:, 1] - tracker.floor_y, min=0).mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if it % 10 == 0 or it == iterations - 1:
            last_psnr = psnr(rgb.detach(), frames.images[c])
        progress(FitEvent("iteration", t, it + 1, iterations, float(loss.detach()), last_psnr))
    with torch.no_grad():
        full_m = prev[0].clone()
        full_r = prev[1].clone()
        full_m[fi] = forecast_m + step * offset.detach()
        full_r[fi] = torch.nn.functional.normalize(rots.detach(), dim=-1)
        if opts.lr_colors_later > 0:
            full_colors = full_colors.clone()
            full_colors[fi] = fg_colors.detach().clamp(0, 1)
    return full_m, full_r, full_colors, last_psnr


def move_parts(model: GaussianModel, tracker: Tracker, frames: TrainingFrames, opts: FitOptions, scene_radius: float,
               start_m: torch.Tensor, start_r: torch.Tensor, generator: torch.Generator, steps: int,
               only_free: bool = False, colors: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The part steps of a later timestep: optimize one translation and one rotation (about the part's
    mean centre) per rigid part of ``tracker.parts`` for ``steps`` steps, one training camera per step at
    ``opts.part_scale`` of the fit resolution, under the image, segmentation and floor losses.

    Args:
        start_m, start_r: (F,3) foreground centres and (F,4) unit rotations to start from (the forecast).
        only_free: move only the free parts (whole connected components); the others stay at the start.
        colors: (F,3) foreground colours to render with (default the model's).
    Returns:
        the moved (F,3) centres and (F,4) unit rotations.
    """
    w = opts.weights
    labels = tracker.parts
    cameras, backgrounds = tracker.scaled_views(opts.part_scale)
    images = [downsample(im, cam.width, cam.height) for im, cam in zip(frames.images, cameras)]
    masks = None if frames.masks is None else [downsample(m, cam.width, cam.height) for m, cam in zip(frames.masks, cameras)]
    n_parts = tracker.free_parts.shape[0]
    counts = torch.bincount(labels, minlength=n_parts).clamp_min(1).to(start_m.dtype)
    centres = torch.zeros(n_parts, 3, dtype=start_m.dtype, device=start_m.device).index_add_(0, labels, start_m)
    centres = centres / counts[:, None]
    movable = (tracker.free_parts if only_free else torch.ones_like(tracker.free_parts)).to(start_m.dtype)[:, None]
    translation = torch.zeros_like(centres).requires_grad_(True)
    omega = torch.zeros_like(centres).requires_grad_(True)
    optimizer = torch.optim.Adam([{"params": [translation], "lr": opts.lr_means_later * scene_radius},
                                  {"params": [omega], "lr": opts.lr_rotations_later}], lr=0.0, eps=1e-15)
    order: list[int] = []
    for _ in range(steps):
        if not order:
            order = torch.randperm(len(cameras), generator=generator).tolist()
        c = order.pop()
        means, unit = rigid_part_motion(start_m, start_r, labels, centres, translation * movable, omega * movable)
        rgb, seg = _composite(model, tracker, cameras, c, means, unit, backgrounds, colors=colors)
        loss = w["im"] * image_loss(rgb, images[c])
        if masks is not None:
            loss = loss + w["seg"] * image_loss(seg, masks[c])
        if tracker.floor_y is not None:
            loss = loss + w["floor"] * torch.clamp(means[:, 1] - tracker.floor_y, min=0).mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        means, unit = rigid_part_motion(start_m, start_r, labels, centres, translation * movable, omega * movable)
        kept = movable[labels] == 0  # exactly where they started, not (x − c) + c
        return torch.where(kept, start_m, means), torch.where(kept, start_r, unit)
