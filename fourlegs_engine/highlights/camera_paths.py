"""Camera poses and camera paths (OpenCV camera axes: x right, y down, z forward; world up is +z).

A :class:`Pose` is a camera-to-world rigid transform. Paths are lists of poses, one per output frame.
Every function here returns proper rotations (orthonormal, det +1) and finite positions for any
finite input, including the degenerate cases a highlight meets in practice: a target behind the
camera, a camera straight above its target (view direction parallel to world up), a zero orbit
radius, a camera sitting on its target.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

WORLD_UP = np.array([0.0, 0.0, 1.0])
_EPS = 1e-9


def orthonormalize(R: np.ndarray) -> np.ndarray:
    """Nearest proper rotation (3,3) to ``R`` (SVD; det forced to +1)."""
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=np.float64))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    return U @ D @ Vt


def _unit(v: np.ndarray) -> tuple[np.ndarray, float]:
    n = float(np.linalg.norm(v))
    return (v / n if n > _EPS else np.zeros_like(v)), n


@dataclass(frozen=True)
class Pose:
    """A camera pose.

    Attributes:
        position: (3,) camera centre in world coordinates (metres).
        rotation: (3,3) camera-to-world rotation; its columns are the camera's x (right), y (down) and
            z (forward) axes in world coordinates.
    """

    position: np.ndarray
    rotation: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", np.asarray(self.position, dtype=np.float64).reshape(3))
        object.__setattr__(self, "rotation", np.asarray(self.rotation, dtype=np.float64).reshape(3, 3))

    @property
    def forward(self) -> np.ndarray:
        return self.rotation[:, 2].copy()

    @property
    def up(self) -> np.ndarray:
        """The world direction that appears upward in the image (-y of the camera)."""
        return -self.rotation[:, 1]

    @property
    def c2w(self) -> np.ndarray:
        """(4,4) camera-to-world transform (OpenCV axes)."""
        out = np.eye(4)
        out[:3, :3] = self.rotation
        out[:3, 3] = self.position
        return out

    @property
    def w2c(self) -> np.ndarray:
        out = np.eye(4)
        out[:3, :3] = self.rotation.T
        out[:3, 3] = -self.rotation.T @ self.position
        return out

    @staticmethod
    def from_c2w(c2w: np.ndarray) -> "Pose":
        c2w = np.asarray(c2w, dtype=np.float64)
        return Pose(c2w[:3, 3], orthonormalize(c2w[:3, :3]))

    @staticmethod
    def from_camera(camera) -> "Pose":
        """Pose of a :class:`fourlegs_engine.scene.Camera`."""
        return Pose.from_c2w(camera.c2w)

    def depth_of(self, point: np.ndarray) -> float:
        """Camera-z depth of a world point (negative when behind the camera)."""
        return float((np.asarray(point, dtype=np.float64) - self.position) @ self.forward)


def rotation_angle(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Geodesic angle (radians, 0..pi) between two rotations."""
    c = (np.trace(np.asarray(Ra).T @ np.asarray(Rb)) - 1.0) / 2.0
    return float(math.acos(min(1.0, max(-1.0, c))))


def axis_angle_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    """(3,3) rotation by ``angle`` radians about ``axis`` (right-handed). Identity for a zero axis."""
    a, n = _unit(np.asarray(axis, dtype=np.float64))
    if n <= _EPS:
        return np.eye(3)
    return Rotation.from_rotvec(a * float(angle)).as_matrix()


def rotation_between(a: np.ndarray, b: np.ndarray, *, fallback_axis: np.ndarray | None = None) -> np.ndarray:
    """Minimal rotation (3,3) taking direction ``a`` onto direction ``b``.

    For opposite directions the rotation is a half turn about ``fallback_axis`` (made perpendicular
    to ``a``), or about any axis perpendicular to ``a`` when none is given.
    """
    a, na = _unit(np.asarray(a, dtype=np.float64))
    b, nb = _unit(np.asarray(b, dtype=np.float64))
    if na <= _EPS or nb <= _EPS:
        return np.eye(3)
    axis = np.cross(a, b)
    s, c = float(np.linalg.norm(axis)), float(np.clip(a @ b, -1.0, 1.0))
    if s > 1e-7:
        return axis_angle_matrix(axis, math.atan2(s, c))
    if c > 0:
        return np.eye(3)
    cand = fallback_axis if fallback_axis is not None else np.eye(3)[int(np.argmin(np.abs(a)))]
    perp = np.asarray(cand, dtype=np.float64) - (np.asarray(cand, dtype=np.float64) @ a) * a
    perp, n = _unit(perp)
    if n <= _EPS:
        perp, _ = _unit(np.cross(a, np.eye(3)[int(np.argmin(np.abs(a)))]))
    return axis_angle_matrix(perp, math.pi)


