"""Easing curves and time remapping between the scene clock and the output timeline.

Two clocks meet in a highlight: the *scene* clock (timesteps of the capture, ``scene_fps`` per second)
and the *output* timeline (frames of the video, ``output_fps`` per second, numbered from
``frame_start``). A shot plays scene time from ``t_from`` to ``t_to`` at a playback ``speed``
(1 = real time, 0.5 = half-speed slow motion, 0 = frozen); these helpers turn that into a whole
number of output frames and one fractional timestep per frame.
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np

from ..errors import InputError

# Rounding to whole frames: a duration is rounded to the nearest frame, ties up, after removing
# float noise (e.g. 2.5 s * 24 fps = 59.99999 -> 60 frames).
_FRAME_EPS = 1e-6


def _clip01(s: np.ndarray | float) -> np.ndarray:
    return np.clip(np.asarray(s, dtype=np.float64), 0.0, 1.0)


def linear(s):
    return _clip01(s)


def smoothstep(s):
    s = _clip01(s)
    return s * s * (3.0 - 2.0 * s)


def smootherstep(s):
    s = _clip01(s)
    return s * s * s * (s * (6.0 * s - 15.0) + 10.0)


def ease_in_out_sine(s):
    return 0.5 - 0.5 * np.cos(math.pi * _clip01(s))


def ease_in_out_cubic(s):
    s = _clip01(s)
    return np.where(s < 0.5, 4.0 * s ** 3, 1.0 - (-2.0 * s + 2.0) ** 3 / 2.0)


def ease_in_cubic(s):
    return _clip01(s) ** 3


def ease_out_cubic(s):
    return 1.0 - (1.0 - _clip01(s)) ** 3


EASINGS: dict[str, Callable] = {
    "linear": linear,
    "smoothstep": smoothstep,
    "smootherstep": smootherstep,
    "ease_in_out_sine": ease_in_out_sine,
    "ease_in_out_cubic": ease_in_out_cubic,
    "ease_in_cubic": ease_in_cubic,
    "ease_out_cubic": ease_out_cubic,
}


def ease(name: str, s) -> np.ndarray:
    """Apply the easing curve ``name`` to progress values ``s`` (any shape; clipped to [0,1]).

    Every curve maps 0 -> 0 and 1 -> 1 and is monotone non-decreasing.
    """
    try:
        fn = EASINGS[name]
    except KeyError:
        raise InputError(f"unknown easing {name!r} (one of {', '.join(EASINGS)})", field="easing") from None
    return np.asarray(fn(s), dtype=np.float64)


def progress(n: int) -> np.ndarray:
    """(n,) progress values 0..1 for n frames (a single frame is at progress 1: the shot's end state)."""
    if n <= 0:
        raise InputError(f"a shot needs at least one frame, got {n}", field="frames")
    if n == 1:
        return np.ones(1)
    return np.linspace(0.0, 1.0, n)


def check_fps(fps: float, field: str = "fps") -> float:
    fps = float(fps)
    if not math.isfinite(fps) or fps <= 0:
        raise InputError(f"frame rate must be a positive finite number, got {fps}", field=field)
    return fps


#: the most output frames one shot may have (69 minutes at 24 fps): more is a typo, not a highlight, and
#: would take hours of planning and days of rendering
MAX_SHOT_FRAMES = 100_000


def bounded_frames(frames: float, what: str) -> int:
    """``frames`` as an int, or InputError when it exceeds :data:`MAX_SHOT_FRAMES`."""
    if not frames <= MAX_SHOT_FRAMES:
        raise InputError(f"{what} needs {frames:.4g} frames, more than the {MAX_SHOT_FRAMES} a shot may have; "
                         "lower the frame rate or the duration", field="frames")
    return int(frames)


def frames_for_duration(seconds: float, fps: float, *, minimum: int = 1) -> int:
    """Whole output frames for ``seconds`` at ``fps``: nearest frame (ties up), at least ``minimum``.

    >>> frames_for_duration(2.5, 24), frames_for_duration(1.0, 23.976), frames_for_duration(0.0, 24)
    (60, 24, 1)
    """
    fps = check_fps(fps)
    seconds = float(seconds)
    if not math.isfinite(seconds) or seconds < 0:
        raise InputError(f"duration must be a finite number >= 0 seconds, got {seconds}", field="duration_s")
    frames = bounded_frames(math.floor(seconds * fps + 0.5 + _FRAME_EPS), f"{seconds:g} s at {fps:g} fps")
    return max(int(minimum), frames)


def seconds_to_timesteps(seconds: float, scene_fps: float) -> float:
    """Scene-clock offset in (fractional) timesteps."""
    return float(seconds) * check_fps(scene_fps, "scene fps")


def clamp_timestep(t: float, num_timesteps: int) -> float:
    """Clamp a fractional timestep into [0, T-1]."""
    return float(min(max(float(t), 0.0), float(max(num_timesteps - 1, 0))))


def play_frame_count(t_from: float, t_to: float, *, scene_fps: float, output_fps: float, speed: float,
                     minimum: int = 1) -> int:
    """Output frames needed to play scene time ``t_from``..``t_to`` at ``speed`` x real time.

    The span covers ``|t_to - t_from|`` timestep intervals, i.e. that many / scene_fps seconds of scene
    time, shown over that / speed seconds of output. The endpoints are both shown, so a span of k
    output frame intervals needs k+1 frames. ``speed`` <= 0 means frozen (``minimum`` frames).
    """
    scene_fps = check_fps(scene_fps, "scene fps")
    output_fps = check_fps(output_fps, "output fps")
    speed = float(speed)
    if not math.isfinite(speed):
        raise InputError(f"speed must be finite, got {speed}", field="speed")
    span = abs(float(t_to) - float(t_from))
    if speed <= 0 or span == 0:
        return max(1, int(minimum))
    intervals = span / scene_fps / speed * output_fps
    frames = bounded_frames(math.floor(intervals + 0.5 + _FRAME_EPS) + 1,
                            f"playing {span:g} timesteps at {speed:g}x and {output_fps:g} fps")
    return max(int(minimum), frames)


def remap_time(t_from: float, t_to: float, n: int, *, hold_frames: int = 0) -> np.ndarray:
    """(n,) fractional timesteps running linearly from ``t_from`` to ``t_to`` over n frames.

    With ``hold_frames`` > 0 the first frames hold ``t_from`` (used when a shot is longer than its
    time span, e.g. a lead-in clipped by the start of the sequence). Constant time when n == 1.
    """
    if n <= 0:
        raise InputError(f"a shot needs at least one frame, got {n}", field="frames")
    hold = int(min(max(hold_frames, 0), n - 1))
    moving = n - hold
    if moving <= 1:
        run = np.full(moving, float(t_to))
    else:
        run = np.linspace(float(t_from), float(t_to), moving)
    return np.concatenate([np.full(hold, float(t_from)), run])


def effective_speed(t_from: float, t_to: float, n: int, *, scene_fps: float, output_fps: float) -> float:
    """The playback speed actually achieved after rounding to n frames (0 when frozen)."""
    if n <= 1 or t_to == t_from:
        return 0.0
    return abs(t_to - t_from) / scene_fps / ((n - 1) / output_fps)
