"""Contact sheet of a plan: sampled frames rendered by the engine's rasterizer through each shot's camera.

Each tile is rendered at the shot's camera key and scene time; a fractional timestep linearly blends
the Gaussian means (and per-timestep colours/scales) of the two neighbouring timesteps and
normalized-lerps their rotations. Frames the plan desaturates or blurs show it (relevancy from the
localizer, at the nearest timestep) — the only frames for which relevancy is computed unless
``overlay`` asks for a relevancy heat overlay on every tile. The action centre is marked with a cross.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch

from ..fileio import atomic_path
from ..scene.camera import Camera
from ..scene.gaussians import GaussianFrame
from .plan import CameraKey, HighlightPlan

EFFECT_COLOURS = {"play": "#9e9e9e", "zoom_in": "#00bcd4", "bullet_time": "#ff9800",
                  "desaturate_background": "#e040fb", "blur_background": "#7c4dff"}


def frame_at(gaussians, timestep: float, device: str = "cpu") -> GaussianFrame:
    """The scene's Gaussians at a fractional timestep (linear blend of the two neighbours)."""
    T = gaussians.num_timesteps
    t = min(max(float(timestep), 0.0), T - 1.0)
    t0 = int(math.floor(t))
    t1 = min(t0 + 1, T - 1)
    w = t - t0
    a = gaussians.at(t0, device)
    if w < 1e-6 or t1 == t0:
        return a
    b = gaussians.at(t1, device)

    def lerp(x: Optional[torch.Tensor], y: Optional[torch.Tensor]) -> Optional[torch.Tensor]:
        return None if x is None else x + w * (y - x)

    rb = torch.where(((a.rotations * b.rotations).sum(-1, keepdim=True) < 0), -b.rotations, b.rotations)
    rot = lerp(a.rotations, rb)
    rot = rot / rot.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return GaussianFrame(means=lerp(a.means, b.means), rotations=rot, log_scales=lerp(a.log_scales, b.log_scales),
                         opacity_logits=a.opacity_logits, colors=lerp(a.colors, b.colors), sh=lerp(a.sh, b.sh),
                         latents=None, foreground=a.foreground)


def key_camera(key: CameraKey, plan: HighlightPlan, width: int, near: float = 0.01, far: float = 100.0) -> Camera:
    """The plan's camera at one key, at a preview width (same aspect and field of view as the plan)."""
    W, H = plan.resolution
    s = width / W
    w, h = max(1, int(round(W * s))), max(1, int(round(H * s)))
    f = key.focal_px * s
    K = np.array([[f, 0.0, w / 2.0], [0.0, f, h / 2.0], [0.0, 0.0, 1.0]])
    pose = key.pose
    return Camera(K=K, w2c=pose.w2c, width=w, height=h, near=near, far=far)


def sample_frames(plan: HighlightPlan, per_shot: int = 4) -> list[tuple[int, int]]:
    """(shot index, frame) pairs: ``per_shot`` frames evenly spread over each shot, ends included."""
    out = []
    for i, s in enumerate(plan.shots):
        k = max(1, min(per_shot, s.num_frames))
        frames = np.unique(np.round(np.linspace(s.frame_start, s.frame_end, k)).astype(int))
        out += [(i, int(f)) for f in frames]
    return out


def desaturate(rgb: np.ndarray, relevancy: np.ndarray, weight: float) -> np.ndarray:
    """Grey out the background: lerp(rgb, luma, weight * (1 - relevancy)). (H,W,3),(H,W) -> (H,W,3)."""
    luma = rgb @ np.array([0.2126, 0.7152, 0.0722])
    k = np.clip(weight * (1.0 - np.clip(relevancy, 0.0, 1.0)), 0.0, 1.0)[..., None]
    return rgb * (1.0 - k) + luma[..., None] * k


def blur_background(rgb: np.ndarray, relevancy: np.ndarray, weight: float, radius: float) -> np.ndarray:
    """Blur the background: lerp(rgb, gaussian_blur(rgb, weight * radius * H), 1 - relevancy).
    (H,W,3),(H,W) -> (H,W,3); ``radius`` is a fraction of the image height."""
    from scipy.ndimage import gaussian_filter

    sigma = float(weight) * float(radius) * rgb.shape[0]
    if sigma <= 0:
        return rgb
    blurred = gaussian_filter(rgb, sigma=(sigma, sigma, 0.0), mode="nearest")
    k = np.clip(1.0 - np.clip(relevancy, 0.0, 1.0), 0.0, 1.0)[..., None]
    return rgb * (1.0 - k) + blurred * k


