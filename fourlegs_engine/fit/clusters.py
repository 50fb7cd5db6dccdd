"""Rigid parts of the foreground for the part steps of a later timestep (:func:`.optimize.move_parts`).

Gaussians that touch at the first timestep (a chain of k-nearest-neighbour links each at most
``LINK_FACTOR`` times the median nearest-neighbour distance) form one connected part; a part of fewer
than ``MIN_PART`` Gaussians (one inside the ball, a stray one) joins the part of its nearest neighbour
outside it; a part wider than ``max_extent`` along its principal axis is halved at
the median along that axis, recursively. A thrown ball is then one *free* part (a whole connected
component: a rigid body of its own), a person a few cut parts (head, trunk, limbs). The part steps of a
later timestep move parts rigidly (:func:`rigid_part_motion`), so all Gaussians of the ball follow it
together instead of tearing into those the image pulls and those it does not.
"""
from __future__ import annotations

import numpy as np
import torch

from ..scene.gaussians import quaternion_to_matrix
from .losses import quat_multiply

#: a kNN link joins two Gaussians when it is at most this many times the median nearest-neighbour distance
LINK_FACTOR = 4.0
#: connected parts smaller than this join their nearest neighbouring part
MIN_PART = 20


def motion_parts(points: np.ndarray, neighbors: np.ndarray, distances: np.ndarray, max_extent: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The rigid parts of F points: (F,) int64 part label (0..P−1) of each point, and (P,) bool, True
    for a free part (a whole connected component, not cut to ``max_extent``).

    Args:
        points: (F,3) positions at the first timestep.
        neighbors: (F,K) indices of each point's K nearest neighbours (K may be 0; an index ≥ F with an
            infinite distance, as scipy's cKDTree gives for a missing neighbour, is no neighbour).
        distances: (F,K) their distances.
        max_extent: the longest a part may be along its principal axis (same unit as ``points``).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = points.shape[0]
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0, bool)
    if neighbors.shape[1] and np.isfinite(distances).any():
        link = LINK_FACTOR * float(np.median(distances[:, 0]))
        valid = (neighbors >= 0) & (neighbors < n) & np.isfinite(distances)
        neighbors = np.where(valid, neighbors, np.arange(n)[:, None])  # a missing neighbour: the point itself
        keep = valid & (distances <= link)
        rows = np.repeat(np.arange(n), neighbors.shape[1])[keep.ravel()]
        cols = neighbors.ravel()[keep.ravel()]
        _, components = connected_components(coo_matrix((np.ones(rows.size, np.int8), (rows, cols)), shape=(n, n)),
                                             directed=False)
        small = np.flatnonzero(np.bincount(components)[components] < MIN_PART)
        other = components[neighbors[small]] != components[small][:, None]
        has = other.any(axis=1)
        nearest_other = neighbors[small[has], other[has].argmax(axis=1)]
        rows, cols = np.concatenate([rows, small[has]]), np.concatenate([cols, nearest_other])
        _, components = connected_components(coo_matrix((np.ones(rows.size, np.int8), (rows, cols)), shape=(n, n)),
                                             directed=False)
    else:
        components = np.zeros(n, np.int64)
    labels = np.empty(n, np.int64)
    order = np.argsort(components, kind="stable")
    pending = [(idx, True) for idx in np.split(order, np.cumsum(np.bincount(components))[:-1]) if idx.size]
    count = 0
    free = []
    while pending:
        idx, whole = pending.pop()
        part = points[idx].astype(np.float64)
        centred = part - part.mean(axis=0)
        if idx.size > 1:
            axis = np.linalg.svd(centred, full_matrices=False)[2][0]
            along = centred @ axis
            if float(along.max() - along.min()) > max_extent:
                split = along <= np.median(along)
                if split.all() or not split.any():  # ties at the median: order instead
                    split = np.zeros(idx.size, bool)
                    split[np.argsort(along, kind="stable")[: idx.size // 2]] = True
                pending.extend([(idx[split], False), (idx[~split], False)])
                continue
        labels[idx] = count
        free.append(whole)
        count += 1
    return labels, np.asarray(free, bool)


def axis_angle_quaternion(omega: torch.Tensor) -> torch.Tensor:
    """(P,4) unit quaternions (w,x,y,z) of (P,3) axis-angle vectors (finite gradient at 0)."""
    theta = torch.sqrt((omega * omega).sum(-1, keepdim=True) + 1e-24)
    half = 0.5 * theta
    return torch.cat([torch.cos(half), omega * (torch.sin(half) / theta)], dim=-1)


def rigid_part_motion(means: torch.Tensor, rotations: torch.Tensor, labels: torch.Tensor, centres: torch.Tensor,
                      translation: torch.Tensor, omega: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Move every part rigidly: rotate about its centre, then translate.

    Args:
        means: (F,3) centres, rotations: (F,4) unit quaternions, labels: (F,) part of each.
        centres: (P,3) the point each part rotates about; translation: (P,3); omega: (P,3) axis-angle.
    Returns:
        (F,3) moved centres and (F,4) unit rotations.
    """
    q = axis_angle_quaternion(omega)
    r = quaternion_to_matrix(q)[labels]
    c = centres[labels]
    moved = torch.einsum("fij,fj->fi", r, means - c) + c + translation[labels]
    return moved, torch.nn.functional.normalize(quat_multiply(q[labels], rotations), dim=-1)
