"""The synthetic scene's rigid parts: rotations, surfaces of Gaussians (floor, dome wall, boxes,
ellipsoids) and the people's body parts on an articulated skeleton. Units are metres, world up is +z."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

ROOM_RADIUS = 5.5
WALL_HEIGHT = 3.5


def rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def matrix_to_quaternion(R: np.ndarray) -> np.ndarray:
    """(...,3,3) rotation matrices -> (...,4) unit quaternions (w,x,y,z) with w >= 0 (numerically stable)."""
    R = np.asarray(R, dtype=np.float64)
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    # Squared magnitudes of the four components, each from a sum that cannot cancel badly.
    sq = np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    q_abs = 0.5 * np.sqrt(np.clip(sq, 0.0, None))
    k = np.argmax(q_abs, axis=-1)
    w_ = R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]
    x_ = R[..., 2, 1] - R[..., 1, 2], R[..., 0, 1] + R[..., 1, 0], R[..., 0, 2] + R[..., 2, 0]
    y_ = R[..., 0, 2] - R[..., 2, 0], R[..., 0, 1] + R[..., 1, 0], R[..., 1, 2] + R[..., 2, 1]
    z_ = R[..., 1, 0] - R[..., 0, 1], R[..., 0, 2] + R[..., 2, 0], R[..., 1, 2] + R[..., 2, 1]
    cands = np.stack([
        np.stack([sq[..., 0], w_[0], w_[1], w_[2]], -1),
        np.stack([x_[0], sq[..., 1], x_[1], x_[2]], -1),
        np.stack([y_[0], y_[1], sq[..., 2], y_[2]], -1),
        np.stack([z_[0], z_[1], z_[2], sq[..., 3]], -1),
    ], -2)
    q = np.take_along_axis(cands, k[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True).clip(1e-300)
    return np.where(q[..., :1] < 0, -q, q)


def smoothstep(x: float) -> float:
    x = min(max(x, 0.0), 1.0)
    return x * x * (3 - 2 * x)


def lerp(a: float, b: float, s: float) -> float:
    return a + (b - a) * s


# ------------------------------------------------------------------------------- static parts


@dataclass
class Part:
    """Gaussians of one rigid part in its local frame."""

    local: np.ndarray        # (n,3) positions in the part frame
    log_scales: np.ndarray   # (n,3)
    local_rot: np.ndarray    # (n,3,3) orientation of each Gaussian in the part frame
    colors: np.ndarray       # (n,3)


def ellipsoid_surface(rng: np.random.Generator, n: int, radii: Sequence[float], center: Sequence[float],
                       color: Sequence[float], jitter: float = 0.05) -> Part:
    """``n`` Gaussians on an ellipsoid surface, flattened along the surface normal."""
    r = np.asarray(radii, dtype=np.float64)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True).clip(1e-12)
    pts = d * r + np.asarray(center, dtype=np.float64)
    normal = d / r
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    # Approximate ellipsoid area (Knud Thomsen) to size the Gaussians to the sampling density.
    p = 1.6075
    a, b, c = r
    area = 4 * math.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3) ** (1 / p)
    spacing = math.sqrt(area / max(n, 1))
    tangent_scale = float(np.clip(0.65 * spacing, 0.008, 0.05))
    scales = np.tile([tangent_scale, tangent_scale, max(0.3 * tangent_scale, 0.004)], (n, 1))
    return Part(pts, np.log(scales), _frames_from_normals(normal), _jitter_colors(rng, n, color, jitter))


def _frames_from_normals(normal: np.ndarray) -> np.ndarray:
    """(n,3) unit normals -> (n,3,3) rotations whose third column is the normal (det +1)."""
    helper = np.where(np.abs(normal[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    t1 = np.cross(helper, normal)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normal, t1)
    return np.stack([t1, t2, normal], axis=2)


def _jitter_colors(rng: np.random.Generator, n: int, color: Sequence[float], amount: float) -> np.ndarray:
    base = np.asarray(color, dtype=np.float64)
    return np.clip(base * (1 + amount * rng.normal(size=(n, 1))) + 0.5 * amount * rng.normal(size=(n, 3)),
                   0.0, 1.0)


def floor_part(rng: np.random.Generator, n: int) -> Part:
    """A round court: wooden tiles, a white centre circle and line, flat Gaussians."""
    radius = ROOM_RADIUS * np.sqrt(rng.uniform(size=n))
    angle = rng.uniform(0, 2 * np.pi, size=n)
    pts = np.stack([radius * np.cos(angle), radius * np.sin(angle), np.zeros(n)], 1)
    spacing = math.sqrt(math.pi * ROOM_RADIUS ** 2 / n)
    s = 0.8 * spacing
    scales = np.tile([s, s, 0.004], (n, 1))
    tile = (np.floor(pts[:, 0] / 0.8) + np.floor(pts[:, 1] / 0.8)) % 2
    col = np.where(tile[:, None] > 0, [[0.72, 0.52, 0.32]], [[0.64, 0.45, 0.27]])
    r = np.linalg.norm(pts[:, :2], axis=1)
    line = (np.abs(r - 1.8) < 0.05) | (np.abs(pts[:, 0]) < 0.03)
    col = np.where(line[:, None], [[0.92, 0.92, 0.9]], col)
    col = np.clip(col * (1 + 0.05 * rng.normal(size=(n, 1))), 0, 1)
    return Part(pts, np.log(scales), np.tile(np.eye(3), (n, 1, 1)), col)


def wall_part(rng: np.random.Generator, n: int) -> Part:
    """The dome wall: a cylinder of grey panels with lighter seams; Gaussians flat along the radius."""
    theta = rng.uniform(0, 2 * np.pi, size=n)
    z = rng.uniform(0, WALL_HEIGHT, size=n)
    pts = np.stack([ROOM_RADIUS * np.cos(theta), ROOM_RADIUS * np.sin(theta), z], 1)
    spacing = math.sqrt(2 * math.pi * ROOM_RADIUS * WALL_HEIGHT / n)
    s = 0.8 * spacing
    scales = np.tile([s, s, 0.004], (n, 1))
    tangent = np.stack([-np.sin(theta), np.cos(theta), np.zeros(n)], 1)
    up = np.tile([0.0, 0.0, 1.0], (n, 1))
    radial = np.stack([np.cos(theta), np.sin(theta), np.zeros(n)], 1)
    rot = np.stack([tangent, up, radial], axis=2)
    panel = (theta / (2 * np.pi) * 24) % 1.0
    seam = (panel < 0.04) | (np.abs(z - 1.2) < 0.03) | (np.abs(z - 2.4) < 0.03)
    col = np.where(seam[:, None], [[0.78, 0.78, 0.8]], [[0.42, 0.44, 0.48]])
    col = np.clip(col * (1 + 0.04 * rng.normal(size=(n, 1))), 0, 1)
    return Part(pts, np.log(scales), rot, col)


def box_surface(rng: np.random.Generator, n: int, center: Sequence[float], size: Sequence[float],
                 color: Sequence[float]) -> Part:
    """``n`` flat Gaussians on the faces of an axis-aligned box (the bottom face is omitted)."""
    sx, sy, sz = size
    faces = [  # (normal axis, sign, face area)
        (0, 1, sy * sz), (0, -1, sy * sz), (1, 1, sx * sz), (1, -1, sx * sz), (2, 1, sx * sy)]
    areas = np.array([f[2] for f in faces])
    which = rng.choice(len(faces), size=n, p=areas / areas.sum())
    u = rng.uniform(-0.5, 0.5, size=(n, 3)) * np.asarray(size)
    normal = np.zeros((n, 3))
    for i, (axis, sign, _) in enumerate(faces):
        sel = which == i
        u[sel, axis] = sign * 0.5 * size[axis]
        normal[sel, axis] = sign
    spacing = math.sqrt(areas.sum() / max(n, 1))
    s = float(np.clip(0.7 * spacing, 0.008, 0.05))
    scales = np.tile([s, s, 0.004], (n, 1))
    col = _jitter_colors(rng, n, color, 0.06)
    # Wood grain: darker stripes along x.
    col *= (0.9 + 0.1 * np.sin(u[:, 0:1] * 40.0 + u[:, 2:3] * 5.0))
    return Part(u + np.asarray(center), np.log(scales), _frames_from_normals(normal), np.clip(col, 0, 1))


# ------------------------------------------------------------------------------------ people

# Body parts: name, (radii), parent joint, segment length along -z from the joint (0: centred part).
_SKIN = (0.86, 0.66, 0.52)
_HAIR = (0.16, 0.11, 0.08)
_TROUSERS = (0.14, 0.16, 0.24)
_SHOES = (0.08, 0.08, 0.09)


@dataclass(frozen=True)
class Pose:
    """Skeleton state of one person at one time (body frame: x right, y forward, z up)."""

    root: tuple[float, float, float]          # pelvis-floor point in world (x, y, z offset of a jump)
    yaw: float                                # heading: body +y rotated by yaw about world z
    arm_pitch: tuple[float, float]            # (right, left): 0 down, +pi/2 forward, pi up
    arm_abduct: tuple[float, float]           # sideways raise
    elbow: tuple[float, float]                # forearm bend forward
    leg_pitch: tuple[float, float]            # thigh swing forward
    knee: tuple[float, float]                 # shin bend backward
    lean: float = 0.0                         # torso pitch forward


_SHOULDER = 1.45
_HIP = 0.92
_UPPER_ARM, _FOREARM, _THIGH, _SHIN = 0.30, 0.28, 0.45, 0.45


def person_parts(rng: np.random.Generator, n: int, shirt: Sequence[float]) -> list[tuple[str, Part]]:
    """Body parts of one person in their joint frames; counts proportional to rough surface area."""
    spec = [
        ("torso", (0.17, 0.11, 0.27), (0, 0, 0.0), shirt),
        ("head", (0.095, 0.105, 0.115), (0, 0, 0.0), _SKIN),
        ("hair", (0.1, 0.1, 0.06), (0, -0.01, 0.06), _HAIR),
        ("upper_arm_r", (0.055, 0.055, 0.17), (0, 0, -_UPPER_ARM / 2), shirt),
        ("upper_arm_l", (0.055, 0.055, 0.17), (0, 0, -_UPPER_ARM / 2), shirt),
        ("forearm_r", (0.045, 0.045, 0.16), (0, 0, -_FOREARM / 2), _SKIN),
        ("forearm_l", (0.045, 0.045, 0.16), (0, 0, -_FOREARM / 2), _SKIN),
        ("thigh_r", (0.075, 0.075, 0.25), (0, 0, -_THIGH / 2), _TROUSERS),
        ("thigh_l", (0.075, 0.075, 0.25), (0, 0, -_THIGH / 2), _TROUSERS),
        ("shin_r", (0.06, 0.06, 0.24), (0, 0, -_SHIN / 2), _TROUSERS),
        ("shin_l", (0.06, 0.06, 0.24), (0, 0, -_SHIN / 2), _TROUSERS),
        ("foot_r", (0.05, 0.11, 0.04), (0, 0.05, -0.02), _SHOES),
        ("foot_l", (0.05, 0.11, 0.04), (0, 0.05, -0.02), _SHOES),
    ]
    weights = np.array([r[0] * r[1] + r[0] * r[2] + r[1] * r[2] for _, r, _, _ in spec])
    counts = np.maximum(8, np.floor(n * weights / weights.sum())).astype(int)
    return [(name, ellipsoid_surface(rng, int(c), radii, centre, color))
            for (name, radii, centre, color), c in zip(spec, counts)]


def person_transforms(pose: Pose) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """World rotation (3,3) and origin (3,) of every body part frame for ``pose``."""
    Rb = rot_z(pose.yaw)
    root = np.asarray(pose.root, dtype=np.float64)
    R_torso = Rb @ rot_x(pose.lean)
    hip_centre = root + np.array([0, 0, _HIP])
    out = {"torso": (R_torso, hip_centre + R_torso @ np.array([0, 0, 0.30]))}
    neck = hip_centre + R_torso @ np.array([0, 0, 0.62])
    out["head"] = (R_torso, neck + R_torso @ np.array([0, 0, 0.12]))
    out["hair"] = out["head"]
    for k, (side, tag) in enumerate(((1.0, "r"), (-1.0, "l"))):
        shoulder = hip_centre + R_torso @ np.array([side * 0.22, 0, _SHOULDER - _HIP])
        R_up = R_torso @ rot_x(pose.arm_pitch[k]) @ rot_y(-side * pose.arm_abduct[k])
        out[f"upper_arm_{tag}"] = (R_up, shoulder)
        elbow = shoulder + R_up @ np.array([0, 0, -_UPPER_ARM])
        R_fore = R_up @ rot_x(pose.elbow[k])
        out[f"forearm_{tag}"] = (R_fore, elbow)
        hip = hip_centre + Rb @ np.array([side * 0.1, 0, 0])
        R_thigh = Rb @ rot_x(pose.leg_pitch[k])
        out[f"thigh_{tag}"] = (R_thigh, hip)
        knee = hip + R_thigh @ np.array([0, 0, -_THIGH])
        R_shin = R_thigh @ rot_x(-pose.knee[k])
        out[f"shin_{tag}"] = (R_shin, knee)
        ankle = knee + R_shin @ np.array([0, 0, -_SHIN])
        out[f"foot_{tag}"] = (Rb, ankle)
    return out


def hand(transforms: dict[str, tuple[np.ndarray, np.ndarray]], tag: str) -> np.ndarray:
    R, origin = transforms[f"forearm_{tag}"]
    return origin + R @ np.array([0, 0, -_FOREARM - 0.04])


