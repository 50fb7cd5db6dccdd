"""Synthetic 4D grounding scenes with exact space-time ground truth.

A Panoptic-like capture, generated deterministically from a seed:

* a dome of cameras (OpenCV convention, aimed at the centre; world up is +z, metres),
* static background Gaussians: a court-like floor, the dome wall, a wooden box and a bench,
* three people made of Gaussians (ellipsoid body parts on an articulated skeleton) and a ball, playing a
  scripted scene: a throw-and-catch exchange (the ball flies twice), a person walking across, jumps
  (repeated, overlapping another person's jump), a wave, holding the ball.

Every Gaussian carries a ground-truth label per timestep (``GaussianSequence.labels`` (T,N) int32) that
indexes ``LABELS`` (stored as ``scene.json["metadata"]["labels"]``); people carry the label of the action
they perform at that timestep ("person jumping", ...), the ball "ball flying in the air" while in flight.
``queries.json`` beside ``scene.json`` maps each benchmark query text to the label names it refers to.

The script is defined on normalized time u = t / (T-1) in [0, 1], so every size plays the same scene
(about six seconds: ``fps = T / 6``). Sizes (train cameras + held-out test cameras; the benchmark is
evaluated on the test cameras):

======  ==========  ===========  =====  =========
size    Gaussians   cameras      T      image
======  ==========  ===========  =====  =========
tiny    ~2k         4 + 2        12     96x54
demo    ~30k        8 + 2        48     320x180
bench   ~100k       12 + 3       60     320x180
full    ~300k       27 + 4       150    640x360
======  ==========  ===========  =====  =========
"""
from __future__ import annotations

import hashlib
import math
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from ..errors import InputError, OutputExistsError
from ..fileio import read_json, write_json_atomic
from .bundle import is_bundle, write_bundle
from .camera import Camera, CameraRig
from .gaussians import GaussianSequence
from .scene import Scene

GENERATOR_VERSION = 4
QUERIES_FILE = "queries.json"
SCENE_SECONDS = 6.0

#: Ground-truth label vocabulary (index = value stored in ``labels.npy``).
LABELS: tuple[str, ...] = (
    "floor",
    "wall",
    "wooden box",
    "bench",
    "person standing",
    "person walking",
    "person jumping",
    "person waving",
    "person throwing the ball",
    "person catching the ball",
    "person holding the ball",
    "ball flying in the air",
    "ball in a hand",
)
LABEL_INDEX = {name: i for i, name in enumerate(LABELS)}

#: Benchmark queries: text -> the label names whose Gaussians are the answer.
QUERIES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("a person jumping", ("person jumping",)),
    ("a person waving", ("person waving",)),
    ("a person throwing the ball", ("person throwing the ball",)),
    ("a person catching the ball", ("person catching the ball",)),
    ("a person walking", ("person walking",)),
    ("a person holding the ball", ("person holding the ball",)),
    ("a ball flying in the air", ("ball flying in the air",)),
)


@dataclass(frozen=True)
class SizeSpec:
    """Scale of a generated scene."""

    num_gaussians: int
    num_train_cameras: int
    num_test_cameras: int
    num_timesteps: int
    width: int
    height: int


SIZES: dict[str, SizeSpec] = {
    "tiny": SizeSpec(2_000, 4, 2, 12, 96, 54),
    "demo": SizeSpec(30_000, 8, 2, 48, 320, 180),
    "bench": SizeSpec(100_000, 12, 3, 60, 320, 180),
    "full": SizeSpec(300_000, 27, 4, 150, 640, 360),
}

# Share of the Gaussian budget per scene element (the remainder goes to the floor).
_BUDGET = {"wall": 0.16, "box": 0.04, "bench": 0.04, "person": 0.17, "ball": 0.03}

ROOM_RADIUS = 5.5
WALL_HEIGHT = 3.5
DOME_RADIUS = 4.5
LOOK_TARGET = (0.0, 0.0, 1.0)
BALL_RADIUS = 0.16
FOV_Y_DEG = 52.0
PERSON_SALIENCE = 6.0   # simulated video-model response per unit of crop coverage (background: 1)
BALL_SALIENCE = 20.0    # the ball is small, yet a video model notices it

# ----------------------------------------------------------------------------------- small math


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


def _rot_z(a: float) -> np.ndarray:
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


