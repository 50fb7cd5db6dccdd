"""Shot quality as numbers: how each frame of a highlight shows its subject.

For every frame, through the plan's camera at that frame and the scene at its (fractional) timestep,
the subject's Gaussians are rendered twice with the engine's rasterizer: alone (where the subject
would cover the picture if nothing were in front of it) and inside the whole scene with a feature that
is 1 on the subject (where it is actually seen). From those:

- ``height``: the rows the subject alone covers (alpha > 0.5), as a fraction of the frame height;
- ``offset``: distance of the subject's alpha-weighted centre from the frame centre, as a fraction of
  half the frame diagonal (0 = centred, 1 = in a corner);
- ``in_frame``: every subject Gaussian's centre projects inside the frame, in front of the camera, and
  the subject's alpha does not reach the frame border;
- ``occluded``: 1 - (seen subject coverage) / (coverage alone): the share of the subject hidden by
  other Gaussians (0 = fully visible);
- ``floaters``: the share of the frame covered by the fit's floaters in front of the camera — faint
  Gaussians (opacity below :data:`FLOATER_OPACITY`) nearer to the camera than half its distance to the
  subject (each pixel's blended weight of those Gaussians, averaged over the frame).
"""
from __future__ import annotations

from typing import Any, Optional, Sequence

import numpy as np
import torch

#: Alpha above which a pixel belongs to the subject's silhouette.
SILHOUETTE_ALPHA = 0.5
#: Opacity below which a Gaussian near the camera counts as a floater.
FLOATER_OPACITY = 0.3


def frame_quality(gaussians_frame, subject: np.ndarray, camera) -> dict[str, Any]:
    """The four numbers of one frame (see the module doc).

    Args:
        gaussians_frame: the scene's Gaussians at the frame's time (``GaussianFrame``, colours unused).
        subject: (N,) bool, the subject's Gaussians.
        camera: the frame's camera (``fourlegs_engine.scene.Camera``).
    """
    from fourlegs_engine.render import rasterize

    g = gaussians_frame
    idx = torch.as_tensor(np.flatnonzero(subject))
    H, W = camera.height, camera.width
    means = g.means.double().numpy()
    distance = np.linalg.norm(means - camera.center, axis=1)
    subject_distance = float(np.median(distance[subject])) if subject.any() else 0.0
    faint = torch.sigmoid(g.opacity_logits.double()).numpy() < FLOATER_OPACITY
    with torch.no_grad():
        alone = rasterize(g.means[idx], g.rotations[idx], g.log_scales[idx], g.opacity_logits[idx], camera,
                          outputs=("alpha",))["alpha"].reshape(H, W).double().numpy()
        flags = torch.zeros((g.means.shape[0], 2), dtype=g.means.dtype)
        flags[idx, 0] = 1.0
        flags[:, 1] = torch.as_tensor(faint & (distance < 0.5 * subject_distance), dtype=g.means.dtype)
        both = rasterize(g.means, g.rotations, g.log_scales, g.opacity_logits, camera, features=flags,
                         outputs=("features",), background=torch.zeros(2))["features"].reshape(H, W, 2).double().numpy()
    seen, floaters = both[..., 0], float(np.nan_to_num(both[..., 1]).mean())
    alone = np.nan_to_num(alone)
    seen = np.nan_to_num(seen)
    rows = np.flatnonzero((alone > SILHOUETTE_ALPHA).any(axis=1))
    height = float(rows[-1] - rows[0] + 1) / H if rows.size else 0.0
    mass = float(alone.sum())
    if mass > 1e-9:
        yy, xx = np.mgrid[0:H, 0:W] + 0.5
        cx, cy = float((alone * xx).sum() / mass), float((alone * yy).sum() / mass)
        offset = float(np.hypot(cx - W / 2, cy - H / 2) / np.hypot(W / 2, H / 2))
    else:
        offset = 1.0
    uv, z = camera.project(g.means[idx].double().numpy())
    inside = (z > camera.near) & (uv[:, 0] >= 0) & (uv[:, 0] <= W) & (uv[:, 1] >= 0) & (uv[:, 1] <= H)
    border = np.concatenate([alone[0], alone[-1], alone[:, 0], alone[:, -1]])
    in_frame = bool(inside.all() and (border <= SILHOUETTE_ALPHA).all() and mass > 1e-9)
    occluded = float(np.clip(1.0 - seen.sum() / mass, 0.0, 1.0)) if mass > 1e-9 else 1.0
    return {"height": height, "offset": offset, "in_frame": in_frame, "occluded": occluded,
            "in_front": float(inside.mean()) if len(inside) else 0.0, "floaters": floaters}


