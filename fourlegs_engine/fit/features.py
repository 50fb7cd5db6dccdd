"""Initial points from feature matches triangulated with the known cameras (needs OpenCV).

* SIFT keypoints and descriptors in every training view.
* Each camera is matched with its nearest cameras that look the same way: mutual nearest descriptors
  that pass Lowe's ratio test and lie within ``epipolar_px`` of the epipolar line given by the
  calibration (no pose is estimated: the cameras are known).
* Every surviving match is triangulated with ``cv2.triangulatePoints`` from the two calibrated
  projection matrices and kept when it lies in front of both cameras, reprojects within
  ``reprojection_px`` in both and sees the point under at least ``min_angle_deg`` of parallax.
* Matches sharing a keypoint form a track. Per track, the candidate point that reprojects within
  ``reprojection_px`` into the most distinct views wins; a track is kept when at least ``min_views``
  views agree on it, and its point is re-solved by linear least squares over those views.
* Colour: median over the agreeing views of the pixel the point projects to. Foreground: the
  majority of those views' masks (every point is foreground without masks). Scale: the root mean
  square distance to the three nearest points (as in 3DGS), clipped to 0.5–20 pixel footprints.

Coordinates follow :class:`~fourlegs_engine.scene.camera.Camera`: pixel centres at +0.5, so OpenCV
keypoints (pixel centres at integers) are shifted by half a pixel.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import InputError
from ..scene.camera import Camera


@dataclass(frozen=True)
class FeatureOptions:
    """Knobs of :func:`feature_cloud`.

    Attributes:
        max_features: SIFT keypoints kept per view (strongest first).
        contrast_threshold: SIFT's contrast threshold (lower finds more keypoints in dim, flat regions).
        neighbors: cameras each camera is matched with (nearest centres among those within
            ``max_view_angle_deg`` of its viewing direction).
        ratio: Lowe's ratio test threshold.
        epipolar_px: largest distance (pixels) of a match from its epipolar line, both ways.
        reprojection_px: largest reprojection error (pixels) of an agreeing view.
        min_views: distinct views that must agree on a track.
        min_angle_deg: smallest parallax angle of a triangulated pair.
        max_view_angle_deg: largest angle between two matched cameras' viewing directions.
        upsample: images are enlarged by this factor before detection (keypoints are scaled back).
    """

    max_features: int = 8000
    contrast_threshold: float = 0.01
    neighbors: int = 6
    ratio: float = 0.85
    epipolar_px: float = 1.5
    reprojection_px: float = 1.5
    min_views: int = 3
    min_angle_deg: float = 1.0
    max_view_angle_deg: float = 70.0
    upsample: int = 2


@dataclass
class Triangulated:
    """Triangulated tracks.

    Attributes:
        points: (M,3) float64 world positions.
        inliers: (M,V) bool, the views that agree on each point (reprojection within tolerance).
        errors: (M,) mean reprojection error (pixels) over the agreeing views.
    """

    points: np.ndarray
    inliers: np.ndarray
    errors: np.ndarray


def require_cv2() -> Any:
    """The ``cv2`` module, or one clear :class:`InputError` when OpenCV is not installed."""
    try:
        import cv2
    except ImportError:
        raise InputError("the 'features' initialisation needs OpenCV, which is not installed: "
                         "pip install 'fourlegs[fit-features]' (or opencv-python-headless)", field="init") from None
    return cv2


def projection_matrix(camera: Camera) -> np.ndarray:
    """(3,4) float64 ``K [R|t]``, mapping homogeneous world points to the camera's pixel coordinates."""
    return camera.K @ camera.w2c[:3, :4]


def fundamental_matrix(cam_a: Camera, cam_b: Camera) -> np.ndarray:
    """(3,3) F with ``x_bᵀ F x_a = 0`` for the pixels x_a, x_b (homogeneous) of one world point."""
    Ra, ta = cam_a.w2c[:3, :3], cam_a.w2c[:3, 3]
    Rb, tb = cam_b.w2c[:3, :3], cam_b.w2c[:3, 3]
    R = Rb @ Ra.T
    t = tb - R @ ta
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return np.linalg.inv(cam_b.K).T @ tx @ R @ np.linalg.inv(cam_a.K)


