"""Pinhole cameras in the OpenCV convention (x right, y down, z forward, metres).

``Camera`` holds float64 numpy intrinsics/extrinsics; renderers convert to tensors themselves.
``CameraRig`` holds the per-timestep camera lists of a capture, split into train and test views, as in
the Panoptic-Sports metadata (``k[t][c]``, ``w2c[t][c]``).
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field, replace
from typing import Any, Sequence

import numpy as np

from ..errors import InputError

RIGIDITY_TOL = 1e-4
MAX_IMAGE_SIDE = 1 << 15  # pixels; beyond any camera, and keeps per-image buffers allocatable
MAX_RIG_TIMESTEPS = 1 << 20


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
        if not (0 < self.width <= MAX_IMAGE_SIDE and 0 < self.height <= MAX_IMAGE_SIDE):
            raise InputError(f"image size must be 1..{MAX_IMAGE_SIDE} pixels a side, got {self.width}x{self.height}",
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
        """Lift pixels with camera-z depth to world points: (M,2),(M,) -> (M,3). InputError for a pixel or
        depth that is not finite (a point at infinite depth has no world position)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        z = np.asarray(depth, dtype=np.float64).reshape(-1)
        if not (np.isfinite(uv).all() and np.isfinite(z).all()):
            raise InputError("pixels and depths must be finite (a point at infinite depth has no position)",
                             field="unproject")
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
        eye_v = _finite_vector(eye, "look_at.eye")
        target_v = _finite_vector(target, "look_at.target")
        up_v = _finite_vector(up, "look_at.up")
        fwd = target_v - eye_v
        extent = float(np.abs(fwd).max())  # scaled first: the norm of 1e300-sized vectors overflows
        if not math.isfinite(extent):
            raise InputError("eye and target are too far apart to represent", field="look_at")
        if extent < 1e-12:
            raise InputError("eye and target coincide; the viewing direction is undefined", field="look_at")
        fwd = fwd / extent
        fwd = fwd / np.linalg.norm(fwd)
        R = look_rotation(fwd, up_v / max(float(np.abs(up_v).max()), 1e-300))
        width = _json_number(width, "look_at.width", None, integer=True, low=1, high=MAX_IMAGE_SIDE)
        height = _json_number(height, "look_at.height", None, integer=True, low=1, high=MAX_IMAGE_SIDE)
        if focal is None:
            fov = math.radians(50.0) if fov_y is None else fov_y
            if not (isinstance(fov, numbers.Real) and 0 < fov < math.pi):
                raise InputError(f"vertical field of view must be in (0, pi) radians, got {fov_y!r}",
                                 field="look_at.fov_y")
            focal = 0.5 * height / math.tan(0.5 * fov)
        elif not (isinstance(focal, numbers.Real) and math.isfinite(focal) and focal > 0):
            raise InputError(f"focal length must be positive and finite, got {focal!r}", field="look_at.focal")
        K = np.array([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]])
        w2c = np.eye(4)
        w2c[:3, :3] = R
        w2c[:3, 3] = -R @ eye_v
        return Camera(K=K, w2c=w2c, width=width, height=height, near=near, far=far, name=name)

    def scaled(self, factor: float) -> "Camera":
        """The same camera at ``factor`` times the resolution (intrinsics scaled to match)."""
        if not (factor > 0 and math.isfinite(factor)):
            raise InputError(f"resolution scale must be positive and finite, got {factor}", field="scale")
        w = max(1, int(round(self.width * factor)))
        h = max(1, int(round(self.height * factor)))
        if w > MAX_IMAGE_SIDE or h > MAX_IMAGE_SIDE:
            raise InputError(f"{self.width}x{self.height} scaled by {factor:g} is {w}x{h}, over the "
                             f"{MAX_IMAGE_SIDE}-pixel limit a side", field="scale")
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
        if not isinstance(d, dict):
            raise InputError(f"must be an object, got {type(d).__name__}", file=file, field=field_prefix)
        try:
            size = [_json_number(d[k], f"{field_prefix}.{k}", file, integer=True, low=1, high=MAX_IMAGE_SIDE)
                    for k in ("width", "height")]
            near = _json_number(d.get("near", 0.01), f"{field_prefix}.near", file)
            far = _json_number(d.get("far", 100.0), f"{field_prefix}.far", file)
            name = d.get("name", "")
            if not isinstance(name, (str, int)):
                raise InputError(f"must be a string, got {name!r}", file=file, field=f"{field_prefix}.name")
            cam = Camera(K=_as_matrix(d["K"], (3, 3), f"{field_prefix}.K", file),
                         w2c=_as_matrix(d["w2c"], (4, 4), f"{field_prefix}.w2c", file),
                         width=size[0], height=size[1], near=near, far=far, name=str(name))
        except KeyError as exc:
            raise InputError(f"missing key {exc}", file=file, field=field_prefix) from None
        return cam.validate(file, field_prefix)


def _finite_vector(value: Any, name: str) -> np.ndarray:
    try:
        v = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"must be 3 numbers, got {value!r}", field=name) from None
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise InputError(f"must be 3 finite numbers, got {value!r}", field=name)
    return v


def _json_number(value: Any, name: str, file: str | None, *, integer: bool = False,
                 low: float | None = None, high: float | None = None) -> Any:
    """A JSON number of the right kind and range (an integer-valued float counts as an integer)."""
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)
    if ok and integer:
        ok = float(value).is_integer()
    if ok and ((low is not None and value < low) or (high is not None and value > high)):
        ok = False
    if not ok:
        kind = "an integer" if integer else "a finite number"
        bounds = f" in {low:g}..{high:g}" if low is not None and high is not None else ""
        raise InputError(f"must be {kind}{bounds}, got {value!r}", file=file, field=name)
    return int(value) if integer else float(value)


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
        """The rig of a ``to_dict`` object; every entry's type and bound is checked (InputError)."""
        if not isinstance(d, dict):
            raise InputError(f"must be an object, got {type(d).__name__}", file=file, field="cameras")

        def lists(split: str, depth: int) -> list:
            value = d.get(split, [])
            if not isinstance(value, list) or (depth == 2 and not all(isinstance(l, list) for l in value)):
                raise InputError("must be a list" + (" of per-timestep camera lists" if depth == 2 else ""),
                                 file=file, field=f"cameras.{split}")
            return value

        static = d.get("static", False)
        if not isinstance(static, bool):
            raise InputError(f"must be true or false, got {static!r}", file=file, field="cameras.static")
        if static:
            T = _json_number(d.get("num_timesteps"), "cameras.num_timesteps", file, integer=True, low=0,
                             high=MAX_RIG_TIMESTEPS)
            tr = [Camera.from_dict(c, file, f"cameras.train[{i}]") for i, c in enumerate(lists("train", 1))]
            te = [Camera.from_dict(c, file, f"cameras.test[{i}]") for i, c in enumerate(lists("test", 1))]
            return CameraRig.static(tr, te, T)
        train, test = lists("train", 2), lists("test", 2)
        if max(len(train), len(test)) > MAX_RIG_TIMESTEPS:
            raise InputError(f"more than {MAX_RIG_TIMESTEPS} timesteps of cameras", file=file, field="cameras")
        return CameraRig(
            train=[[Camera.from_dict(c, file, f"cameras.train[{t}][{i}]") for i, c in enumerate(l)]
                   for t, l in enumerate(train)],
            test=[[Camera.from_dict(c, file, f"cameras.test[{t}][{i}]") for i, c in enumerate(l)]
                  for t, l in enumerate(test)])