def _smoothstep(x: float) -> float:
    x = min(max(x, 0.0), 1.0)
    return x * x * (3 - 2 * x)


def _lerp(a: float, b: float, s: float) -> float:
    return a + (b - a) * s


# ------------------------------------------------------------------------------- static parts


@dataclass
class _Part:
    """Gaussians of one rigid part in its local frame."""

    local: np.ndarray        # (n,3) positions in the part frame
    log_scales: np.ndarray   # (n,3)
    local_rot: np.ndarray    # (n,3,3) orientation of each Gaussian in the part frame
    colors: np.ndarray       # (n,3)


def _ellipsoid_surface(rng: np.random.Generator, n: int, radii: Sequence[float], center: Sequence[float],
                       color: Sequence[float], jitter: float = 0.05) -> _Part:
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
    return _Part(pts, np.log(scales), _frames_from_normals(normal), _jitter_colors(rng, n, color, jitter))


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


def _floor(rng: np.random.Generator, n: int) -> _Part:
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
    return _Part(pts, np.log(scales), np.tile(np.eye(3), (n, 1, 1)), col)


def _wall(rng: np.random.Generator, n: int) -> _Part:
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
    return _Part(pts, np.log(scales), rot, col)


def _box_surface(rng: np.random.Generator, n: int, center: Sequence[float], size: Sequence[float],
                 color: Sequence[float]) -> _Part:
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
    return _Part(u + np.asarray(center), np.log(scales), _frames_from_normals(normal), np.clip(col, 0, 1))


# ------------------------------------------------------------------------------------ people

# Body parts: name, (radii), parent joint, segment length along -z from the joint (0: centred part).
_SKIN = (0.86, 0.66, 0.52)
_HAIR = (0.16, 0.11, 0.08)
_TROUSERS = (0.14, 0.16, 0.24)
_SHOES = (0.08, 0.08, 0.09)


@dataclass(frozen=True)
class _Pose:
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


def _person_parts(rng: np.random.Generator, n: int, shirt: Sequence[float]) -> list[tuple[str, _Part]]:
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
    return [(name, _ellipsoid_surface(rng, int(c), radii, centre, color))
            for (name, radii, centre, color), c in zip(spec, counts)]


def _person_transforms(pose: _Pose) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """World rotation (3,3) and origin (3,) of every body part frame for ``pose``."""
    Rb = _rot_z(pose.yaw)
    root = np.asarray(pose.root, dtype=np.float64)
    R_torso = Rb @ _rot_x(pose.lean)
    hip_centre = root + np.array([0, 0, _HIP])
    out = {"torso": (R_torso, hip_centre + R_torso @ np.array([0, 0, 0.30]))}
    neck = hip_centre + R_torso @ np.array([0, 0, 0.62])
    out["head"] = (R_torso, neck + R_torso @ np.array([0, 0, 0.12]))
    out["hair"] = out["head"]
    for k, (side, tag) in enumerate(((1.0, "r"), (-1.0, "l"))):
        shoulder = hip_centre + R_torso @ np.array([side * 0.22, 0, _SHOULDER - _HIP])
        R_up = R_torso @ _rot_x(pose.arm_pitch[k]) @ _rot_y(-side * pose.arm_abduct[k])
        out[f"upper_arm_{tag}"] = (R_up, shoulder)
        elbow = shoulder + R_up @ np.array([0, 0, -_UPPER_ARM])
        R_fore = R_up @ _rot_x(pose.elbow[k])
        out[f"forearm_{tag}"] = (R_fore, elbow)
        hip = hip_centre + Rb @ np.array([side * 0.1, 0, 0])
        R_thigh = Rb @ _rot_x(pose.leg_pitch[k])
        out[f"thigh_{tag}"] = (R_thigh, hip)
        knee = hip + R_thigh @ np.array([0, 0, -_THIGH])
        R_shin = R_thigh @ _rot_x(-pose.knee[k])
        out[f"shin_{tag}"] = (R_shin, knee)
        ankle = knee + R_shin @ np.array([0, 0, -_SHIN])
        out[f"foot_{tag}"] = (Rb, ankle)
    return out


def _hand(transforms: dict[str, tuple[np.ndarray, np.ndarray]], tag: str) -> np.ndarray:
    R, origin = transforms[f"forearm_{tag}"]
    return origin + R @ np.array([0, 0, -_FOREARM - 0.04])