def look_at_rotation(eye: np.ndarray, target: np.ndarray, up: Sequence[float] = (0.0, 0.0, 1.0),
                     *, previous: np.ndarray | None = None) -> np.ndarray:
    """Camera-to-world rotation (3,3) of a camera at ``eye`` looking at ``target`` with ``up`` upward.

    When ``up`` is (nearly) parallel to the view direction the roll is undefined; then the roll of
    ``previous`` (a c2w rotation) is kept if given, else the world axis least aligned with the view
    defines it. Eye == target keeps ``previous`` (or identity).
    """
    f, dist = _unit(np.asarray(target, dtype=np.float64) - np.asarray(eye, dtype=np.float64))
    if dist <= _EPS:
        return orthonormalize(previous) if previous is not None else np.eye(3)
    u, _ = _unit(np.asarray(up, dtype=np.float64))
    right = np.cross(f, u)
    if np.linalg.norm(right) < 1e-6:
        if previous is not None:  # keep the previous roll: rotate it minimally onto the new forward
            return orthonormalize(rotation_between(previous[:, 2], f, fallback_axis=-previous[:, 1]) @ previous)
        right = np.cross(f, np.eye(3)[int(np.argmin(np.abs(f)))])
    right, _ = _unit(right)
    down = np.cross(f, right)
    return orthonormalize(np.stack([right, down, f], axis=1))


def aim(pose: Pose, target: np.ndarray) -> Pose:
    """The same camera turned by the smallest rotation so that ``target`` is at the image centre.

    Keeps the camera's roll as far as possible; a target straight behind the camera turns it half
    round about its own vertical axis. A target at the camera centre leaves the pose unchanged.
    """
    d = np.asarray(target, dtype=np.float64) - pose.position
    if np.linalg.norm(d) <= _EPS:
        return pose
    turn = rotation_between(pose.forward, d, fallback_axis=pose.up)
    return Pose(pose.position, orthonormalize(turn @ pose.rotation))


