"""The highlight plan: what Blender (or any renderer) must animate and render, as versioned JSON.

The schema is fixed in docs/CONTRACTS.md ("highlights — plan JSON (version 1)"). Camera keys are
dense (one per timeline frame), OpenCV camera-to-world; the lens is given for a horizontal sensor fit
(``lens_mm = focal_px * sensor_width_mm / width_px``). Scene-time keys are dense too and may be
fractional. ``passes`` lists, per render pass, the inclusive timeline frame ranges that need it.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np

from ..errors import InputError
from ..fileio import read_json, write_json_atomic
from .camera_paths import Pose

PLAN_FORMAT = "fourlegs-highlight-plan"
PLAN_VERSION = 1
DEFAULT_SENSOR_WIDTH_MM = 36.0


def _finite(x: Any, what: str) -> float:
    v = float(x)
    if not math.isfinite(v):
        raise InputError(f"is not finite ({v})", field=what)
    return v


def merge_ranges(ranges: list[tuple[int, int]] | list[list[int]]) -> list[list[int]]:
    """Sorted union of inclusive integer ranges; adjacent ranges are merged: [[1,3],[4,6]] -> [[1,6]]."""
    out: list[list[int]] = []
    for a, b in sorted((int(a), int(b)) for a, b in ranges if int(b) >= int(a)):
        if out and a <= out[-1][1] + 1:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return out


def frames_in_ranges(ranges: list[list[int]]) -> set[int]:
    return {f for a, b in ranges for f in range(int(a), int(b) + 1)}


@dataclass
class CameraKey:
    """One camera keyframe: OpenCV c2w (4,4), focal length in pixels of the plan's resolution."""

    frame: int
    c2w: np.ndarray
    focal_px: float
    lens_mm: float
    sensor_width_mm: float = DEFAULT_SENSOR_WIDTH_MM

    @property
    def pose(self) -> Pose:
        return Pose.from_c2w(self.c2w)

    @staticmethod
    def make(frame: int, pose: Pose, focal_px: float, width: int,
             sensor_width_mm: float = DEFAULT_SENSOR_WIDTH_MM) -> "CameraKey":
        return CameraKey(int(frame), pose.c2w, float(focal_px), float(focal_px) * sensor_width_mm / width,
                         sensor_width_mm)

    def to_dict(self) -> dict[str, Any]:
        return {"frame": int(self.frame), "c2w": [[float(v) for v in row] for row in np.asarray(self.c2w)],
                "focal_px": float(self.focal_px), "lens_mm": float(self.lens_mm),
                "sensor_width_mm": float(self.sensor_width_mm)}

    @staticmethod
    def from_dict(d: dict[str, Any], where: str) -> "CameraKey":
        c2w = np.asarray(d["c2w"], dtype=np.float64)
        if c2w.shape != (4, 4) or not np.all(np.isfinite(c2w)):
            raise InputError("c2w must be a finite 4x4 matrix", field=f"{where}.c2w")
        return CameraKey(int(d["frame"]), c2w, _finite(d["focal_px"], f"{where}.focal_px"),
                         _finite(d["lens_mm"], f"{where}.lens_mm"),
                         _finite(d.get("sensor_width_mm", DEFAULT_SENSOR_WIDTH_MM), f"{where}.sensor_width_mm"))


@dataclass
class TimeKey:
    """Timeline frame -> scene timestep (fractional allowed)."""

    frame: int
    timestep: float

    def to_dict(self) -> dict[str, Any]:
        return {"frame": int(self.frame), "timestep": float(self.timestep)}


@dataclass
class Shot:
    """One shot of the highlight.

    Attributes:
        name: label from the preset ("context", "zoom", ...).
        effect: "play" | "zoom_in" | "bullet_time" | "desaturate_background" | "blur_background".
        frame_start, frame_end: inclusive timeline frames.
        camera_keys: one per frame, in frame order.
        time_keys: one per frame, in frame order.
        interpolation: hint for the renderer between keys ("linear": keys are dense and already eased).
        params: the effect's resolved parameters (JSON values).
        passes: render passes this shot needs -> inclusive frame ranges.
    """

    name: str
    effect: str
    frame_start: int
    frame_end: int
    camera_keys: list[CameraKey]
    time_keys: list[TimeKey]
    interpolation: str = "linear"
    params: dict[str, Any] = field(default_factory=dict)
    passes: dict[str, list[list[int]]] = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return self.frame_end - self.frame_start + 1

    @property
    def first_pose(self) -> Pose:
        return self.camera_keys[0].pose

    @property
    def last_pose(self) -> Pose:
        return self.camera_keys[-1].pose

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "effect": self.effect, "frame_start": int(self.frame_start),
                "frame_end": int(self.frame_end), "camera_keys": [k.to_dict() for k in self.camera_keys],
                "time_keys": [k.to_dict() for k in self.time_keys], "interpolation": self.interpolation,
                "params": _jsonable(self.params)}