# ------------------------------------------------------------------------------------ script


@dataclass(frozen=True)
class Action:
    """One scripted action: ``actor`` performs ``label`` over normalized time [start, end)."""

    actor: str
    label: str
    start: float
    end: float


# Times are normalized to [0, 1]. Ball exchange: A throws to B, B throws a lob back to A.
_RELEASE_1, _ARRIVE_1 = 0.20, 0.33
_RELEASE_2, _ARRIVE_2 = 0.60, 0.84

SCRIPT: tuple[Action, ...] = (
    Action("A", "person holding the ball", 0.00, 0.12),
    Action("A", "person throwing the ball", 0.12, 0.25),
    Action("A", "person waving", 0.42, 0.60),
    Action("A", "person catching the ball", 0.76, 0.88),
    Action("A", "person holding the ball", 0.88, 1.01),
    Action("B", "person catching the ball", 0.25, 0.37),
    Action("B", "person holding the ball", 0.37, 0.52),
    Action("B", "person throwing the ball", 0.52, 0.64),
    Action("B", "person jumping", 0.70, 0.82),
    Action("C", "person walking", 0.00, 0.36),
    Action("C", "person jumping", 0.45, 0.58),
    Action("C", "person jumping", 0.76, 0.89),
)


class _Actor:
    """A scripted person: a base stance, actions over time, and a walking path."""

    def __init__(self, name: str, position: np.ndarray, yaw: float, path_end: np.ndarray | None = None):
        self.name = name
        self.position = position
        self.yaw = yaw
        self.path_end = path_end
        self.actions = [a for a in SCRIPT if a.actor == name]

    def action_at(self, u: float) -> tuple[Action | None, float]:
        for a in self.actions:
            if a.start <= u < a.end:
                return a, (u - a.start) / (a.end - a.start)
        return None, 0.0

    def label_at(self, u: float) -> str:
        a, _ = self.action_at(u)
        return a.label if a else "person standing"

    def root_xy(self, u: float) -> tuple[np.ndarray, float]:
        if self.path_end is None:
            return self.position, self.yaw
        walk = next((a for a in self.actions if a.label == "person walking"), None)
        s = 0.0 if walk is None else min(max((u - walk.start) / (walk.end - walk.start), 0.0), 1.0)
        d = self.path_end - self.position
        heading = math.atan2(-d[0], d[1])
        pos = self.position + s * d
        turn = (self.yaw - heading + math.pi) % (2 * math.pi) - math.pi   # shortest way round
        yaw = heading if s < 1.0 else heading + turn * _smoothstep((u - walk.end) / 0.06)
        return pos, yaw

    def pose(self, u: float) -> _Pose:
        pos, yaw = self.root_xy(u)
        action, p = self.action_at(u)
        label = action.label if action else "person standing"
        z = 0.0
        arm_p, arm_a, elbow = [0.05, 0.05], [0.12, 0.12], [0.15, 0.15]
        leg_p, knee, lean = [0.0, 0.0], [0.03, 0.03], 0.0
        if label == "person walking":
            walk_len = float(np.linalg.norm(self.path_end - self.position)) if self.path_end is not None else 0
            phase = 2 * math.pi * (p * walk_len / 1.4)
            swing = math.sin(phase)
            leg_p = [0.45 * swing, -0.45 * swing]
            knee = [0.1 + 0.5 * max(0.0, -swing), 0.1 + 0.5 * max(0.0, swing)]
            arm_p = [-0.35 * swing, 0.35 * swing]
            elbow = [0.3, 0.3]
            z = 0.02 * abs(math.cos(phase))
        elif label == "person jumping":
            crouch = _smoothstep(p / 0.2) * (1 - _smoothstep((p - 0.2) / 0.08)) + \
                _smoothstep((p - 0.8) / 0.1) * (1 - _smoothstep((p - 0.9) / 0.1))
            air = min(max((p - 0.25) / 0.55, 0.0), 1.0)
            z = 0.5 * math.sin(math.pi * air) - 0.18 * crouch
            knee = [0.2 + 1.0 * crouch] * 2
            leg_p = [0.1 + 0.6 * crouch] * 2
            lean = 0.3 * crouch
            raise_ = math.sin(math.pi * air)
            arm_p = [0.3 + 2.5 * raise_] * 2
            arm_a = [0.2, 0.2]
            elbow = [0.2, 0.2]
        elif label == "person waving":
            up = _smoothstep(p / 0.15) * (1 - _smoothstep((p - 0.85) / 0.15))
            arm_a = [0.12 + 2.4 * up + 0.35 * up * math.sin(2 * math.pi * 3 * p), 0.12]
            elbow = [0.15 + 0.4 * up, 0.15]
            arm_p = [0.05 + 0.3 * up, 0.05]
        elif label == "person throwing the ball":
            if p < 0.45:
                s = _smoothstep(p / 0.45)
                arm_p = [_lerp(0.9, 3.7, s), 0.9 - 0.3 * s]
                elbow = [_lerp(1.3, 1.4, s), 1.0]
            else:
                s = _smoothstep((p - 0.45) / 0.55)
                arm_p = [_lerp(3.7, 0.7, s), _lerp(0.6, 0.1, s)]
                elbow = [_lerp(1.4, 0.1, min(1.0, 2 * s)), 0.3]
                lean = 0.25 * math.sin(math.pi * s)
            arm_a = [0.15, 0.15]
            leg_p = [0.25, -0.2]
        elif label == "person catching the ball":
            reach = _smoothstep(p / 0.35)
            arm_p = [_lerp(0.05, 1.45, reach)] * 2
            arm_a = [0.22, 0.22]
            arrive = self._arrival_phase(action)
            pull = _smoothstep((p - arrive) / 0.3) if p > arrive else 0.0
            elbow = [_lerp(0.35, 1.3, pull)] * 2
            arm_p = [_lerp(arm_p[0], 0.95, pull)] * 2
            knee = [0.15 + 0.2 * reach * (1 - pull)] * 2
        elif label == "person holding the ball":
            arm_p, arm_a, elbow = [0.95, 0.95], [0.22, 0.22], [1.3, 1.3]
        return _Pose((float(pos[0]), float(pos[1]), z), yaw, tuple(arm_p), tuple(arm_a), tuple(elbow),
                     tuple(leg_p), tuple(knee), lean)

    @staticmethod
    def _arrival_phase(action: Action) -> float:
        for arrive in (_ARRIVE_1, _ARRIVE_2):
            if action.start <= arrive < action.end:
                return (arrive - action.start) / (action.end - action.start)
        return 0.5