def plan_quality(scene, plan, subjects, *, width: int = 320,
                 frames: Optional[Sequence[int]] = None) -> list[dict[str, Any]]:
    """One record per frame of ``plan`` (or of ``frames``): shot, effect, frame, timestep and the four numbers.

    ``subjects``: a list whose item k (N,) bool is subject k's Gaussians, or a function
    ``(rank k, timestep t) -> (N,) bool`` (the subject of rank k found at timestep t). A shot's subject is
    its ``subject`` parameter (0 when absent), found at its ``subject_t`` (the plan's peak when absent).
    """
    peak = int(plan.localization.get("t") or plan.localization.get("peak") or 0)
    if not callable(subjects):
        fixed = list(subjects)
        subjects_of = lambda k, t: fixed[min(k, len(fixed) - 1)]  # noqa: E731
    else:
        subjects_of = subjects
    from fourlegs_engine.highlights.preview import frame_at, key_camera

    wanted = None if frames is None else set(int(f) for f in frames)
    out = []
    for shot in plan.shots:
        subject = subjects_of(int(shot.params.get("subject", 0)), int(shot.params.get("subject_t", peak)))
        for key, tkey in zip(shot.camera_keys, shot.time_keys):
            if wanted is not None and key.frame not in wanted:
                continue
            cam = key_camera(key, plan, width, near=0.1)
            g = frame_at(scene.gaussians, tkey.timestep)
            out.append({"shot": shot.name, "effect": shot.effect, "frame": key.frame,
                        "timestep": float(tkey.timestep), **frame_quality(g, subject, cam)})
    return out


def summarize(records: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per shot (in order): frames, height fraction (min/mean/max), largest centre offset, share of frames
    wholly in frame, occlusion (mean/max)."""
    shots: dict[str, list[dict[str, Any]]] = {}
    for r in records:
        shots.setdefault(r["shot"], []).append(r)
    rows = []
    for name, rs in shots.items():
        h = np.array([r["height"] for r in rs])
        occ = np.array([r["occluded"] for r in rs])
        rows.append({"shot": name, "effect": rs[0]["effect"], "frames": len(rs), "height_min": float(h.min()),
                     "height_mean": float(h.mean()), "height_max": float(h.max()),
                     "height_last": float(h[-1]),
                     "offset_max": float(max(r["offset"] for r in rs)),
                     "in_frame_share": float(np.mean([r["in_frame"] for r in rs])),
                     "occluded_mean": float(occ.mean()), "occluded_max": float(occ.max()),
                     "floaters_max": float(max(r["floaters"] for r in rs))})
    return rows


def markdown_table(rows: Sequence[dict[str, Any]]) -> str:
    """The per-shot summary as a Markdown table."""
    lines = ["| shot | effect | frames | height (min / mean / max / last) | max centre offset | wholly in frame | "
             "occluded (mean / max) | floaters (max) |", "|---|---|---:|---|---:|---:|---|---:|"]
    for r in rows:
        lines.append(f"| {r['shot']} | {r['effect']} | {r['frames']} | {r['height_min']:.2f} / {r['height_mean']:.2f} / "
                     f"{r['height_max']:.2f} / {r['height_last']:.2f} | {r['offset_max']:.2f} | "
                     f"{100 * r['in_frame_share']:.0f} % | {r['occluded_mean']:.2f} / {r['occluded_max']:.2f} | "
                     f"{r['floaters_max']:.4f} |")
    return "\n".join(lines)