@dataclass
class HighlightPlan:
    """A complete highlight (see the module docstring and docs/CONTRACTS.md)."""

    scene: dict[str, Any]
    query: str
    localization: dict[str, Any]
    fps: float
    resolution: tuple[int, int]
    frame_start: int
    frame_end: int
    shots: list[Shot]
    passes: dict[str, list[list[int]]]
    desaturate: Optional[dict[str, Any]] = None
    messages: list[str] = field(default_factory=list)
    preset: Optional[str] = None
    blur: Optional[dict[str, Any]] = None

    @property
    def effects(self) -> list[str]:
        """The effects the plan contains (desaturation counts when it applies to any frame)."""
        out = [s.effect for s in self.shots]
        return list(dict.fromkeys(out))

    def to_dict(self) -> dict[str, Any]:
        fps = int(self.fps) if float(self.fps).is_integer() else float(self.fps)
        return {
            "format": PLAN_FORMAT, "version": PLAN_VERSION,
            "scene": _jsonable(self.scene), "query": self.query,
            "localization": _jsonable(self.localization),
            "fps": fps, "resolution": [int(self.resolution[0]), int(self.resolution[1])],
            "frame_start": int(self.frame_start), "frame_end": int(self.frame_end),
            "shots": [s.to_dict() for s in self.shots],
            "passes": {k: [[int(a), int(b)] for a, b in v] for k, v in self.passes.items()},
            "desaturate": _jsonable(self.desaturate),
            "blur": _jsonable(self.blur),
            "messages": list(self.messages),
            "preset": self.preset,
        }

    def to_json(self, indent: int | None = 2) -> str:
        return json.dumps(self.to_dict(), indent=indent, allow_nan=False)

    def save(self, path: str | Path, *, overwrite: bool = False) -> None:
        write_json_atomic(path, self.to_dict(), overwrite=overwrite)

    @staticmethod
    def from_dict(d: dict[str, Any], file: str | Path | None = None) -> "HighlightPlan":
        """Parse and validate a plan dictionary; problems raise :class:`InputError` naming the field."""
        try:
            if d.get("format") != PLAN_FORMAT:
                raise InputError(f"expected {PLAN_FORMAT!r}, got {d.get('format')!r}", file=file, field="format")
            if d.get("version") != PLAN_VERSION:
                raise InputError(f"unsupported plan version {d.get('version')!r} (this engine reads "
                                 f"{PLAN_VERSION})", file=file, field="version")
            shots = []
            for i, s in enumerate(d["shots"]):
                where = f"shots[{i}]"
                shots.append(Shot(
                    name=str(s["name"]), effect=str(s["effect"]), frame_start=int(s["frame_start"]),
                    frame_end=int(s["frame_end"]),
                    camera_keys=[CameraKey.from_dict(k, f"{where}.camera_keys[{j}]")
                                 for j, k in enumerate(s["camera_keys"])],
                    time_keys=[TimeKey(int(k["frame"]), _finite(k["timestep"], f"{where}.time_keys[{j}]"))
                               for j, k in enumerate(s["time_keys"])],
                    interpolation=str(s.get("interpolation", "linear")), params=dict(s.get("params", {}))))
            res = d["resolution"]
            plan = HighlightPlan(
                scene=dict(d["scene"]), query=str(d["query"]), localization=dict(d["localization"]),
                fps=_finite(d["fps"], "fps"), resolution=(int(res[0]), int(res[1])),
                frame_start=int(d["frame_start"]), frame_end=int(d["frame_end"]), shots=shots,
                passes={str(k): [[int(a), int(b)] for a, b in v] for k, v in d.get("passes", {}).items()},
                desaturate=d.get("desaturate"), messages=[str(m) for m in d.get("messages", [])],
                preset=d.get("preset"), blur=d.get("blur"))
        except InputError as exc:
            if exc.file is None and file is not None:
                raise InputError(exc.problem, file=file, field=exc.field) from None
            raise
        except KeyError as exc:
            raise InputError(f"missing key {exc}", file=file) from None
        except (TypeError, ValueError, IndexError) as exc:
            raise InputError(f"malformed plan ({exc})", file=file) from None
        return plan.validate(file)

    @staticmethod
    def load(path: str | Path) -> "HighlightPlan":
        return HighlightPlan.from_dict(read_json(path), file=path)

    def validate(self, file: str | Path | None = None) -> "HighlightPlan":
        """Check the invariants the renderer relies on (contiguous dense keys, proper rotations...)."""
        def bad(problem: str, where: str) -> InputError:
            return InputError(problem, file=file, field=where)

        if self.fps <= 0:
            raise bad(f"must be positive, got {self.fps}", "fps")
        if self.resolution[0] <= 0 or self.resolution[1] <= 0:
            raise bad(f"must be positive, got {list(self.resolution)}", "resolution")
        expected = self.frame_start
        for i, s in enumerate(self.shots):
            where = f"shots[{i}]"
            if s.frame_start != expected or s.frame_end < s.frame_start:
                raise bad(f"frames {s.frame_start}..{s.frame_end} do not continue the timeline at {expected}",
                          where)
            frames = list(range(s.frame_start, s.frame_end + 1))
            if [k.frame for k in s.camera_keys] != frames:
                raise bad("needs exactly one camera key per frame, in order", f"{where}.camera_keys")
            if [k.frame for k in s.time_keys] != frames:
                raise bad("needs exactly one time key per frame, in order", f"{where}.time_keys")
            c2w = np.stack([np.asarray(k.c2w, dtype=np.float64) for k in s.camera_keys])
            R = c2w[:, :3, :3]
            err = np.maximum(np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2)),
                             np.abs(np.linalg.det(R) - 1.0))
            err = np.maximum(err, np.abs(c2w[:, 3] - [0, 0, 0, 1]).max(axis=1) * 1e4)
            bad_keys = np.flatnonzero(~(err <= 1e-5) | ~np.isfinite(c2w).all(axis=(1, 2)))
            if bad_keys.size:
                raise bad("is not a rigid transform", f"{where}.camera_keys[{int(bad_keys[0])}].c2w")
            for j, k in enumerate(s.camera_keys):
                if not k.focal_px > 0:
                    raise bad(f"must be positive, got {k.focal_px}", f"{where}.camera_keys[{j}].focal_px")
            expected = s.frame_end + 1
        if self.shots and expected - 1 != self.frame_end:
            raise bad(f"is {self.frame_end} but the last shot ends at {expected - 1}", "frame_end")
        for name, ranges in self.passes.items():
            for a, b in ranges:
                if not (self.frame_start <= a <= b <= self.frame_end):
                    raise bad(f"range [{a}, {b}] lies outside the plan's frames", f"passes.{name}")
        return self

    # ------------------------------------------------------------------ convenience
    def shot_at(self, frame: int) -> Shot:
        for s in self.shots:
            if s.frame_start <= frame <= s.frame_end:
                return s
        raise InputError(f"frame {frame} is outside the plan ({self.frame_start}..{self.frame_end})", field="frame")

    def camera_key_at(self, frame: int) -> CameraKey:
        s = self.shot_at(frame)
        return s.camera_keys[frame - s.frame_start]

    def timestep_at(self, frame: int) -> float:
        s = self.shot_at(frame)
        return s.time_keys[frame - s.frame_start].timestep

    def desaturation_weight(self, frame: int) -> float:
        if not self.desaturate:
            return 0.0
        return float(self.desaturate.get("weights", {}).get(str(int(frame)), 0.0))

    def blur_weight(self, frame: int) -> float:
        if not self.blur:
            return 0.0
        return float(self.blur.get("weights", {}).get(str(int(frame)), 0.0))


def _jsonable(obj: Any) -> Any:
    """Convert numpy scalars/arrays and tuples to plain JSON values; refuse NaN/Inf."""
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        if not math.isfinite(v):
            raise InputError(f"non-finite value {v} cannot be written to a plan", field="plan")
        return v
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot serialize {type(obj).__name__} in a highlight plan")