def _ball_state(u: float, actors: dict[str, _Actor]) -> tuple[np.ndarray, str]:
    """Ball centre (3,) and its label at normalized time ``u``."""

    def held(actor: _Actor, t: float) -> np.ndarray:
        tr = _person_transforms(actor.pose(t))
        a, _ = actor.action_at(t)
        if a is not None and a.label == "person throwing the ball":
            return _hand(tr, "r") + tr["torso"][0] @ np.array([0, 0.02, 0.08])
        mid = 0.5 * (_hand(tr, "r") + _hand(tr, "l"))
        return mid + tr["torso"][0] @ np.array([0, BALL_RADIUS * 0.9, 0.02])

    for (thrower, catcher, release, arrive, apex) in (("A", "B", _RELEASE_1, _ARRIVE_1, 0.5),
                                                      ("B", "A", _RELEASE_2, _ARRIVE_2, 0.9)):
        if release <= u < arrive:
            p0, p1 = held(actors[thrower], release - 1e-9), held(actors[catcher], arrive)
            s = (u - release) / (arrive - release)
            pos = (1 - s) * p0 + s * p1
            pos[2] += 4 * apex * s * (1 - s)
            return pos, "ball flying in the air"
    if u < _RELEASE_1:
        holder = "A"
    elif u < _RELEASE_2:
        holder = "B"
    else:
        holder = "A"
    return held(actors[holder], u), "ball in a hand"


# ------------------------------------------------------------------------------------ cameras


