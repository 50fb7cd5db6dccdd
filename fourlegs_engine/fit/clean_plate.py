"""Clean plates: each training camera's view of the static background with the people removed.

At the first timestep the people hide parts of the background from every camera that looks through
them; those parts get no initial points and almost no gradient, and show up as smeared, dark patches
once the people walk away (the background is held still after the first timestep). The cameras are
static, so the background hidden at one timestep is visible at others: the per-pixel median of a
camera's pixels outside the foreground masks over a few timesteps spread across the fitted range is
that camera's background alone.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .dataset import Capture


@dataclass
class CleanPlates:
    """Per training camera: ``images[c]`` (h,w,3) float32 median background colour (0 where unknown)
    and ``known[c]`` (h,w) bool: at least one sampled timestep saw that pixel outside the mask."""

    images: list[np.ndarray]
    known: list[np.ndarray]


def sample_timesteps(steps: range, count: int) -> list[int]:
    """``count`` timesteps spread evenly over ``steps`` (always its first), without repeats."""
    if count <= 1 or len(steps) <= 1:
        return [steps.start]
    picks = np.linspace(0, len(steps) - 1, num=min(count, len(steps))).round().astype(int)
    return sorted({steps[int(i)] for i in picks})


def median_background(images: np.ndarray, masks: np.ndarray, threshold: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel median of ``images`` over the samples whose mask is below ``threshold``.

    Args:
        images: (S,h,w,3) one camera's frames. masks: (S,h,w) foreground fraction in [0,1].
    Returns:
        plate (h,w,3) float32 (0 where no sample is background), known (h,w) bool.
    """
    background = masks < threshold
    known = background.any(0)
    stacked = np.where(background[..., None], images, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN pixels: marked unknown below
        plate = np.nanmedian(stacked, axis=0)
    return np.where(known[..., None], plate, 0.0).astype(np.float32), known


def clean_plates(capture: Capture, cams: Sequence[int], timesteps: Sequence[int], size: tuple[int, int]
                 ) -> CleanPlates:
    """The clean plate of every training camera in ``cams`` from the frames at ``timesteps``, at ``size``
    = (w, h). Needs the capture's masks."""
    images, known = [], []
    for c in cams:
        frames = np.stack([capture.load_image("train", t, c, size) for t in timesteps])
        masks = np.stack([capture.load_mask("train", t, c, size) for t in timesteps])
        plate, ok = median_background(frames, masks)
        images.append(plate)
        known.append(ok)
    return CleanPlates(images, known)