def neighbor_pairs(cameras: list[Camera], neighbors: int, max_view_angle_deg: float) -> list[tuple[int, int]]:
    """Sorted unique pairs (i, j), i < j: every camera with its ``neighbors`` nearest cameras (by centre)
    whose viewing direction is within ``max_view_angle_deg`` of its own."""
    centers = np.stack([c.center for c in cameras])
    forwards = np.stack([c.forward / np.linalg.norm(c.forward) for c in cameras])
    cos_max = np.cos(np.radians(max_view_angle_deg))
    pairs = set()
    for i in range(len(cameras)):
        dist = np.linalg.norm(centers - centers[i], axis=1)
        ok = (forwards @ forwards[i] >= cos_max) & (np.arange(len(cameras)) != i)
        for j in [j for j in np.argsort(dist, kind="stable") if ok[j]][:neighbors]:
            pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)


def detect_features(images: list[np.ndarray], options: FeatureOptions) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """SIFT in every image.

    Args:
        images: V arrays (h,w,3) RGB in [0,1].
    Returns:
        keypoints: V arrays (n_v,2) float64 pixel coordinates (centres at +0.5);
        descriptors: V arrays (n_v,128) float32.
    """
    cv2 = require_cv2()
    sift = cv2.SIFT_create(nfeatures=options.max_features, contrastThreshold=options.contrast_threshold)
    keypoints, descriptors = [], []
    for image in images:
        gray = (np.clip(np.asarray(image, np.float64).mean(-1), 0, 1) * 255).round().astype(np.uint8)
        s = max(1, int(options.upsample))
        if s > 1:
            gray = cv2.resize(gray, (gray.shape[1] * s, gray.shape[0] * s), interpolation=cv2.INTER_CUBIC)
        kps, des = sift.detectAndCompute(gray, None)
        if des is None or not kps:
            keypoints.append(np.zeros((0, 2)))
            descriptors.append(np.zeros((0, 128), np.float32))
            continue
        # an upsampled pixel centre at integer k lies at (k + 0.5)/s in the original pixel grid
        uv = (np.array([kp.pt for kp in kps], np.float64) + 0.5) / s
        keypoints.append(uv)
        descriptors.append(des.astype(np.float32))
    return keypoints, descriptors


def match_pair(cam_a: Camera, cam_b: Camera, uv_a: np.ndarray, des_a: np.ndarray, uv_b: np.ndarray,
               des_b: np.ndarray, options: FeatureOptions) -> np.ndarray:
    """(m,2) int64 keypoint index pairs (a, b): mutual best descriptor matches passing the ratio test
    and within ``epipolar_px`` of each other's epipolar lines."""
    cv2 = require_cv2()
    if len(des_a) < 2 or len(des_b) < 2:
        return np.zeros((0, 2), np.int64)
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    fwd = matcher.knnMatch(des_a, des_b, k=2)
    back = matcher.match(des_b, des_a)
    best_back = np.full(len(des_b), -1, np.int64)
    for m in back:
        best_back[m.queryIdx] = m.trainIdx
    pairs = [(m[0].queryIdx, m[0].trainIdx) for m in fwd
             if len(m) == 2 and m[0].distance < options.ratio * m[1].distance
             and best_back[m[0].trainIdx] == m[0].queryIdx]
    if not pairs:
        return np.zeros((0, 2), np.int64)
    idx = np.asarray(pairs, np.int64)
    F = fundamental_matrix(cam_a, cam_b)
    xa = np.concatenate([uv_a[idx[:, 0]], np.ones((len(idx), 1))], 1)
    xb = np.concatenate([uv_b[idx[:, 1]], np.ones((len(idx), 1))], 1)
    line_b = xa @ F.T  # epipolar lines in b of the points of a
    line_a = xb @ F
    d_b = np.abs((line_b * xb).sum(1)) / np.maximum(np.linalg.norm(line_b[:, :2], axis=1), 1e-12)
    d_a = np.abs((line_a * xa).sum(1)) / np.maximum(np.linalg.norm(line_a[:, :2], axis=1), 1e-12)
    return idx[(d_a <= options.epipolar_px) & (d_b <= options.epipolar_px)]