def dome_cameras(spec: SizeSpec, rng: np.random.Generator) -> tuple[list[Camera], list[Camera]]:
    """Train and test cameras on a dome around the centre, all aimed at ``LOOK_TARGET``."""
    offset = rng.uniform(0, 2 * np.pi / max(spec.num_train_cameras, 1))
    heights = (1.3, 2.4, 3.2)
    train = []
    for i in range(spec.num_train_cameras):
        az = offset + 2 * np.pi * i / spec.num_train_cameras
        h = heights[i % len(heights)]
        r = math.sqrt(max(DOME_RADIUS ** 2 - (h - 1.0) ** 2 * 0.3, 1.0))
        eye = (r * math.cos(az), r * math.sin(az), h)
        train.append(Camera.look_at(eye, LOOK_TARGET, width=spec.width, height=spec.height,
                                    fov_y=math.radians(FOV_Y_DEG), name=f"cam{i:02d}"))
    test = []
    for j in range(spec.num_test_cameras):
        az = offset + 2 * np.pi * (j + 0.37) / spec.num_test_cameras + np.pi / max(spec.num_train_cameras, 1)
        eye = (DOME_RADIUS * math.cos(az), DOME_RADIUS * math.sin(az), 1.8)
        test.append(Camera.look_at(eye, LOOK_TARGET, width=spec.width, height=spec.height,
                                   fov_y=math.radians(FOV_Y_DEG), name=f"test{j:02d}"))
    return train, test


# ------------------------------------------------------------------------------------ builder


def _spec_for(size: str) -> SizeSpec:
    if size not in SIZES:
        raise InputError(f"unknown size {size!r} (choose from {', '.join(SIZES)})", field="size")
    return SIZES[size]


