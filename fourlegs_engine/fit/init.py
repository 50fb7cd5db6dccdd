"""Initial Gaussians from the capture itself (no point cloud is shipped with the data).

* Foreground: a visual hull carved on a voxel grid from the foreground masks and the calibration; the
  surface voxels become Gaussians coloured by the median of the pixels they project to.
* Background: a depth-less proxy of the studio. The cameras are mounted on a dome, so the walls they
  see lie near the sphere through the camera centres; the floor is the plane under the lowest hull
  voxels. Background pixels (outside the masks) on a regular stride are cast onto the nearer of the
  two surfaces and become Gaussians the size of their pixel footprint.
Without masks there is no hull: every Gaussian comes from the proxy and counts as foreground.

The ``method`` of :func:`initial_cloud` chooses the sources: "hull" (the two above), "features"
(feature matches triangulated with the known cameras alone, :mod:`.features`, needs OpenCV) or
"hull+features" (both; the triangulated points take their share of the per-class caps first).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..scene.camera import Camera

INIT_METHODS = ("hull", "features", "hull+features")


@dataclass
class InitialCloud:
    """Points to start the fit from.

    Attributes:
        points: (N,3) world positions. colors: (N,3) RGB in [0,1]. scales: (N,) isotropic std (m).
        foreground: (N,) bool.
        floor_y: world y of the floor plane (y points down in Panoptic's world), or None.
        dome_center: (3,), dome_radius: the sphere fitted through the camera centres.
    """

    points: np.ndarray
    colors: np.ndarray
    scales: np.ndarray
    foreground: np.ndarray
    floor_y: float | None
    dome_center: np.ndarray
    dome_radius: float


def fit_sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares sphere through (M,3) points: |p|² = 2 p·c + (r² − |c|²) is linear in c and r²−|c|²."""
    A = np.concatenate([2 * points, np.ones((points.shape[0], 1))], axis=1)
    b = (points ** 2).sum(1)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    center = sol[:3]
    radius = float(np.sqrt(max(sol[3] + center @ center, 1e-12)))
    return center, radius


def look_at_point(cameras: list[Camera]) -> np.ndarray:
    """(3,) the point closest (least squares) to every camera's optical axis."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for cam in cameras:
        d = cam.forward / np.linalg.norm(cam.forward)
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ cam.center
    return np.linalg.solve(A + 1e-9 * np.eye(3), b)


def carve_visual_hull(cameras: list[Camera], masks: list[np.ndarray], images: list[np.ndarray], *,
                      voxel: float, half_extent: float, center: np.ndarray, min_views: int = 4,
                      max_misses: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Surface voxels of the visual hull.

    Args:
        cameras: C cameras (at the masks' resolution). masks: C arrays (h,w) in [0,1].
        images: C arrays (h,w,3) for the colours.
        voxel: voxel side (m). half_extent: half side of the carved cube (m) around ``center``.
        min_views: a voxel must project inside at least this many images.
        max_misses: it may fall outside the mask in at most this many of them (mask errors).
    Returns:
        points (M,3) voxel centres on the hull surface, colors (M,3) median pixel colour over views.
    """
    coarse_factor = 4
    n = max(2, int(np.ceil(2 * half_extent / (voxel * coarse_factor)))) * coarse_factor
    half_extent = n * voxel / 2
    nc = n // coarse_factor
    # coarse pass on voxels coarse_factor times larger (a cell is kept when its centre or any
    # neighbour's survives), then the fine grid only inside the kept cells
    axis_c = (np.arange(nc) + 0.5) * voxel * coarse_factor - half_extent
    pts_c = np.stack(np.meshgrid(axis_c, axis_c, axis_c, indexing="ij"), -1).reshape(-1, 3) + center
    occ_c = _carve(pts_c, cameras, masks, min_views, max_misses + 1).reshape(nc, nc, nc)
    grown = occ_c.copy()
    for axis_i in range(3):
        for shift in (-1, 1):
            grown |= np.roll(occ_c, shift, axis=axis_i)
    cells = np.argwhere(grown)
    sub = np.stack(np.meshgrid(*[np.arange(coarse_factor)] * 3, indexing="ij"), -1).reshape(-1, 3)
    fine_idx = (cells[:, None, :] * coarse_factor + sub[None]).reshape(-1, 3)
    occ = np.zeros((n, n, n), bool)
    if fine_idx.shape[0]:
        pts = (fine_idx + 0.5) * voxel - half_extent + center
        keep = _carve(pts, cameras, masks, min_views, max_misses)
        occ[tuple(fine_idx[keep].T)] = True
    padded = np.pad(occ, 1)
    interior = occ.copy()
    for axis_i in range(3):
        for shift in (-1, 1):
            interior &= np.roll(padded, shift, axis=axis_i)[1:-1, 1:-1, 1:-1]
    # the surface voxels' centres straight from their indices (the whole grid's centres would be n^3 points)
    points = (np.argwhere(occ & ~interior) + 0.5) * voxel - half_extent + center
    colors = np.zeros((points.shape[0], len(cameras), 3), np.float32)
    valid = np.zeros((points.shape[0], len(cameras)), bool)
    for i, (cam, image) in enumerate(zip(cameras, images)):
        uv, z = cam.project(points)
        px = np.clip(np.floor(uv[:, 0]).astype(np.int64), 0, cam.width - 1)
        py = np.clip(np.floor(uv[:, 1]).astype(np.int64), 0, cam.height - 1)
        colors[:, i] = image[py, px]
        valid[:, i] = (z > cam.near) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    colors = np.where(valid[..., None], colors, np.nan)
    with np.errstate(all="ignore"):
        med = np.nanmedian(colors, axis=1) if points.shape[0] else np.zeros((0, 3), np.float32)
    return points, np.nan_to_num(med, nan=0.5).astype(np.float32)


def _carve(pts: np.ndarray, cameras: list[Camera], masks: list[np.ndarray], min_views: int,
           max_misses: int) -> np.ndarray:
    """(M,) bool: the points inside at least ``min_views`` images and outside the mask in at most
    ``max_misses`` of them."""
    inside = np.zeros(pts.shape[0], np.int16)
    misses = np.zeros(pts.shape[0], np.int16)
    for cam, mask in zip(cameras, masks):
        uv, z = cam.project(pts)
        px = np.floor(uv[:, 0]).astype(np.int64)
        py = np.floor(uv[:, 1]).astype(np.int64)
        ok = (z > cam.near) & (px >= 0) & (px < cam.width) & (py >= 0) & (py < cam.height)
        hit = np.zeros(pts.shape[0], bool)
        hit[ok] = mask[py[ok], px[ok]] >= 0.5
        inside += ok
        misses += ok & ~hit
    return (inside >= min_views) & (misses <= max_misses)


def background_proxy(cameras: list[Camera], images: list[np.ndarray], masks: list[np.ndarray] | None, *,
                     stride: int, dome_center: np.ndarray, dome_radius: float, floor_y: float | None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Background pixels cast onto the dome sphere / floor plane.

    Returns:
        points (M,3), colors (M,3), scales (M,) (pixel footprint at the hit, metres).
    """
    pts_all, col_all, scl_all = [], [], []
    for i, (cam, image) in enumerate(zip(cameras, images)):
        ys, xs = np.mgrid[stride // 2:cam.height:stride, stride // 2:cam.width:stride]
        xs, ys = xs.reshape(-1), ys.reshape(-1)
        if masks is not None:
            keep = masks[i][ys, xs] < 0.5
            xs, ys = xs[keep], ys[keep]
        uv = np.stack([xs + 0.5, ys + 0.5], 1)
        origin = cam.center
        d = cam.unproject(uv, np.ones(len(xs))) - origin
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        # ray–sphere: |o + s d − c|² = r²; o is inside the dome, so take the positive root
        oc = origin - dome_center
        bq = d @ oc
        disc = bq ** 2 - (oc @ oc - dome_radius ** 2)
        s = -bq + np.sqrt(np.maximum(disc, 0.0))
        if floor_y is not None:
            with np.errstate(divide="ignore", invalid="ignore"):
                s_floor = (floor_y - origin[1]) / d[:, 1]
            s = np.where((s_floor > 0) & (s_floor < s), s_floor, s)
        s = np.maximum(s, 2 * cam.near)
        pts_all.append(origin + s[:, None] * d)
        col_all.append(image[ys, xs])
        z = s * (d @ cam.forward)
        scl_all.append(0.5 * stride * z / cam.fx)
    return (np.concatenate(pts_all), np.concatenate(col_all).astype(np.float32),
            np.concatenate(scl_all))


def initial_cloud(cameras: list[Camera], images: list[np.ndarray], masks: list[np.ndarray] | None, *,
                  voxel: float = 0.02, hull_half_extent: float = 2.5, bg_stride: int = 6,
                  max_foreground: int | None = None, max_background: int | None = None,
                  seed: int = 0, method: str = "hull", feature_options=None) -> InitialCloud:
    """The initial cloud (see the module docstring for the methods).

    Args:
        cameras, images, masks: C cameras at the images' resolution, C arrays (h,w,3) in [0,1], C masks
            (h,w) in [0,1] or None.
        voxel, hull_half_extent: hull voxel side and half extent (m). bg_stride: background proxy stride (px).
        max_foreground, max_background: caps on the foreground / background points (random subsets;
            triangulated points are kept before hull / proxy points).
        method: "hull", "features" or "hull+features".
        feature_options: :class:`~.features.FeatureOptions` (None: defaults).
    """
    if method not in INIT_METHODS:
        raise InputError(f"must be one of {', '.join(INIT_METHODS)}, got {method!r}", field="init")
    rng = np.random.default_rng(seed)
    centers = np.stack([c.center for c in cameras])
    dome_center, dome_radius = fit_sphere(centers) if len(cameras) >= 4 else (centers.mean(0), 5.0)
    empty = (np.zeros((0, 3)), np.zeros((0, 3), np.float32), np.zeros(0))
    feat_fg = feat_bg = empty
    if method != "hull":
        from .features import feature_cloud, require_cv2

        require_cv2()
        f_pts, f_col, f_scl, f_fg = feature_cloud(cameras, images, masks, feature_options)
        feat_fg = _cap(rng, max_foreground, f_pts[f_fg], f_col[f_fg], f_scl[f_fg])
        feat_bg = _cap(rng, max_background, f_pts[~f_fg], f_col[~f_fg], f_scl[~f_fg])
    hull = proxy = empty
    floor_y = None
    if method != "features":
        if masks is not None:
            target = look_at_point(cameras)
            fg_pts, fg_col = carve_visual_hull(cameras, masks, images, voxel=voxel, half_extent=hull_half_extent,
                                               center=target, min_views=min(4, len(cameras)),
                                               max_misses=1 if len(cameras) >= 6 else 0)
            if fg_pts.shape[0]:
                floor_y = float(np.quantile(fg_pts[:, 1], 0.995)) + voxel
            hull = _cap(rng, _room(max_foreground, feat_fg), fg_pts, fg_col, np.full(fg_pts.shape[0], voxel * 0.6))
        proxy = background_proxy(cameras, images, masks, stride=bg_stride, dome_center=dome_center,
                                 dome_radius=dome_radius, floor_y=floor_y)
        proxy = _cap(rng, _room(max_background, feat_bg), *proxy)
    elif masks is not None and feat_fg[0].shape[0]:
        floor_y = float(np.quantile(feat_fg[0][:, 1], 0.995)) + voxel
    if method == "hull+features":
        feat_fg, feat_bg = _fit_scales_among(feat_fg, hull, proxy), _fit_scales_among(feat_bg, hull, proxy)
    parts = [hull, feat_fg, proxy, feat_bg]
    points = np.concatenate([p[0] for p in parts])
    colors = np.concatenate([p[1] for p in parts]).astype(np.float32)
    scales = np.concatenate([p[2] for p in parts])
    fg = np.concatenate([np.full(len(p[0]), i < 2) for i, p in enumerate(parts)]).astype(bool)
    if masks is None:
        fg[:] = True
    return InitialCloud(points=points, colors=colors, scales=scales, foreground=fg, floor_y=floor_y,
                        dome_center=dome_center, dome_radius=dome_radius)


def _fit_scales_among(points: tuple[np.ndarray, ...], *others: tuple[np.ndarray, ...]) -> tuple[np.ndarray, ...]:
    """``points`` (pts, colors, scales) with each scale no larger than the root mean square distance to
    its three nearest points among ``points`` and ``others`` together: a sparse feature point's own
    spacing would make it a large splat in front of the denser hull and proxy points."""
    pts, col, scl = points
    cloud = np.concatenate([pts] + [o[0] for o in others])
    if pts.shape[0] == 0 or cloud.shape[0] < 5:
        return points
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(cloud).query(pts, k=4)
    return pts, col, np.minimum(scl, np.sqrt((dist[:, 1:] ** 2).mean(1)))


def _room(limit: int | None, taken: tuple[np.ndarray, ...]) -> int | None:
    return None if limit is None else max(0, limit - taken[0].shape[0])


def _cap(rng, limit, *arrays):
    n = arrays[0].shape[0]
    if limit is None or n <= limit:
        return arrays
    keep = np.sort(rng.choice(n, size=limit, replace=False))
    return tuple(a[keep] for a in arrays)
