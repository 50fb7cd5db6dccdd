"""The separate things a query matches at one timestep: the relevant Gaussians split into instances.

Two people 2.8 m apart, a ball and a blob of floor the 2D evidence spilled onto: each is an
instance, a 3D connected component of the relevant Gaussians (centres closer than 1.5 times their
median 3-sigma size are linked). Instances are ranked by relevancy mass (the sum of the members'
relevancy); when the scene marks its foreground Gaussians, instances that are mostly background
(floor and wall patches) rank after every foreground one, since the moving things are what a
highlight is about.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

#: Mahalanobis radius of a Gaussian's extent (3 sigma).
SIGMAS = 3.0


@dataclass(frozen=True)
class Instance:
    """One connected group of relevant Gaussians.

    Attributes:
        members: (N,) bool over the scene's Gaussians.
        centre: (3,) middle of the per-axis percentile box of the members' centres.
        radius: distance from ``centre`` enclosing the robust share of the members plus their 3-sigma size.
        height: extent along the scene's up (robust percentiles of the centres plus 2 sigma at both ends).
        mass: sum of the members' relevancy.
        foreground_share: share of the members the scene marks as foreground (None: not known).
    """

    members: np.ndarray
    centre: np.ndarray
    radius: float
    height: float
    mass: float
    foreground_share: Optional[float] = None

    @property
    def count(self) -> int:
        return int(self.members.sum())

    def to_dict(self) -> dict:
        return {"centre": [float(v) for v in self.centre], "radius": float(self.radius),
                "height": float(self.height), "mass": float(self.mass), "gaussians": self.count,
                "foreground_share": None if self.foreground_share is None else float(self.foreground_share)}


def describe(means: np.ndarray, scales: np.ndarray, idx: np.ndarray, up: np.ndarray, *,
             percentile: float = 95.0) -> tuple[np.ndarray, float, float]:
    """(centre (3,), radius, height along ``up``) of the Gaussians ``idx`` (robust percentiles).

    means (N,3), scales (N,3) standard deviations."""
    pts = means[idx]
    size = scales[idx].max(axis=1)
    lo, hi = np.percentile(pts, 100.0 - percentile, axis=0), np.percentile(pts, percentile, axis=0)
    centre = 0.5 * (lo + hi)
    reach = np.linalg.norm(pts - centre, axis=1) + np.minimum(SIGMAS * size, np.percentile(SIGMAS * size, 95.0))
    radius = float(np.percentile(reach, percentile))
    h = pts @ (up / np.linalg.norm(up))
    pad = 2.0 * float(np.median(size))
    height = float(np.percentile(h, percentile) - np.percentile(h, 100.0 - percentile)) + 2.0 * pad
    return centre, max(radius, 1e-3), max(height, 1e-3)


def split_instances(means: np.ndarray, relevancy: np.ndarray, scales: np.ndarray, members: np.ndarray,
                    up: np.ndarray, *, foreground: Optional[np.ndarray] = None, min_members: int = 8,
                    min_share: float = 0.01) -> list[Instance]:
    """The instances among the Gaussians ``members`` (N,) bool, best first.

    Components smaller than ``max(min_members, min_share * members.sum())`` are dropped (stray
    relevant splats); when none is that large, all relevant Gaussians form one instance.

    Args:
        means: (N,3) centres; relevancy: (N,) in [0,1]; scales: (N,3) standard deviations;
        up: (3,) the scene's up; foreground: (N,) bool or None.
    """
    means = np.asarray(means, dtype=np.float64)
    scales = np.asarray(scales, dtype=np.float64)
    rel = np.nan_to_num(np.asarray(relevancy, dtype=np.float64), nan=0.0)
    idx = np.flatnonzero(members)
    if idx.size == 0:
        return []
    link = 1.5 * SIGMAS * float(np.median(scales[idx].max(axis=1)))
    pairs = cKDTree(means[idx]).query_pairs(link, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(idx.size, idx.size))
    _, labels = connected_components(graph, directed=False)
    counts = np.bincount(labels)
    keep = np.flatnonzero(counts >= max(min_members, min_share * idx.size))
    groups = [idx[labels == k] for k in keep] if keep.size else [idx]
    fg = None if foreground is None else np.asarray(foreground, dtype=bool).reshape(-1)
    out = []
    for group in groups:
        mask = np.zeros(len(means), dtype=bool)
        mask[group] = True
        centre, radius, height = describe(means, scales, group, up)
        share = None if fg is None or fg.shape[0] != len(means) else float(fg[group].mean())
        out.append(Instance(mask, centre, radius, height, float(rel[group].sum()), share))
    out.sort(key=lambda i: (-(i.foreground_share is None or i.foreground_share >= 0.5), -i.mass))
    return out
