"""The s_t curve as a Blender image for the panel (numpy drawing; no matplotlib inside Blender)."""
from __future__ import annotations

from typing import Optional, Sequence

import bpy
import numpy as np

IMAGE_NAME = "fourlegs_scores"
BACKGROUND = (0.12, 0.12, 0.12, 1.0)
BAR = (0.45, 0.45, 0.45, 1.0)
POSITIVE = (0.95, 0.55, 0.15, 1.0)
SEGMENT = (0.25, 0.35, 0.55, 1.0)
PEAK = (1.0, 1.0, 1.0, 1.0)


def scores_pixels(scores: np.ndarray, positive: np.ndarray, segment: Optional[Sequence[int]],
                  peak: Optional[int], width: int = 256, height: int = 80) -> np.ndarray:
    """(height, width, 4) top-down RGBA: one bar per timestep (orange = positive), segment shaded, peak line."""
    img = np.empty((height, width, 4), np.float32)
    img[:] = BACKGROUND
    T = len(scores)
    if T == 0:
        return img
    s = np.nan_to_num(np.asarray(scores, np.float64))
    top = max(float(s.max()), 1e-12)
    cols = np.minimum((np.arange(width) * T) // width, T - 1)
    if segment is not None:
        in_seg = (cols >= segment[0]) & (cols <= segment[1])
        img[:, in_seg] = SEGMENT
    bar_h = np.round(s[cols] / top * (height - 2)).astype(int)
    rows = np.arange(height)[:, None]
    mask = rows >= (height - bar_h)[None, :]
    colour = np.where(np.asarray(positive, bool)[cols][:, None], POSITIVE, BAR)
    img[mask] = np.broadcast_to(colour[None], (height, width, 4))[mask]
    if peak is not None and 0 <= peak < T:
        x = int((peak + 0.5) * width / T)
        img[:, min(x, width - 1)] = PEAK
    return img


def scores_image(scores, positive, segment, peak, width: int = 256, height: int = 80) -> bpy.types.Image:
    """Create/refresh the ``fourlegs_scores`` image shown in the panel."""
    img = bpy.data.images.get(IMAGE_NAME)
    if img is None or tuple(img.size) != (width, height):
        if img is not None:
            bpy.data.images.remove(img)
        img = bpy.data.images.new(IMAGE_NAME, width, height, alpha=True)
    pixels = scores_pixels(scores, positive, segment, peak, width, height)[::-1]  # Blender rows go up
    img.pixels.foreach_set(np.ascontiguousarray(pixels).ravel())
    img.update()
    img.pack()  # saved inside the .blend (a generated image is otherwise lost on save) ...
    img.use_fake_user = True  # ... and kept although no material or editor uses it
    img.preview_ensure() if hasattr(img, "preview_ensure") else None
    return img
