"""Spatial localization on a 2D relevancy map: centre of mass, 3D lift, best connected component.

Paper §6.1: "the center of the action in the image is identified using the center of mass of the 2D
relevancy map; the 3D location is calculated using the action's location in the image and the rendered
depth of the pixel". The map's non-relevant part (R <= 0.5, the query is not more likely than a
canonical phrase) carries no evidence, so the centre of mass weighs pixels by R where R > 0.5 (and by R
everywhere if no pixel is relevant). The bounding-box variant (supplementary B.2) takes the box of the
connected component (scipy.ndimage.label on R > 0.5) with the highest score (its peak relevancy; ties
to the larger summed relevancy). The action centre is the centre of mass of that component (see
:func:`action_focus`), so the centre pixel lies inside the reported box.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
from scipy import ndimage

from ..scene.camera import Camera
from .temporal import RELEVANT

ALPHA_SOLID = 0.5


def _as_map(x) -> np.ndarray:
    a = np.asarray(x.detach().cpu().numpy() if hasattr(x, "detach") else x, dtype=np.float64)
    if a.ndim == 3:
        a = a[..., 0]
    return np.nan_to_num(a, nan=0.0, posinf=0.0, neginf=0.0)


def centre_weights(relevancy_map) -> np.ndarray:
    """(H,W) weights for the centre of mass: R on relevant pixels, else R everywhere."""
    r = np.clip(_as_map(relevancy_map), 0.0, 1.0)
    rel = r > RELEVANT
    return np.where(rel, r, 0.0) if rel.any() else r


def centre_of_mass(relevancy_map) -> Optional[np.ndarray]:
    """(H,W) relevancy -> (2,) centre (x, y) in pixel coordinates (centres at +0.5), or None if empty."""
    w = centre_weights(relevancy_map)
    total = w.sum()
    if w.size == 0 or total <= 0:
        return None
    ys, xs = np.mgrid[0:w.shape[0], 0:w.shape[1]]
    return np.array([(w * (xs + 0.5)).sum() / total, (w * (ys + 0.5)).sum() / total])


def lift_centre(camera: Camera, centre_px, depth_map, alpha_map, relevancy_map) -> tuple[Optional[np.ndarray], float]:
    """3D action centre: unproject ``centre_px`` with the rendered depth there.

    When the centre of mass falls on an empty pixel (alpha < 0.5, e.g. between two relevant objects),
    the depth is the centre-weight average of the rendered depth over solid pixels instead.

    Returns:
        ((3,) world point or None, the depth used).
    """
    if centre_px is None:
        return None, 0.0
    depth, alpha = _as_map(depth_map), _as_map(alpha_map)
    H, W = depth.shape
    x = int(np.clip(np.floor(centre_px[0]), 0, W - 1))
    y = int(np.clip(np.floor(centre_px[1]), 0, H - 1))
    z = depth[y, x] if alpha[y, x] >= ALPHA_SOLID else 0.0
    if not z > 0:
        w = centre_weights(relevancy_map) * (alpha >= ALPHA_SOLID) * (depth > 0)
        if w.sum() <= 0:
            return None, 0.0
        z = float((w * depth).sum() / w.sum())
    if not (np.isfinite(z) and np.isfinite(np.asarray(centre_px, dtype=np.float64)).all()):
        return None, 0.0
    point = camera.unproject(np.asarray(centre_px, dtype=np.float64)[None], np.array([z]))[0]
    return point, float(z)


def best_component(relevancy_map, threshold: float = RELEVANT) -> Optional[np.ndarray]:
    """(H,W) bool mask of the best connected component of R > threshold (highest peak relevancy, ties to the
    larger summed relevancy), or None when no pixel is above the threshold."""
    r = _as_map(relevancy_map)
    labels, n = ndimage.label(r > threshold)
    if n == 0:
        return None
    idx = np.arange(1, n + 1)
    peak = ndimage.maximum(r, labels, idx)
    total = ndimage.sum(r, labels, idx)
    return labels == int(idx[np.lexsort((total, peak))[-1]])


def best_component_bbox(relevancy_map, threshold: float = RELEVANT) -> Optional[tuple[int, int, int, int]]:
    """Box (x0, y0, x1, y1), inclusive pixels, of the best connected component of R > threshold."""
    component = best_component(relevancy_map, threshold)
    return None if component is None else mask_bbox(component)


def action_focus(relevancy_map) -> tuple[np.ndarray, Optional[tuple[int, int, int, int]]]:
    """The part of the map the action centre is taken from, and its box.

    A map often holds several separate relevant blobs (the ball in the air and a smear on the floor); the
    centre of mass of all of them can lie on none, outside every blob's box. The action is the best
    connected component (its box is the bounding-box output), so the centre is taken from that
    component alone: it lies inside the box. Without relevant pixels the whole map is the focus (no box).

    Returns:
        (H,W) float64 relevancy zeroed outside the best component (or the whole map), its box or None.
    """
    r = _as_map(relevancy_map)
    component = best_component(r)
    if component is None:
        return r, None
    return np.where(component, r, 0.0), mask_bbox(component)


def mask_bbox(mask) -> Optional[tuple[int, int, int, int]]:
    """Box (x0, y0, x1, y1) of a binary mask, or None when empty."""
    m = np.asarray(mask, dtype=bool)
    if not m.any():
        return None
    ys, xs = np.nonzero(m)
    return int(xs.min()), int(ys.min()), int(xs.max()), int(ys.max())