def render_tiles(scene, plan: HighlightPlan, *, localizer: Any = None, overlay: bool = False, per_shot: int = 4,
                 width: int = 320, background=(0.0, 0.0, 0.0)) -> list[dict[str, Any]]:
    """Render the sampled frames. Returns one dict per tile: image (H,W,3) in [0,1], relevancy or None,
    shot, effect, frame, timestep, weight, centre_uv or None."""
    from ..render import render_frame

    centre = plan.localization.get("action_centre")
    tiles = []
    for shot_index, frame in sample_frames(plan, per_shot):
        shot = plan.shots[shot_index]
        key = shot.camera_keys[frame - shot.frame_start]
        t = shot.time_keys[frame - shot.frame_start].timestep
        cam = key_camera(key, plan, width)
        g = frame_at(scene.gaussians, t)
        with torch.no_grad():
            rgb = render_frame(g, cam, outputs=("rgb",), background=torch.tensor(background, dtype=torch.float32))["rgb"]
        img = np.clip(np.nan_to_num(rgb.detach().cpu().numpy().astype(np.float64)), 0.0, 1.0)
        weight, blur = plan.desaturation_weight(frame), plan.blur_weight(frame)
        rel = None
        if localizer is not None and (weight > 0 or blur > 0 or overlay):
            out = localizer.relevancy_map(plan.query, cam, int(round(t)), outputs=("relevancy",))
            rel = np.asarray(out["relevancy"].detach().cpu().numpy() if torch.is_tensor(out["relevancy"])
                             else out["relevancy"], dtype=np.float64).reshape(cam.height, cam.width)
            rel = np.clip(np.nan_to_num(rel), 0.0, 1.0)
            if blur > 0:
                img = blur_background(img, rel, blur, float((plan.blur or {}).get("radius", 0.02)))
            if weight > 0:
                img = desaturate(img, rel, weight)
        uv = None
        if centre is not None:
            p, z = cam.project(np.asarray(centre)[None])
            if z[0] > 0 and np.all(np.isfinite(p)):
                uv = p[0]
        tiles.append({"image": img, "relevancy": rel if overlay else None, "shot": shot.name,
                      "effect": shot.effect, "frame": frame, "timestep": float(t), "weight": weight, "blur": blur,
                      "centre_uv": uv})
    return tiles


def write_contact_sheet(path: str | Path, scene, plan: HighlightPlan, *, localizer: Any = None,
                        overlay: bool = False, per_shot: int = 4, width: int = 320, overwrite: bool = False) -> Path:
    """Render the sampled frames and save them as one PNG contact sheet (rows = shots)."""
    import matplotlib
    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    tiles = render_tiles(scene, plan, localizer=localizer, overlay=overlay, per_shot=per_shot, width=width)
    rows = [[t for t in tiles if t["shot"] == s.name] for s in plan.shots]
    ncols = max(len(r) for r in rows)
    h, w = tiles[0]["image"].shape[:2]
    tile_w = 3.2
    tile_h = tile_w * h / w + 0.35
    fig, axes = plt.subplots(len(rows), ncols, figsize=(tile_w * ncols, tile_h * len(rows) + 0.6), squeeze=False)
    for r, row in enumerate(rows):
        for c in range(ncols):
            ax = axes[r][c]
            ax.set_xticks([])
            ax.set_yticks([])
            if c >= len(row):
                ax.axis("off")
                continue
            t = row[c]
            ax.imshow(t["image"], interpolation="nearest")
            if t["relevancy"] is not None:
                ax.imshow(np.dstack([np.ones_like(t["relevancy"]), np.zeros_like(t["relevancy"]),
                                     np.zeros_like(t["relevancy"]), 0.55 * t["relevancy"]]), interpolation="nearest")
            if t["centre_uv"] is not None:
                u, v = t["centre_uv"]
                ax.plot([u], [v], marker="+", color="yellow", markersize=9, markeredgewidth=1.2)
                ax.set_xlim(0, w)
                ax.set_ylim(h, 0)
            colour = EFFECT_COLOURS.get(t["effect"], "white")
            for spine in ax.spines.values():
                spine.set_edgecolor(colour)
                spine.set_linewidth(3)
            label = f"{t['shot']} ({t['effect']})  f{t['frame']}  t={t['timestep']:.1f}"
            if t["weight"] > 0:
                label += f"  desat {t['weight']:.2f}"
            if t.get("blur", 0) > 0:
                label += f"  blur {t['blur']:.2f}"
            ax.set_title(label, fontsize=7)
    loc = plan.localization
    seg = loc.get("segment")
    fig.suptitle(f"{plan.scene.get('name')}: \"{plan.query}\"  preset {plan.preset}  segment {seg}  peak "
                 f"{loc.get('peak')}  best view {loc.get('best_view')}  frames {plan.frame_start}-{plan.frame_end}"
                 f" @ {plan.fps:g} fps", fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    with atomic_path(path, overwrite=overwrite) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return Path(path)
