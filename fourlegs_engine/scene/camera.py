"""Pinhole cameras in the OpenCV convention (x right, y down, z forward, metres).

``Camera`` holds float64 numpy intrinsics/extrinsics; renderers convert to tensors themselves.
``CameraRig`` holds the per-timestep camera lists of a capture, split into train and test views, as in
the Panoptic-Sports metadata (``k[t][c]``, ``w2c[t][c]``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Sequence

import numpy as np

from ..errors import InputError

RIGIDITY_TOL = 1e-4


def _as_matrix(value: Any, shape: tuple[int, int], name: str, file: str | None) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"is not a numeric {shape[0]}x{shape[1]} matrix", file=file, field=name) from None
    if arr.shape != shape:
        raise InputError(f"has shape {arr.shape}, expected {shape}", file=file, field=name)
    if not np.all(np.isfinite(arr)):
        raise InputError("contains NaN or Inf", file=file, field=name)
    return arr


@dataclass(frozen=True)
class Camera:
    """A pinhole camera.

    Attributes:
        K: (3,3) intrinsics [[fx,0,cx],[0,fy,cy],[0,0,1]] in pixels (pixel centres at +0.5).
        w2c: (4,4) world-to-camera rigid transform, OpenCV axes.
        width, height: image size in pixels.
        near, far: clipping distances along +z (metres).
        name: identifier (e.g. the Panoptic camera id).
    """

    K: np.ndarray
    w2c: np.ndarray
    width: int
    height: int
    near: float = 0.01
    far: float = 100.0
    name: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", np.asarray(self.K, dtype=np.float64))
        object.__setattr__(self, "w2c", np.asarray(self.w2c, dtype=np.float64))
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "near", float(self.near))
        object.__setattr__(self, "far", float(self.far))

    # ----------------------------------------------------------------- validation
    def validate(self, file: str | None = None, field_prefix: str = "camera") -> "Camera":
        """Raise :class:`InputError` for a non-positive focal length, non-rigid w2c, bad size or range."""
        name = f"{field_prefix}[{self.name}]" if self.name else field_prefix
        _as_matrix(self.K, (3, 3), f"{name}.K", file)
        _as_matrix(self.w2c, (4, 4), f"{name}.w2c", file)
        if not (self.K[0, 0] > 0 and self.K[1, 1] > 0):
            raise InputError(f"focal length must be positive (fx={self.K[0, 0]}, fy={self.K[1, 1]})",
                             file=file, field=f"{name}.K")
        R = self.w2c[:3, :3]
        if (np.abs(R @ R.T - np.eye(3)).max() > RIGIDITY_TOL or abs(np.linalg.det(R) - 1.0) > RIGIDITY_TOL
                or np.abs(self.w2c[3] - [0, 0, 0, 1]).max() > RIGIDITY_TOL):
            raise InputError("is not a rigid transform (rotation not orthonormal with det +1, or last row "
                             "not [0,0,0,1])", file=file, field=f"{name}.w2c")
        if self.width <= 0 or self.height <= 0:
            raise InputError(f"image size must be positive, got {self.width}x{self.height}",
                             file=file, field=f"{name}.size")
        if not (0 < self.near < self.far) or not math.isfinite(self.far):
            raise InputError(f"need 0 < near < far < inf, got near={self.near} far={self.far}",
                             file=file, field=f"{name}.near/far")
        return self

    # ------------------------------------------------------------------- geometry
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def c2w(self) -> np.ndarray:
        """(4,4) camera-to-world transform (the rigid inverse of ``w2c``)."""
        R, t = self.w2c[:3, :3], self.w2c[:3, 3]
        out = np.eye(4)
        out[:3, :3] = R.T
        out[:3, 3] = -R.T @ t
        return out

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in world coordinates."""
        return self.c2w[:3, 3]

    @property
    def forward(self) -> np.ndarray:
        """(3,) unit viewing direction (+z of the camera) in world coordinates."""
        return self.w2c[2, :3].copy()

    @property
    def fov_x(self) -> float:
        """Horizontal field of view in radians."""
        return 2.0 * math.atan(self.width / (2.0 * self.fx))

    @property
    def fov_y(self) -> float:
        """Vertical field of view in radians."""
        return 2.0 * math.atan(self.height / (2.0 * self.fy))

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points.

        Args:
            points: (M,3) world coordinates.
        Returns:
            uv: (M,2) pixel coordinates (continuous; pixel centres at +0.5), depth: (M,) camera z.
        """
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        cam = p @ self.w2c[:3, :3].T + self.w2c[:3, 3]
        z = cam[:, 2]
        safe = np.where(np.abs(z) < 1e-12, 1e-12, z)
        uv = np.stack([self.fx * cam[:, 0] / safe + self.cx, self.fy * cam[:, 1] / safe + self.cy], axis=1)
        return uv, z

    def unproject(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Lift pixels with camera-z depth to world points: (M,2),(M,) -> (M,3)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        z = np.asarray(depth, dtype=np.float64).reshape(-1)
        cam = np.stack([(uv[:, 0] - self.cx) / self.fx * z, (uv[:, 1] - self.cy) / self.fy * z, z], axis=1)
        c2w = self.c2w
        return cam @ c2w[:3, :3].T + c2w[:3, 3]

    # --------------------------------------------------------------- constructors
    @staticmethod
    def look_at(eye: Sequence[float], target: Sequence[float], up: Sequence[float] = (0.0, 0.0, 1.0), *,
                width: int, height: int, fov_y: float | None = None, focal: float | None = None,
                near: float = 0.01, far: float = 100.0, name: str = "") -> "Camera":
        """Camera at ``eye`` looking at ``target`` with world ``up`` appearing upward in the image.

        Exactly one of ``fov_y`` (radians) or ``focal`` (pixels) may be given (default fov_y=50°).
        When ``up`` is parallel to the viewing direction a stable fallback up vector is used.
        """
        eye_v = np.asarray(eye, dtype=np.float64)
        fwd = np.asarray(target, dtype=np.float64) - eye_v
        dist = np.linalg.norm(fwd)
        if not np.isfinite(dist) or dist < 1e-12:
            raise InputError("eye and target coincide; the viewing direction is undefined", field="look_at")
        fwd = fwd / dist
        R = look_rotation(fwd, np.asarray(up, dtype=np.float64))
        if focal is None:
            focal = 0.5 * height / math.tan(0.5 * (fov_y if fov_y is not None else math.radians(50.0)))
        K = np.array([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]])
        w2c = np.eye(4)
        w2c[:3, :3] = R
        w2c[:3, 3] = -R @ eye_v
        return Camera(K=K, w2c=w2c, width=width, height=height, near=near, far=far, name=name)

    def scaled(self, factor: float) -> "Camera":
        """The same camera at ``factor`` times the resolution (intrinsics scaled to match)."""
        if not factor > 0:
            raise InputError(f"resolution scale must be positive, got {factor}", field="scale")
        w = max(1, int(round(self.width * factor)))
        h = max(1, int(round(self.height * factor)))
        sx, sy = w / self.width, h / self.height
        K = self.K.copy()
        K[0] *= sx
        K[1] *= sy
        return replace(self, K=K, width=w, height=h)

    # -------------------------------------------------------------- serialization
    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "width": self.width, "height": self.height, "near": self.near,
                "far": self.far, "K": self.K.tolist(), "w2c": self.w2c.tolist()}

    @staticmethod
    def from_dict(d: dict[str, Any], file: str | None = None, field_prefix: str = "camera") -> "Camera":
        try:
            cam = Camera(K=_as_matrix(d["K"], (3, 3), f"{field_prefix}.K", file),
                         w2c=_as_matrix(d["w2c"], (4, 4), f"{field_prefix}.w2c", file),
                         width=int(d["width"]), height=int(d["height"]), near=float(d.get("near", 0.01)),
                         far=float(d.get("far", 100.0)), name=str(d.get("name", "")))
        except KeyError as exc:
            raise InputError(f"missing key {exc}", file=file, field=field_prefix) from None
        return cam.validate(file, field_prefix)


def look_rotation(forward: np.ndarray, up: np.ndarray) -> np.ndarray:
    """World-to-camera rotation (3,3) whose rows are the OpenCV camera axes (x right, y down, z fwd).

    ``up`` is the world direction that should point up in the image. If ``up`` is (nearly) parallel
    to ``forward`` the world axis least aligned with ``forward`` is used instead, so the result is
    always a proper rotation (no NaN, det +1).
    """
    f = forward / max(np.linalg.norm(forward), 1e-300)
    u = up / max(np.linalg.norm(up), 1e-300)
    right = np.cross(f, u)
    if np.linalg.norm(right) < 1e-6:
        fallback = np.eye(3)[int(np.argmin(np.abs(f)))]
        right = np.cross(f, fallback)
    right /= np.linalg.norm(right)
    down = np.cross(f, right)
    return np.stack([right, down, f])


@dataclass
class CameraRig:
    """Per-timestep camera lists, as in Panoptic metadata.

    Attributes:
        train: ``train[t][c]`` the c-th training camera at timestep t (lists may be equal across t).
        test: ``test[t][c]`` held-out cameras (may be empty lists).
    """

    train: list[list[Camera]] = field(default_factory=list)
    test: list[list[Camera]] = field(default_factory=list)

    @staticmethod
    def static(train: Sequence[Camera], test: Sequence[Camera] = (), num_timesteps: int = 1) -> "CameraRig":
        """A rig whose cameras do not move: the same lists at every timestep."""
        tr, te = list(train), list(test)
        return CameraRig(train=[tr for _ in range(num_timesteps)], test=[te for _ in range(num_timesteps)])

    @property
    def num_timesteps(self) -> int:
        return max(len(self.train), len(self.test))

    def cameras(self, t: int, split: str = "train") -> list[Camera]:
        """Cameras at timestep ``t`` of ``split`` ('train', 'test' or 'all')."""
        if split == "all":
            return self.cameras(t, "train") + self.cameras(t, "test")
        lists = {"train": self.train, "test": self.test}.get(split)
        if lists is None:
            raise InputError(f"unknown camera split {split!r} (train, test, all)", field="split")
        if not lists:
            return []
        if not 0 <= t < len(lists):
            raise InputError(f"timestep {t} is out of range 0..{len(lists) - 1}", field="t")
        return list(lists[t])

    def num_cameras(self, split: str = "train") -> int:
        lists = self.train if split == "train" else self.test
        return len(lists[0]) if lists else 0

    def find(self, name: str, t: int = 0) -> Camera:
        """The camera called ``name`` at timestep ``t`` (train first, then test)."""
        for cam in self.cameras(t, "all"):
            if cam.name == name:
                return cam
        raise InputError(f"no camera named {name!r}", field="views")

    def is_static(self) -> bool:
        def same(lists: list[list[Camera]]) -> bool:
            return all(len(l) == len(lists[0]) and all(a is b or (np.array_equal(a.K, b.K) and np.array_equal(a.w2c, b.w2c))
                                                        for a, b in zip(l, lists[0])) for l in lists)
        return same(self.train) and same(self.test)

    def to_dict(self) -> dict[str, Any]:
        if self.is_static():
            return {"static": True, "num_timesteps": self.num_timesteps,
                    "train": [c.to_dict() for c in (self.train[0] if self.train else [])],
                    "test": [c.to_dict() for c in (self.test[0] if self.test else [])]}
        return {"static": False, "num_timesteps": self.num_timesteps,
                "train": [[c.to_dict() for c in l] for l in self.train],
                "test": [[c.to_dict() for c in l] for l in self.test]}

    @staticmethod
    def from_dict(d: dict[str, Any], file: str | None = None) -> "CameraRig":
        try:
            if d.get("static", False):
                T = int(d["num_timesteps"])
                tr = [Camera.from_dict(c, file, f"cameras.train[{i}]") for i, c in enumerate(d["train"])]
                te = [Camera.from_dict(c, file, f"cameras.test[{i}]") for i, c in enumerate(d["test"])]
                return CameraRig.static(tr, te, T)
            return CameraRig(
                train=[[Camera.from_dict(c, file, f"cameras.train[{t}][{i}]") for i, c in enumerate(l)]
                       for t, l in enumerate(d["train"])],
                test=[[Camera.from_dict(c, file, f"cameras.test[{t}][{i}]") for i, c in enumerate(l)]
                      for t, l in enumerate(d["test"])])
        except KeyError as exc:
            raise InputError(f"missing key {exc}", file=file, field="cameras") from None