def generate_scene(size: str = "tiny", seed: int = 0,
                   progress: Callable[[int, int], None] | None = None) -> Scene:
    """Build the synthetic scene of ``size`` deterministically from ``seed`` (in memory).

    Returns a :class:`Scene` whose Gaussians carry ``labels`` (T,N) int32 and whose metadata holds
    ``labels`` (the vocabulary), ``queries`` ({text: [label names]}), ``script`` (the actions with
    their frame ranges), ``generator`` (version, size, seed).
    """
    spec = _spec_for(size)
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"seed must be a non-negative integer, got {seed!r}", field="seed")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), GENERATOR_VERSION, 0x4C454753]))
    N_target, T = spec.num_gaussians, spec.num_timesteps
    counts = {k: int(v * N_target) for k, v in _BUDGET.items()}

    # Static background.
    static_parts: list[tuple[str, _Part]] = [
        ("floor", _floor(rng, N_target - sum(counts.values()) - 2 * counts["person"])),
        ("wall", _wall(rng, counts["wall"])),
        ("wooden box", _box_surface(rng, counts["box"], (2.9 + rng.uniform(-0.2, 0.2), 2.4, 0.35),
                                    (0.7, 0.7, 0.7), (0.62, 0.42, 0.22))),
        ("bench", _box_surface(rng, counts["bench"], (-2.7, -2.9 + rng.uniform(-0.2, 0.2), 0.25),
                               (1.6, 0.45, 0.5), (0.25, 0.3, 0.45))),
    ]

    # Actors. Shirt colours differ per person; small seed-dependent placement offsets.
    shirts = [(0.78, 0.16, 0.14), (0.16, 0.36, 0.78), (0.2, 0.62, 0.3)]
    order = rng.permutation(3)
    jit = rng.uniform(-0.15, 0.15, size=(3, 2))
    actors = {
        "A": _Actor("A", np.array([-1.3, 0.15]) + jit[0], -math.pi / 2),
        "B": _Actor("B", np.array([1.3, -0.15]) + jit[1], math.pi / 2),
        "C": _Actor("C", np.array([-1.9, 1.7]) + jit[2], math.pi, path_end=np.array([0.3, 1.9]) + jit[2]),
    }
    per_person = 3 * counts["person"] // 3
    actor_parts = {name: _person_parts(rng, per_person, shirts[order[i]]) for i, name in enumerate("ABC")}
    ball_n = N_target - sum(p.local.shape[0] for _, p in static_parts) - \
        sum(p.local.shape[0] for parts in actor_parts.values() for _, p in parts)
    ball_n = max(ball_n, 16)
    ball = _ellipsoid_surface(rng, ball_n, (BALL_RADIUS,) * 3, (0, 0, 0), (0.9, 0.42, 0.1), jitter=0.03)
    seam = np.abs(ball.local[:, 2]) < 0.012
    seam |= np.abs(ball.local[:, 0]) < 0.012
    ball.colors[seam] = (0.12, 0.06, 0.03)

    # Assemble static arrays.
    blocks_local, blocks_scales, blocks_colors, blocks_localrot = [], [], [], []
    static_label = []
    for label, part in static_parts:
        blocks_local.append(part.local)
        blocks_scales.append(part.log_scales)
        blocks_colors.append(part.colors)
        blocks_localrot.append(part.local_rot)
        static_label.append(np.full(part.local.shape[0], LABEL_INDEX[label]))
    n_static = sum(b.shape[0] for b in blocks_local)
    moving: list[tuple[str, str, slice]] = []  # (actor or "ball", part name, index range)
    cursor = n_static
    for name, parts in actor_parts.items():
        for part_name, part in parts:
            n = part.local.shape[0]
            blocks_local.append(part.local)
            blocks_scales.append(part.log_scales)
            blocks_colors.append(part.colors)
            blocks_localrot.append(part.local_rot)
            moving.append((name, part_name, slice(cursor, cursor + n)))
            cursor += n
    blocks_local.append(ball.local)
    blocks_scales.append(ball.log_scales)
    blocks_colors.append(ball.colors)
    blocks_localrot.append(ball.local_rot)
    moving.append(("ball", "ball", slice(cursor, cursor + ball.local.shape[0])))
    N = cursor + ball.local.shape[0]

    local = np.concatenate(blocks_local)
    local_rot = np.concatenate(blocks_localrot)
    means = np.empty((T, N, 3), np.float32)
    rotations = np.empty((T, N, 4), np.float32)
    labels = np.empty((T, N), np.int32)
    static_q = matrix_to_quaternion(local_rot[:n_static]).astype(np.float32)
    static_lab = np.concatenate(static_label).astype(np.int32)
    foreground = np.zeros(N, bool)
    foreground[n_static:] = True

    script_frames: list[dict] = []
    ball_labels: list[str] = []
    for t in range(T):
        u = t / (T - 1) if T > 1 else 0.0
        means[t, :n_static] = local[:n_static]
        rotations[t, :n_static] = static_q
        labels[t, :n_static] = static_lab
        transforms = {name: _person_transforms(actor.pose(u)) for name, actor in actors.items()}
        ball_centre, ball_label = _ball_state(u, actors)
        ball_labels.append(ball_label)
        for owner, part_name, sl in moving:
            if owner == "ball":
                spin = _rot_x(6.0 * u * 2 * np.pi) @ _rot_z(2.0 * u * 2 * np.pi)
                R, origin, lab = spin, ball_centre, LABEL_INDEX[ball_label]
            else:
                R, origin = transforms[owner][part_name]
                lab = LABEL_INDEX[actors[owner].label_at(u)]
            means[t, sl] = local[sl] @ R.T + origin
            rotations[t, sl] = matrix_to_quaternion(R[None] @ local_rot[sl]).astype(np.float32)
            labels[t, sl] = lab
        if progress is not None:
            progress(t + 1, T)

    log_scales = np.concatenate(blocks_scales).astype(np.float32)
    colors = np.concatenate(blocks_colors).astype(np.float32)
    opacity = np.full(N, 3.5, np.float32)  # sigmoid = 0.97
    opacity[:n_static] = 4.0
    gaussians = GaussianSequence(means=means, rotations=rotations, log_scales=log_scales,
                                 opacity_logits=opacity, colors=colors, foreground=foreground, labels=labels)
    train, test = dome_cameras(spec, rng)
    rig = CameraRig.static(train, test, T)
    for a in SCRIPT:
        script_frames.append({"actor": a.actor, "label": a.label, "start": a.start, "end": a.end,
                              "frames": _frames_of(a.start, a.end, T)})
    metadata = {
        "source": "synthetic",
        "generator": {"name": "fourlegs_engine.scene.synthetic", "version": GENERATOR_VERSION,
                      "size": size, "seed": int(seed)},
        "labels": list(LABELS),
        "queries": {text: list(labs) for text, labs in QUERIES},
        "script": script_frames,
        "ball_labels": ball_labels,
        "background_labels": ["floor", "wall", "wooden box", "bench"],
        # how strongly a (simulated) video model responds to a label per unit of crop coverage
        "salience": {name: (1.0 if name in ("floor", "wall", "wooden box", "bench") else
                            BALL_SALIENCE if name.startswith("ball") else PERSON_SALIENCE) for name in LABELS},
    }
    return Scene(gaussians=gaussians, cameras=rig, name=f"synthetic-{size}-seed{int(seed)}",
                 fps=T / SCENE_SECONDS, metadata=metadata)