def _reproject(P: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """P (K,3,4) or (3,4), X (K,3) -> uv (K,2), depth (K,) (the homogeneous w, camera z for K [R|t])."""
    Xh = np.concatenate([X, np.ones((X.shape[0], 1))], 1)
    x = np.einsum("kij,kj->ki", P, Xh) if P.ndim == 3 else Xh @ P.T
    w = x[:, 2]
    safe = np.where(np.abs(w) < 1e-12, 1e-12, w)
    return x[:, :2] / safe[:, None], w


def triangulate_matches(cameras: list[Camera], keypoints: list[np.ndarray], matches: dict[tuple[int, int], np.ndarray],
                        *, reprojection_px: float = 1.5, min_views: int = 3,
                        min_angle_deg: float = 1.0) -> Triangulated:
    """Triangulate pairwise matches into multi-view consistent points.

    Args:
        cameras: V calibrated cameras. keypoints: V arrays (n_v,2) pixel coordinates (centres at +0.5).
        matches: (i, j) -> (m,2) int keypoint index pairs between views i and j.
        reprojection_px: largest reprojection error of an agreeing view (pixels).
        min_views: distinct agreeing views needed to keep a track (2 keeps well-posed pairs).
        min_angle_deg: smallest parallax angle of a triangulated pair.
    Returns:
        :class:`Triangulated` (M points; empty arrays when nothing survives).
    """
    V = len(cameras)
    P = np.stack([projection_matrix(c) for c in cameras])
    offsets = np.concatenate([[0], np.cumsum([len(k) for k in keypoints])]).astype(np.int64)
    empty = Triangulated(np.zeros((0, 3)), np.zeros((0, V), bool), np.zeros(0))
    cand, ga, gb = _pair_candidates(cameras, keypoints, matches, P, offsets, reprojection_px, min_angle_deg)
    if not len(cand):
        return empty
    observations = _Observations(
        uv=np.concatenate([np.asarray(k, np.float64).reshape(-1, 2) for k in keypoints] + [np.zeros((0, 2))]),
        view=np.repeat(np.arange(V), np.diff(offsets)))
    chosen = _best_candidate_per_track(cand, ga, gb, observations, P, reprojection_px, min_views)
    if chosen is None:
        return empty
    return _refined_points(*chosen, observations, P, reprojection_px)


@dataclass
class _Observations:
    """Every keypoint of every view, flattened: pixel coordinates (K,2) and view index (K,)."""

    uv: np.ndarray
    view: np.ndarray


def _pair_candidates(cameras: list[Camera], keypoints: list[np.ndarray], matches: dict[tuple[int, int], np.ndarray],
                     P: np.ndarray, offsets: np.ndarray, reprojection_px: float, min_angle_deg: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points triangulated from each matched pair that both views see in front, within ``reprojection_px``
    and with enough parallax: (M,3) points and the flat keypoint indices (M,), (M,) of the two views."""
    cv2 = require_cv2()
    centers = np.stack([c.center for c in cameras])
    cand_pts, cand_ga, cand_gb = [np.zeros((0, 3))], [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    cos_min = np.cos(np.radians(min_angle_deg))
    for (i, j), idx in matches.items():
        idx = np.asarray(idx, np.int64).reshape(-1, 2)
        if not len(idx):
            continue
        xa, xb = keypoints[i][idx[:, 0]], keypoints[j][idx[:, 1]]
        Xh = cv2.triangulatePoints(P[i], P[j], np.ascontiguousarray(xa.T), np.ascontiguousarray(xb.T)).T
        with np.errstate(divide="ignore", invalid="ignore"):
            X = Xh[:, :3] / Xh[:, 3:4]
        ok = np.isfinite(X).all(1)
        X = np.where(ok[:, None], X, 0.0)
        for v, x in ((i, xa), (j, xb)):
            uv, z = _reproject(P[v], X)
            ok &= (z > cameras[v].near) & (np.linalg.norm(uv - x, axis=1) <= reprojection_px)
        ra, rb = X - centers[i], X - centers[j]
        cos = (ra * rb).sum(1) / np.maximum(np.linalg.norm(ra, axis=1) * np.linalg.norm(rb, axis=1), 1e-12)
        ok &= cos <= cos_min
        cand_pts.append(X[ok])
        cand_ga.append(offsets[i] + idx[ok, 0])
        cand_gb.append(offsets[j] + idx[ok, 1])
    return np.concatenate(cand_pts), np.concatenate(cand_ga), np.concatenate(cand_gb)


def _best_candidate_per_track(cand: np.ndarray, ga: np.ndarray, gb: np.ndarray, obs_all: _Observations,
                              P: np.ndarray, reprojection_px: float, min_views: int) -> tuple | None:
    """Tracks are the connected components of the matched keypoints; every candidate is checked against
    every observation of its track (one vote per view: its best observation) and each track keeps the
    candidate most views agree with (ties: the smaller mean error). None when no track has ``min_views``.

    Returns:
        (candidates (C,3), the kept ones (B,) into them, votes (W,) into the pairs, pair candidate (Q,),
        pair view (Q,), pair observation (Q,)).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    V = P.shape[0]
    n_kp = int(obs_all.uv.shape[0])
    graph = coo_matrix((np.ones(len(ga)), (ga, gb)), shape=(n_kp, n_kp))
    _, label = connected_components(graph, directed=False)
    obs = np.unique(np.concatenate([ga, gb]))
    obs_track = label[obs]
    order = np.argsort(obs_track, kind="stable")
    obs, obs_track = obs[order], obs_track[order]
    tracks, starts, counts = np.unique(obs_track, return_index=True, return_counts=True)
    # a chain of wrong matches can join many keypoints: such tracks are dropped
    big = counts > 2 * V
    cand_track = label[ga]
    pos = np.searchsorted(tracks, cand_track)
    keep_c = ~big[pos]
    cand, cand_track, pos = cand[keep_c], cand_track[keep_c], pos[keep_c]
    if not len(cand):
        return None
    # every candidate against every observation of its track
    n_pairs = counts[pos]
    pair_cand = np.repeat(np.arange(len(cand)), n_pairs)
    within = np.arange(n_pairs.sum()) - np.repeat(np.cumsum(n_pairs) - n_pairs, n_pairs)
    pair_obs = obs[starts[pos][pair_cand] + within]
    pair_view = obs_all.view[pair_obs]
    uv, z = _reproject(P[pair_view], cand[pair_cand])
    err = np.linalg.norm(uv - obs_all.uv[pair_obs], axis=1)
    good = (z > 0) & (err <= reprojection_px)
    # one vote per (candidate, view): the view's best observation
    gi = np.nonzero(good)[0]
    key = pair_cand[gi] * V + pair_view[gi]
    o = np.lexsort((err[gi], key))
    key_s = key[o]
    first = np.ones(len(key_s), bool)
    first[1:] = key_s[1:] != key_s[:-1]
    vote = gi[o][first]
    n_views = np.bincount(pair_cand[vote], minlength=len(cand))
    err_sum = np.bincount(pair_cand[vote], weights=err[vote], minlength=len(cand))
    mean_err = err_sum / np.maximum(n_views, 1)
    best_order = np.lexsort((mean_err, -n_views, cand_track))
    first_of_track = np.ones(len(best_order), bool)
    first_of_track[1:] = cand_track[best_order][1:] != cand_track[best_order][:-1]
    best = best_order[first_of_track]
    best = best[n_views[best] >= max(2, min_views)]
    if not len(best):
        return None
    return cand, best, vote, pair_cand, pair_view, pair_obs


def _refined_points(cand: np.ndarray, best: np.ndarray, vote: np.ndarray, pair_cand: np.ndarray,
                    pair_view: np.ndarray, pair_obs: np.ndarray, obs_all: _Observations, P: np.ndarray,
                    reprojection_px: float) -> Triangulated:
    """A linear multi-view re-solve of each kept candidate over the views that voted for it; the refined
    point where it still agrees with every one of them, else the candidate."""
    V = P.shape[0]
    rank = np.full(len(cand), -1)
    rank[best] = np.arange(len(best))
    sel = vote[rank[pair_cand[vote]] >= 0]
    row_t, row_v, row_uv = rank[pair_cand[sel]], pair_view[sel], obs_all.uv[pair_obs[sel]]
    A = np.zeros((len(best), V, 2, 4))  # rows of views that did not vote stay zero
    A[row_t, row_v, 0] = row_uv[:, :1] * P[row_v, 2] - P[row_v, 0]
    A[row_t, row_v, 1] = row_uv[:, 1:] * P[row_v, 2] - P[row_v, 1]
    A = A.reshape(len(best), 2 * V, 4)
    A /= np.maximum(np.linalg.norm(A, axis=2, keepdims=True), 1e-12)
    _, _, vt = np.linalg.svd(A, full_matrices=False)
    h = vt[:, -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        refined = h[:, :3] / h[:, 3:4]
    inliers = np.zeros((len(best), V), bool)
    inliers[row_t, row_v] = True
    ok = np.isfinite(refined).all(1)
    r_uv, r_z = _reproject(P[row_v], np.where(ok[:, None], refined, 0.0)[row_t])
    bad_row = (r_z <= 0) | (np.linalg.norm(r_uv - row_uv, axis=1) > reprojection_px)
    ok &= np.bincount(row_t, weights=bad_row, minlength=len(best)) == 0
    points = np.where(ok[:, None], refined, cand[best])
    f_uv, _ = _reproject(P[row_v], points[row_t])
    f_err = np.linalg.norm(f_uv - row_uv, axis=1)
    errors = np.bincount(row_t, weights=f_err, minlength=len(best)) / inliers.sum(1)
    return Triangulated(points=points, inliers=inliers, errors=errors)


def feature_cloud(cameras: list[Camera], images: list[np.ndarray], masks: list[np.ndarray] | None,
                  options: FeatureOptions | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Triangulated feature points with colours, scales and the foreground flag (module docstring).

    Args:
        cameras: V cameras at the images' resolution. images: V arrays (h,w,3) in [0,1].
        masks: V arrays (h,w) in [0,1] or None.
    Returns:
        points (M,3) float64, colors (M,3) float32, scales (M,) float64 (metres), foreground (M,) bool.
    """
    opts = options or FeatureOptions()
    keypoints, descriptors = detect_features(images, opts)
    matches = {}
    for i, j in neighbor_pairs(cameras, opts.neighbors, opts.max_view_angle_deg):
        matches[(i, j)] = match_pair(cameras[i], cameras[j], keypoints[i], descriptors[i], keypoints[j],
                                     descriptors[j], opts)
    tri = triangulate_matches(cameras, keypoints, matches, reprojection_px=opts.reprojection_px,
                              min_views=opts.min_views, min_angle_deg=opts.min_angle_deg)
    M, V = tri.inliers.shape
    if M == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.float32), np.zeros(0), np.zeros(0, bool)
    colors = np.full((M, V, 3), np.nan, np.float32)
    fg_votes = np.zeros(M)
    footprint = np.full(M, np.inf)
    for v, (cam, image) in enumerate(zip(cameras, images)):
        rows = np.nonzero(tri.inliers[:, v])[0]
        if not len(rows):
            continue
        uv, z = cam.project(tri.points[rows])
        px = np.clip(np.floor(uv[:, 0]).astype(np.int64), 0, cam.width - 1)
        py = np.clip(np.floor(uv[:, 1]).astype(np.int64), 0, cam.height - 1)
        colors[rows, v] = image[py, px]
        if masks is not None:
            fg_votes[rows] += masks[v][py, px] >= 0.5
        footprint[rows] = np.minimum(footprint[rows], z / cam.fx)
    color = np.nanmedian(colors, axis=1).astype(np.float32)
    n_views = tri.inliers.sum(1)
    foreground = fg_votes * 2 > n_views if masks is not None else np.ones(M, bool)
    if M > 3:
        from scipy.spatial import cKDTree

        dist, _ = cKDTree(tri.points).query(tri.points, k=4)
        scales = np.sqrt((dist[:, 1:] ** 2).mean(1))
    else:
        scales = 5 * footprint
    scales = np.clip(scales, 0.5 * footprint, 20 * footprint)
    return tri.points, np.clip(color, 0, 1), scales, foreground
