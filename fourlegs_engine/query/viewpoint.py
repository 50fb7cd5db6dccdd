"""Best viewpoint (paper §6.1): the camera whose relevancy map has the highest mean relevancy.

:func:`best_view_confirmed` finds it coarse to fine: every camera's map at reduced resolution, then the few
best again at full resolution (the mean of a map changes little with its resolution, so the reduced maps
rank the cameras and the full ones decide among the close ones)."""
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


def best_view_confirmed(cameras: Sequence[Camera], relevancy_of: Callable[[Camera, bool], np.ndarray], t: int,
                        confirm: int) -> ViewResult:
    """:func:`best_view` from reduced maps (``relevancy_of(camera, True)``), then the ``confirm`` best cameras
    (ties to the earlier) re-scored from full maps (``relevancy_of(camera, False)``); the best of those wins.

    Returns:
        the result whose ``scores`` hold the full-resolution score of the confirmed cameras and the
        reduced one of the others; ``confirmed`` lists the names of the cameras scored at full resolution.
    """
    reduced = best_view(cameras, lambda cam: relevancy_of(cam, True), t)
    if reduced.best is None:
        return reduced
    names = list(reduced.scores)
    order = sorted(range(len(names)), key=lambda i: (-reduced.scores[names[i]], i))[:max(1, int(confirm))]
    order.sort()  # full-resolution ties go to the earlier camera, as in best_view
    scores = dict(reduced.scores)
    for i in order:
        m = np.asarray(relevancy_of(cameras[i], False), dtype=np.float64)
        scores[names[i]] = float(m.mean()) if m.size else 0.0
    idx = max(order, key=lambda i: (scores[names[i]], -i))
    return ViewResult(best=names[idx], index=idx, scores=scores, t=int(t), confirmed=[names[i] for i in order])
