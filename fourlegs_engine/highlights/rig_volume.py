"""The volume a capture rig observed: where a highlight camera may stand.

A camera outside the rig films what no training camera saw: the back faces of a dome's wall, the
black beyond the reconstruction. The rig volume is the convex hull of the training cameras' centres
and of their feet on a plane ``min_height`` above the floor, so a framed camera stays inside the ring
of cameras (for a dome: under its cameras, in front of the wall behind them) and above the floor.
The floor is the low percentile of the scene's Gaussians along the scene's up.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.spatial import ConvexHull, QhullError

#: Lowest height of a highlight camera above the floor (metres).
MIN_HEIGHT_M = 0.3
#: Percentile of the Gaussians' heights taken as the floor (the fit's few stray splats lie below it).
FLOOR_PERCENTILE = 1.0
#: Positions this close outside the hull still count as inside (a training camera sits on the hull).
TOLERANCE_M = 0.02


@dataclass(frozen=True)
class RigVolume:
    """A convex volume as half-spaces ``normals @ x + offsets <= 0``.

    Attributes:
        normals: (F,3) unit outward normals of the hull's facets.
        offsets: (F,) their offsets.
        up: (3,) the scene's up; floor: the floor's height along it (metres).
    """

    normals: np.ndarray
    offsets: np.ndarray
    up: np.ndarray
    floor: float

    @staticmethod
    def build(camera_centres: np.ndarray, up: np.ndarray, *, floor: Optional[float] = None,
              gaussian_means: Optional[np.ndarray] = None, min_height: float = MIN_HEIGHT_M) -> Optional["RigVolume"]:
        """The rig volume of cameras at ``camera_centres`` (K,3), or None when they span no volume.

        ``floor`` (height along ``up``) defaults to the low percentile of ``gaussian_means`` (N,3), else
        to the lowest camera's height.
        """
        centres = np.asarray(camera_centres, dtype=np.float64).reshape(-1, 3)
        centres = centres[np.isfinite(centres).all(axis=1)]
        up = np.asarray(up, dtype=np.float64)
        up = up / np.linalg.norm(up)
        if len(centres) < 2:
            return None
        if floor is None and gaussian_means is not None:
            means = np.asarray(gaussian_means, dtype=np.float64).reshape(-1, 3)
            heights = means[np.isfinite(means).all(axis=1)] @ up
            floor = float(np.percentile(heights, FLOOR_PERCENTILE)) if len(heights) else None
        if floor is None:
            floor = float((centres @ up).min())
        base = floor + float(min_height)
        heights = centres @ up
        feet = centres - np.maximum(heights - base, 0.0)[:, None] * up[None] + np.maximum(base - heights, 0.0)[:, None] * up
        try:
            hull = ConvexHull(np.concatenate([centres, feet]))
        except (QhullError, ValueError):
            return None
        eq = hull.equations
        return RigVolume(normals=eq[:, :3].copy(), offsets=eq[:, 3].copy(), up=up, floor=float(floor))

    def outside(self, points: np.ndarray) -> np.ndarray:
        """(K,) how far (metres) each point (K,3) lies outside the volume (0 inside or within
        :data:`TOLERANCE_M` of its surface)."""
        pts = np.atleast_2d(np.asarray(points, dtype=np.float64))
        d = (pts @ self.normals.T + self.offsets[None]).max(axis=1)
        return np.where(d > TOLERANCE_M, d, 0.0)

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(K,) bool: the points are inside (see :meth:`outside`)."""
        return self.outside(points) == 0.0

    def height_above_floor(self, points: np.ndarray) -> np.ndarray:
        """(K,) height of each point above the floor (metres)."""
        return np.atleast_2d(np.asarray(points, dtype=np.float64)) @ self.up - self.floor

    def pull_inside(self, points: np.ndarray, toward: np.ndarray, *, steps: int = 30) -> np.ndarray:
        """(K,3) the points, each one outside moved along the line to ``toward`` (3,), a point inside, until it
        is inside (bisection); points inside are returned unchanged."""
        pts = np.atleast_2d(np.asarray(points, dtype=np.float64)).copy()
        toward = np.asarray(toward, dtype=np.float64)
        for k in np.flatnonzero(self.outside(pts) > 0):
            lo, hi = 0.0, 1.0   # fraction of the way to ``toward``: hi is inside
            for _ in range(steps):
                mid = 0.5 * (lo + hi)
                if self.outside(pts[k] + mid * (toward - pts[k]))[0] > 0:
                    lo = mid
                else:
                    hi = mid
            pts[k] = pts[k] + hi * (toward - pts[k])
        return pts