def _frames_of(start: float, end: float, T: int) -> list[int]:
    """Inclusive frame range [first, last] of normalized interval [start, end), or [] if no frame falls in it."""
    frames = [t for t in range(T) if start <= (t / (T - 1) if T > 1 else 0.0) < end]
    return [frames[0], frames[-1]] if frames else []


def queries_document(scene_or_metadata: Scene | dict) -> dict:
    """The ``queries.json`` document: ``{"format", "version", "queries": [{"text", "labels"}]}``."""
    meta = scene_or_metadata.metadata if isinstance(scene_or_metadata, Scene) else scene_or_metadata
    return {"format": "fourlegs-queries", "version": 1,
            "queries": [{"text": text, "labels": list(labs)} for text, labs in meta["queries"].items()]}


def read_queries(bundle: str | Path) -> dict[str, list[str]]:
    """Read ``queries.json`` of a bundle: {query text: [label names]}; validated against the labels."""
    path = Path(bundle) / QUERIES_FILE
    doc = read_json(path)
    if not isinstance(doc, dict) or doc.get("format") != "fourlegs-queries":
        raise InputError("not a fourlegs-queries document", file=path, field="format")
    out: dict[str, list[str]] = {}
    for i, q in enumerate(doc.get("queries", [])):
        if not isinstance(q, dict) or not isinstance(q.get("text"), str) or not isinstance(q.get("labels"), list):
            raise InputError("each entry needs 'text' (str) and 'labels' (list)", file=path, field=f"queries[{i}]")
        out[q["text"]] = [str(x) for x in q["labels"]]
    return out


def write_synthetic_bundle(path: str | Path, size: str = "tiny", seed: int = 0, *, overwrite: bool = False,
                           progress: Callable[[int, int], None] | None = None) -> Path:
    """Generate a scene and write it as a bundle (with ``queries.json``) at ``path``, atomically."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise OutputExistsError(path)
    scene = generate_scene(size, seed, progress=progress)
    path.parent.mkdir(parents=True, exist_ok=True)
    staging_root = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".gen", dir=path.parent))
    try:
        staged = write_bundle(scene, staging_root / "bundle")
        write_json_atomic(staged / QUERIES_FILE, queries_document(scene))
        if path.exists():  # overwrite requested
            trash = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".old", dir=path.parent))
            path.rename(trash / "old")
            staged.rename(path)
            shutil.rmtree(trash, ignore_errors=True)
        else:
            os.rename(staged, path)
    finally:
        shutil.rmtree(staging_root, ignore_errors=True)
    scene.root = path
    return path


def demo_bundle_path(size: str = "demo", seed: int = 0) -> Path:
    """Where :func:`ensure_demo_bundle` keeps the scene (keyed by generator version, size and seed)."""
    from ..paths import cache_dir
    _spec_for(size)
    return cache_dir() / "scenes" / f"synthetic-v{GENERATOR_VERSION}-{size}-seed{int(seed)}"


def ensure_demo_bundle(size: str = "demo", seed: int = 0) -> Path:
    """The synthetic scene bundle of ``size``/``seed`` in the cache directory, generated on first use.

    Generation is atomic (staged beside the final directory, then renamed), so concurrent callers and
    interrupted runs never see a half-written bundle; a later call reuses the finished one.
    """
    path = demo_bundle_path(size, seed)
    if is_bundle(path) and (path / QUERIES_FILE).is_file():
        return path
    try:
        write_synthetic_bundle(path, size, seed)
    except (OutputExistsError, OSError):
        if not (is_bundle(path) and (path / QUERIES_FILE).is_file()):
            raise
    return path


def bundle_digest(path: str | Path) -> str:
    """SHA-256 over the relative names and bytes of every file of a bundle (sorted); identical bundles match."""
    root = Path(path)
    h = hashlib.sha256()
    for f in sorted(p for p in root.rglob("*") if p.is_file()):
        rel = f.relative_to(root).as_posix()
        if rel.startswith("ground_truth/") or rel.startswith("features/") or rel.startswith("."):
            continue
        h.update(rel.encode())
        h.update(b"\0")
        with open(f, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
    return h.hexdigest()
