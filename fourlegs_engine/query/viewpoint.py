"""Best viewpoint (paper §6.1): the camera whose relevancy map has the highest mean relevancy."""
from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from ..scene.camera import Camera
from .results import ViewResult


def camera_name(camera: Camera, index: int) -> str:
    """The camera's name, or ``camera{index:02d}`` when it has none."""
    return camera.name or f"camera{index:02d}"


def best_view(cameras: Sequence[Camera], relevancy_of: Callable[[Camera], np.ndarray], t: int) -> ViewResult:
    """Score every camera by the mean of ``relevancy_of(camera)`` (an (H,W) map) and pick the best.

    Ties go to the earlier camera; an empty camera list gives ``best=None``.
    """
    scores: dict[str, float] = {}
    for i, cam in enumerate(cameras):
        m = np.asarray(relevancy_of(cam), dtype=np.float64)
        scores[camera_name(cam, i)] = float(m.mean()) if m.size else 0.0
    if not scores:
        return ViewResult(best=None, index=None, scores={}, t=int(t))
    names = list(scores)
    idx = int(np.argmax([scores[n] for n in names]))
    return ViewResult(best=names[idx], index=idx, scores=scores, t=int(t))
