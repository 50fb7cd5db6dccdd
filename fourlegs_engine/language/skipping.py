"""The work feature extraction may skip, and how the skipped features are filled (the cost knobs).

Every knob keeps the features' layout: one (Σ_cameras num_crops, D) array per timestep, so the lift,
the autoencoder and the query engine read them unchanged.

- **Camera subset**: only ``k`` of the training cameras are encoded, chosen for coverage
  (:func:`coverage_cameras`); the others keep zero rows, which the lift and the autoencoder treat as
  "no evidence" (``extract.view_has_evidence``).
- **Timestep stride with tube sharing**: only every ``stride``-th timestep (and the last) is encoded
  (:func:`encoded_timesteps`). The 8-frame tubes of neighbouring timesteps share 7 of their 8 frames, so
  the features of a timestep in between are the normalized linear interpolation of its two encoded
  neighbours' (``fill="interpolate"``) or the nearer neighbour's (``fill="reuse"``) (:func:`fill_features`).
  With ``fill="latents"`` the in-between timesteps get no features: the lift fills them in the field, each
  Gaussian with the normalized interpolation of its own latents at the two encoded neighbours
  (:mod:`.latent_fill`), so the fill follows a moving object instead of smearing it at fixed pixels.
- **Early exits**: a crop whose pixels do not change over every frame from the previous encoded
  timestep's tube to this timestep's tube sees the same clip both times, so its feature is copied
  (:func:`unchanged_crops`). "Unchanged" is read off the foreground (``"foreground"``: no foreground
  coverage in the crop in any of those frames; the background of a fitted or synthetic scene is static)
  or off the frames themselves (``"difference"``: the crop's mean absolute frame-to-frame change stays
  under the threshold).
"""
from __future__ import annotations

from typing import Any, Callable, Sequence

import numpy as np
import torch

from ..errors import InputError
from .plans import EARLY_EXITS, FILL_MODES, LATENT_FILLS

#: a crop counts as unchanged when its mean foreground coverage / mean absolute change per pixel (summed
#: over channels) stays below this in every frame of the tubes compared
DEFAULT_UNCHANGED_BELOW = 0.002
TUBE_BEFORE, TUBE_AFTER = 4, 3  # a timestep's tube holds frames t-4 .. t+3


def coverage_cameras(centers: np.ndarray, forwards: np.ndarray, k: int) -> list[int]:
    """``k`` camera indices spread over the rig: greedy farthest-point sampling on the camera centres
    (scaled by the rig's size) and viewing directions, starting from the camera nearest the rig's mean.

    Args:
        centers: (C, 3) camera centres; forwards: (C, 3) unit viewing directions.
        k: cameras wanted (clamped to 1..C).
    Returns:
        k sorted indices into the C cameras.
    """
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    forwards = np.asarray(forwards, dtype=np.float64).reshape(-1, 3)
    count = centers.shape[0]
    if count == 0:
        return []
    k = int(min(max(int(k), 1), count))
    mean = centers.mean(0)
    scale = float(np.sqrt(((centers - mean) ** 2).sum(1).mean())) or 1.0
    points = np.concatenate([(centers - mean) / scale, forwards], axis=1)         # (C, 6)
    chosen = [int(np.argmin(((centers - mean) ** 2).sum(1)))]
    dist = ((points - points[chosen[0]]) ** 2).sum(1)
    while len(chosen) < k:
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, ((points - points[nxt]) ** 2).sum(1))
    return sorted(chosen)


def encoded_timesteps(num_timesteps: int, stride: int) -> list[int]:
    """The timesteps a stride encodes: 0, s, 2s, ... and the last one (so every other has two neighbours)."""
    if stride < 1:
        raise InputError(f"must be >= 1, got {stride}", field="timestep stride")
    if num_timesteps < 1:
        return []
    steps = list(range(0, num_timesteps, int(stride)))
    if steps[-1] != num_timesteps - 1:
        steps.append(num_timesteps - 1)
    return steps


def feature_timesteps(num_timesteps: int, stride: int, fill: str) -> list[int]:
    """The timesteps that have teacher features once extraction is complete: every one, or with a fill of
    the lifted field (:data:`LATENT_FILLS`) only the stride's grid."""
    if fill in LATENT_FILLS:
        return encoded_timesteps(num_timesteps, stride)
    return list(range(num_timesteps))


def timestep_work(num_timesteps: int, selection: Sequence[int], stride: int, fill: str,
                  shard: tuple[int, int] = (0, 1)) -> tuple[list[int], list[int]]:
    """(timesteps to encode, timesteps to fill) of one worker.

    The selected timesteps on the stride's grid are encoded, and so are the grid neighbours the
    selected timesteps in between are filled from (a selection such as ``4:8`` needs 8 encoded to fill
    5-7). A shard ``(i, n)`` takes every n-th of each list from i; with stride 1 that is the shard of the
    selection itself."""
    grid = encoded_timesteps(num_timesteps, stride)
    on_grid = set(grid)
    off = [t for t in selection if t not in on_grid]
    needed = sorted({t for t in selection if t in on_grid} | {k for t in off for k, _ in fill_sources(t, grid, fill)})
    i, n = shard
    return needed[i::n], off[i::n]