def slerp_rotations(R0: np.ndarray, R1: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(n,3,3) spherical interpolation between two rotations at ``weights`` in [0,1] (shortest arc)."""
    w = np.clip(np.asarray(weights, dtype=np.float64).reshape(-1), 0.0, 1.0)
    R0, R1 = orthonormalize(R0), orthonormalize(R1)
    out = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([R0, R1])))(w).as_matrix()
    out[w == 0.0], out[w == 1.0] = R0, R1   # the ends exactly (no round trip through quaternions)
    return out


def interpolate_poses(start: Pose, end: Pose, weights: np.ndarray, *, pivot: np.ndarray | None = None,
                      up: np.ndarray = WORLD_UP) -> list[Pose]:
    """Poses blending ``start`` into ``end`` at ``weights`` (0 -> start, 1 -> end).

    Orientation: slerp. Position: straight line, or — with a ``pivot`` (the action centre) — in
    cylindrical coordinates about the line through the pivot along ``up`` (angle the short way round,
    radius and height linear), so the camera swings around the action instead of cutting through it.
    """
    w = np.clip(np.asarray(weights, dtype=np.float64).reshape(-1), 0.0, 1.0)
    rots = slerp_rotations(start.rotation, end.rotation, w)
    if pivot is None:
        pos = start.position[None] + w[:, None] * (end.position - start.position)[None]
    else:
        c = np.asarray(pivot, dtype=np.float64)
        ez, n_up = _unit(np.asarray(up, dtype=np.float64))
        if n_up <= _EPS:
            ez = WORLD_UP
        ex = np.eye(3)[int(np.argmin(np.abs(ez)))]
        ex, _ = _unit(ex - (ex @ ez) * ez)
        ey = np.cross(ez, ex)
        r0, r1 = start.position - c, end.position - c
        x0, y0, z0 = r0 @ ex, r0 @ ey, r0 @ ez
        x1, y1, z1 = r1 @ ex, r1 @ ey, r1 @ ez
        rad0, rad1 = math.hypot(x0, y0), math.hypot(x1, y1)
        if rad0 <= 1e-6 or rad1 <= 1e-6:  # on the axis: the angle is undefined, go straight
            pos = start.position[None] + w[:, None] * (end.position - start.position)[None]
        else:
            a0, a1 = math.atan2(y0, x0), math.atan2(y1, x1)
            da = (a1 - a0 + math.pi) % (2 * math.pi) - math.pi
            ang = a0 + w * da
            rad = rad0 + w * (rad1 - rad0)
            z = z0 + w * (z1 - z0)
            pos = c[None] + (rad * np.cos(ang))[:, None] * ex + (rad * np.sin(ang))[:, None] * ey + z[:, None] * ez
    return [Pose(p, R) for p, R in zip(pos, rots)]


def dolly_path(start: Pose, target: np.ndarray, distance_factors: np.ndarray, *, min_distance: float = 0.0) -> list[Pose]:
    """Move the camera along the line from ``target`` through its start position.

    Args:
        start: first pose (its orientation is eased onto the target while it moves).
        target: (3,) the point approached (the action centre).
        distance_factors: (n,) distance to the target as a fraction of the start distance (1 = start).
        min_distance: never get closer to the target than this (metres).
    Returns:
        n poses; the orientation turns from ``start`` onto the target at the same pace as the move
        (a start pose already aimed at the target keeps its orientation exactly).
    """
    target = np.asarray(target, dtype=np.float64)
    factors = np.asarray(distance_factors, dtype=np.float64).reshape(-1)
    offset = start.position - target
    direction, d0 = _unit(offset)
    if d0 <= _EPS:  # camera on the target: nothing to approach
        return [start for _ in factors]
    aimed = aim(start, target)
    dist = np.maximum(d0 * factors, min(min_distance, d0))
    span = max(d0 - float(dist.min()), _EPS)
    turn = np.clip((d0 - dist) / span, 0.0, 1.0) if dist.min() < d0 else np.ones_like(dist)
    rots = slerp_rotations(start.rotation, aimed.rotation, turn)
    return [Pose(target + direction * d, R) for d, R in zip(dist, rots)]


def orbit_path(start: Pose, centre: np.ndarray, angles: np.ndarray, *, axis: np.ndarray = WORLD_UP,
               radius_factors: np.ndarray | None = None, height_factors: np.ndarray | None = None) -> list[Pose]:
    """Orbit the camera about the line through ``centre`` along ``axis`` (bullet time).

    The whole camera is rotated rigidly about that line, so its framing of the centre, its roll and
    its elevation are preserved exactly: there is no look-at and hence no flip, even for a camera
    looking straight down (radius 0 then spins the view in place). Optional radius/height factors
    (1 = unchanged) scale the horizontal and vertical offset from the centre; the orientation is then
    corrected by the minimal rotation that keeps the centre where the rigid orbit had it.

    Args:
        start: the pose at angle 0 (usually the previous shot's last pose).
        centre: (3,) the action centre.
        angles: (n,) orbit angles in radians (positive = counter-clockwise seen from above).
        radius_factors, height_factors: (n,) multipliers of the start radius / height offset.
    Returns:
        n poses; the first equals ``start`` when angles[0] == 0 and the factors start at 1.
    """
    c = np.asarray(centre, dtype=np.float64)
    ax, n_ax = _unit(np.asarray(axis, dtype=np.float64))
    if n_ax <= _EPS:
        ax = WORLD_UP
    angles = np.asarray(angles, dtype=np.float64).reshape(-1)
    ones = np.ones_like(angles)
    rf = ones if radius_factors is None else np.asarray(radius_factors, dtype=np.float64).reshape(-1)
    hf = ones if height_factors is None else np.asarray(height_factors, dtype=np.float64).reshape(-1)
    rel = start.position - c
    rel_v = (rel @ ax) * ax
    rel_h = rel - rel_v
    turns = Rotation.from_rotvec(ax[None, :] * angles[:, None]).as_matrix()            # (n,3,3)
    rigid_rel = turns @ rel                                                          # (n,3)
    actual_rel = np.einsum("nij,nj->ni", turns, rel_h[None] * rf[:, None] + rel_v[None] * hf[:, None])
    rots = turns @ start.rotation                                                    # (n,3,3)
    # Minimal rotation taking the rigid orbit's view of the centre onto the actual one (identity when
    # the factors are 1). Both directions lie on the same side of the horizontal plane, so they are
    # never opposite unless a factor makes the offset vanish; those rows take the scalar fallback.
    a, b = -rigid_rel, -actual_rel
    na, nb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
    ok = (na > _EPS) & (nb > _EPS)
    a_u = a / np.maximum(na, _EPS)[:, None]
    b_u = b / np.maximum(nb, _EPS)[:, None]
    axis_v = np.cross(a_u, b_u)
    sin = np.linalg.norm(axis_v, axis=1)
    cos = np.clip(np.einsum("ni,ni->n", a_u, b_u), -1.0, 1.0)
    regular = ok & ((sin > 1e-7) | (cos > 0))
    rotvec = axis_v / np.maximum(sin, 1e-300)[:, None] * np.arctan2(sin, cos)[:, None]
    rotvec[~regular | (sin <= 1e-7)] = 0.0
    corr = Rotation.from_rotvec(rotvec).as_matrix()
    for i in np.flatnonzero(ok & ~regular):  # exactly opposite directions: half turn
        corr[i] = rotation_between(a[i], b[i])
    rots = _orthonormalize_many(corr @ rots)
    return [Pose(c + r, R) for r, R in zip(actual_rel, rots)]


def _orthonormalize_many(Rs: np.ndarray) -> np.ndarray:
    """(n,3,3) nearest proper rotations."""
    U, _, Vt = np.linalg.svd(Rs)
    d = np.sign(np.linalg.det(U @ Vt))
    d[d == 0] = 1.0
    U[:, :, 2] *= d[:, None]
    return U @ Vt


def hold_path(pose: Pose, n: int) -> list[Pose]:
    return [pose for _ in range(n)]


def is_proper_rotation(R: np.ndarray, tol: float = 1e-6) -> bool:
    R = np.asarray(R, dtype=np.float64)
    return bool(np.all(np.isfinite(R)) and np.abs(R.T @ R - np.eye(3)).max() < tol
                and abs(np.linalg.det(R) - 1.0) < tol)
