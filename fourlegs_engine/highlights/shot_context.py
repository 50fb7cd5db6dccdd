"""The contract between the planner and a shot builder: what a builder may use (:class:`ShotContext`,
filled with only what was computed) and what it returns (:class:`ShotPath`)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Optional

import numpy as np

from ..errors import InputError
from . import timing
from .camera_paths import WORLD_UP, Pose
from .framing import Framing


@dataclass
class ShotContext:
    """What a shot builder may use (filled by the planner with only what was computed).

    Attributes:
        num_timesteps, scene_fps, output_fps: the two clocks.
        segment: (start, end) inclusive timesteps of the localized action, or None.
        peak: peak timestep, or None.
        action_centre: (3,) world point, or None.
        anchor: the best view's pose (re-aimed at the action centre when it is known), or None.
        anchor_focal: its focal length in output pixels.
        previous: the previous shot's last pose, or None for the first shot.
        previous_focal: the previous shot's last focal length (output pixels).
        camera_pose: resolves a scene camera name to (pose, focal) at output resolution.
        up: (3,) the scene's up direction (orbits turn about it, swings pivot about it).
        framing: the action region and the scene's Gaussians at the peak (:mod:`.framing`), or None
            (then zoom and orbit follow the best view's geometry alone).
        resolution: (width, height) of the output.
    """

    num_timesteps: int
    scene_fps: float
    output_fps: float
    segment: Optional[tuple[int, int]] = None
    peak: Optional[int] = None
    action_centre: Optional[np.ndarray] = None
    anchor: Optional[Pose] = None
    anchor_focal: Optional[float] = None
    previous: Optional[Pose] = None
    previous_focal: Optional[float] = None
    camera_pose: Optional[Callable[[str], tuple[Pose, float]]] = None
    up: np.ndarray = field(default_factory=lambda: WORLD_UP.copy())
    framing: Optional[Framing] = None
    resolution: tuple[int, int] = (1280, 720)
    messages: list[str] = field(default_factory=list)

    def timestep(self, anchor: str, offset_s: float) -> float:
        base = {"start": 0.0, "end": float(self.num_timesteps - 1)}.get(anchor)
        if base is None:
            value = {"segment_start": None if self.segment is None else self.segment[0],
                     "segment_end": None if self.segment is None else self.segment[1],
                     "peak": self.peak}[anchor]
            if value is None:
                raise InputError(f"time anchor {anchor!r} needs a temporal localization", field="from/to")
            base = float(value)
        return timing.clamp_timestep(base + timing.seconds_to_timesteps(offset_s, self.scene_fps),
                                     self.num_timesteps)

    def start_camera(self) -> tuple[Pose, float]:
        if self.previous is not None:
            return self.previous, float(self.previous_focal)
        if self.anchor is None:
            raise InputError("the first shot needs a camera (best view not computed)", field="camera")
        return self.anchor, float(self.anchor_focal)

    def require_centre(self, effect: str) -> np.ndarray:
        if self.action_centre is None:
            raise InputError(f"effect {effect!r} needs the 3D action centre", field="action_centre")
        return self.action_centre


@dataclass
class ShotPath:
    """A built shot: per-frame poses, focal lengths (output px) and fractional timesteps."""

    poses: list[Pose]
    focals: np.ndarray
    timesteps: np.ndarray
    params: dict[str, Any]
    desaturation: Optional[np.ndarray] = None  # (n,) weights in [0,1] or None
    blur: Optional[np.ndarray] = None  # (n,) blur weights in [0,1] or None

    def __post_init__(self) -> None:
        n = len(self.poses)
        if len(self.focals) != n or len(self.timesteps) != n:
            raise ValueError("poses, focals and timesteps must have one entry per frame")