def fill_sources(t: int, encoded: Sequence[int], fill: str) -> list[tuple[int, float]]:
    """The encoded timesteps timestep ``t``'s features are made of, with their weights (summing to 1).

    ``t`` itself when it is encoded; else its two neighbours weighted by closeness ("interpolate") or
    the nearer one, the earlier on a tie ("reuse"); "latents" weighs like "interpolate"."""
    if fill not in FILL_MODES:
        raise InputError(f"unknown fill {fill!r} (choose from {', '.join(FILL_MODES)})", field="fill")
    grid = np.asarray(sorted(encoded))
    if grid.size == 0:
        raise InputError("no encoded timestep to fill from", field="timestep stride")
    i = int(np.searchsorted(grid, t))
    if i < grid.size and grid[i] == t:
        return [(int(t), 1.0)]
    if i == 0 or i == grid.size:
        return [(int(grid[min(i, grid.size - 1)]), 1.0)]
    a, b = int(grid[i - 1]), int(grid[i])
    w = (t - a) / float(b - a)
    if fill == "reuse":
        return [(a, 1.0)] if w <= 0.5 else [(b, 1.0)]
    return [(a, 1.0 - w), (b, w)]


def fill_features(parts: Sequence[tuple[np.ndarray, float]]) -> np.ndarray:
    """Σ w·features over the sources, each row L2-normalized (a row zero in every source stays zero).

    Args:
        parts: (features (M, D), weight) pairs with the same M, D.
    Returns:
        (M, D) float16, unit rows or zero rows.
    """
    total = None
    for feats, weight in parts:
        part = np.asarray(feats, dtype=np.float32) * np.float32(weight)
        total = part if total is None else total + part
    norm = np.linalg.norm(total, axis=1, keepdims=True)
    out = np.where(norm > 1e-8, total / np.maximum(norm, 1e-8), 0.0)
    return out.astype(np.float16)


def comparison_frames(t: int, previous: int, num_timesteps: int) -> list[int]:
    """Every frame from the start of ``previous``'s tube to the end of ``t``'s (clamped to the scene)."""
    first = max(0, previous - TUBE_BEFORE)
    last = min(num_timesteps - 1, t + TUBE_AFTER)
    return list(range(first, last + 1))


def unchanged_crops(frame_signal: Callable[[int], torch.Tensor | None], frames: Sequence[int], mode: str,
                    threshold: float = DEFAULT_UNCHANGED_BELOW) -> torch.Tensor | None:
    """Which crops of one camera see the same clip at two timesteps.

    Args:
        frame_signal: frame index -> (num_crops,) per-crop signal of that frame: mean foreground coverage
            (``"foreground"``) or mean absolute change from the frame before (``"difference"``); None when
            the frame is unavailable (then nothing counts as unchanged).
        frames: the frames compared (:func:`comparison_frames`); for ``"difference"`` the first frame's
            own change is not looked at (only changes inside the range matter).
        mode: "foreground" | "difference".
    Returns:
        (num_crops,) bool, True where the crop stays below ``threshold`` in every frame; None if unknown.
    """
    if mode not in EARLY_EXITS or mode == "none":
        raise InputError(f"unknown early exit {mode!r} (choose from {', '.join(EARLY_EXITS[1:])})",
                         field="early exit")
    looked = list(frames[1:]) if mode == "difference" else list(frames)
    if not looked:
        return None
    worst = None
    for k in looked:
        signal = frame_signal(k)
        if signal is None:
            return None
        worst = signal if worst is None else torch.maximum(worst, signal)
    return worst < float(threshold)


def foreground_values(scene: Any) -> torch.Tensor | None:
    """(N, 1) float32 foreground indicator of the scene's Gaussians, None when the scene has none."""
    fg = scene.gaussians.foreground
    if fg is None:
        return None
    return torch.from_numpy(np.asarray(fg, dtype=np.float32).reshape(-1, 1))


def render_foreground(scene: Any, camera: Any, t: int, values: torch.Tensor) -> torch.Tensor:
    """(1, H, W) share of every pixel's colour that foreground Gaussians contribute at timestep ``t``."""
    from ..render import render_frame
    frame = scene.gaussians.at(t)
    out = render_frame(frame, camera, outputs=("features",), features=values)["features"]
    return torch.nan_to_num(out.float(), nan=0.0).clamp_(0.0, 1.0).permute(2, 0, 1).contiguous()
