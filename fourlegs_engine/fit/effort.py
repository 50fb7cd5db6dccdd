"""Iterations where the motion is: how many optimization steps a later timestep of a fit gets.

Before a later timestep is optimized, its constant-velocity forecast is rendered from every training
camera and compared with the new frames on the *moving pixels*, those whose colour changed by more than
``MOVING_THRESHOLD`` (any channel) since the previous timestep's frame of the same camera. The mean
absolute error there is the timestep's residual; its iteration count is the base count scaled by the
residual against the median residual of the timesteps before it, between a floor and a cap
(:func:`iterations_for`). Over a sequence the steps move to the timesteps whose motion the forecast
misses (the ball thrown or caught) and away from those it predicts, at about the same total.
"""
from __future__ import annotations

import math
from typing import Sequence

import torch

#: a pixel moved when one of its channels changed by more than this (images in [0, 1]) between timesteps
MOVING_THRESHOLD = 0.1


def moving_pixels(previous: torch.Tensor, current: torch.Tensor, threshold: float = MOVING_THRESHOLD) -> torch.Tensor:
    """(H, W) bool: pixels of two (H, W, 3) frames of one camera whose colour changed by more than ``threshold``."""
    return (current - previous).abs().amax(dim=-1) > threshold


def moving_residual(renders: Sequence[torch.Tensor], images: Sequence[torch.Tensor],
                    previous_images: Sequence[torch.Tensor]) -> tuple[float, int]:
    """Mean absolute error of ``renders`` against ``images`` over the moving pixels of every camera.

    Args:
        renders, images, previous_images: per camera (H, W, 3) in [0, 1]: the render to judge, this
            timestep's frame and the previous timestep's frame.
    Returns:
        (residual, moving pixel count); (0.0, 0) when no pixel moved.
    """
    total, count = 0.0, 0
    for render, image, previous in zip(renders, images, previous_images):
        moved = moving_pixels(previous, image)
        n = int(moved.sum())
        if n:
            total += float((render.clamp(0, 1) - image).abs()[moved].sum()) / 3.0
            count += n
    return (total / count if count else 0.0), count


def iterations_for(residual: float, earlier_residuals: Sequence[float], base: int, floor: int, cap: int) -> int:
    """Optimization steps of a later timestep: ``base`` scaled by ``residual`` over the median of the
    ``earlier_residuals`` (the first later timestep, with none before it, gets ``base``), clamped to
    [``floor``, ``cap``]. A residual of 0 (nothing moved) gets ``floor``."""
    known = sorted(r for r in earlier_residuals if math.isfinite(r) and r > 0)
    if not math.isfinite(residual) or residual < 0:
        return int(min(max(base, floor), cap))
    if not known:
        steps = base if residual > 0 else floor
    else:
        mid = len(known) // 2
        reference = known[mid] if len(known) % 2 else 0.5 * (known[mid - 1] + known[mid])
        scaled = base * residual / reference
        steps = cap if not math.isfinite(scaled) else int(round(min(scaled, cap)))
    return int(min(max(steps, floor), cap))
