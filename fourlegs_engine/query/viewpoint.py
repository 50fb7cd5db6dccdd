"""Best viewpoint (paper §6.1): the camera whose relevancy map holds the most relevancy.

Two scores (:data:`VIEW_SCORES`): ``"mean"`` is the paper's, the mean of the map; ``"relevant"`` is the
mean of the part above 0.5, ``mean(max(R - 0.5, 0))``: the relevant pixels' mass. Where the subject is
small (a ball covers 0.3 % of a frame) the paper's mean is decided by the relevancy of the
background, 0.1 or so everywhere but varying from camera to camera by more than the subject adds, so it
can pick a view in which the subject is barely visible; the relevant mass ranks the views by how much of
the subject they show. When no camera has a pixel above 0.5, "relevant" falls back to the mean.

:func:`best_view_confirmed` finds it coarse to fine: every camera's map at reduced resolution, then the few
best again at full resolution (the mean of a map changes little with its resolution, so the reduced maps
rank the cameras and the full ones decide among the close ones). It asks for maps a batch at a time (all
cameras reduced, then the confirmed ones), so the caller may render a batch's maps concurrently."""
from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from ..scene.camera import Camera
from .results import ViewResult

VIEW_SCORES = ("relevant", "mean")


def view_score(relevancy: np.ndarray, score: str) -> float:
    """One camera's score from its (H,W) relevancy map: the mean ("mean") or the mean of the part above
    0.5 ("relevant"); 0 for an empty map."""
    m = np.asarray(relevancy, dtype=np.float64)
    if not m.size:
        return 0.0
    if score == "relevant":
        return float(np.clip(m - 0.5, 0.0, None).mean())
    return float(m.mean())


def camera_name(camera: Camera, index: int) -> str:
    """The camera's name, or ``camera{index:02d}`` when it has none."""
    return camera.name or f"camera{index:02d}"


def best_view(cameras: Sequence[Camera], relevancy_of: Callable[[Camera], np.ndarray], t: int,
              score: str = "mean") -> ViewResult:
    """Score every camera by :func:`view_score` of ``relevancy_of(camera)`` (an (H,W) map) and pick the
    best ("relevant" falls back to "mean" when every camera scores 0).

    Ties go to the earlier camera; an empty camera list gives ``best=None``.
    """
    return best_view_of_maps(cameras, [relevancy_of(cam) for cam in cameras], t, score)


def best_view_of_maps(cameras: Sequence[Camera], maps: Sequence[np.ndarray], t: int,
                      score: str = "mean") -> ViewResult:
    """:func:`best_view` of already rendered maps, ``maps[i]`` the (H,W) relevancy of ``cameras[i]``."""
    maps = [np.asarray(m, dtype=np.float64) for m in maps]
    score = _usable_score(maps, score)
    scores = {camera_name(cam, i): view_score(m, score) for i, (cam, m) in enumerate(zip(cameras, maps))}
    if not scores:
        return ViewResult(best=None, index=None, scores={}, t=int(t))
    names = list(scores)
    idx = int(np.argmax([scores[n] for n in names]))
    return ViewResult(best=names[idx], index=idx, scores=scores, t=int(t))


def best_view_confirmed(cameras: Sequence[Camera],
                        maps_of: Callable[[Sequence[Camera], bool], Sequence[np.ndarray]], t: int,
                        confirm: int, score: str = "mean") -> ViewResult:
    """:func:`best_view` from reduced maps (``maps_of(cameras, True)``: one (H,W) map per camera, in order),
    then the ``confirm`` best cameras (ties to the earlier) re-scored from full maps (``maps_of(those,
    False)``); the best of those wins.

    Returns:
        the result whose ``scores`` hold the full-resolution score of the confirmed cameras and the
        reduced one of the others; ``confirmed`` lists the names of the cameras scored at full resolution.
    """
    reduced_maps = [np.asarray(m, dtype=np.float64) for m in maps_of(list(cameras), True)]
    reduced = best_view_of_maps(cameras, reduced_maps, t, score)
    if reduced.best is None:
        return reduced
    score = _usable_score(reduced_maps, score)
    names = list(reduced.scores)
    order = sorted(range(len(names)), key=lambda i: (-reduced.scores[names[i]], i))[:max(1, int(confirm))]
    order.sort()  # full-resolution ties go to the earlier camera, as in best_view
    scores = dict(reduced.scores)
    for i, full in zip(order, maps_of([cameras[i] for i in order], False)):
        scores[names[i]] = view_score(full, score)
    idx = max(order, key=lambda i: (scores[names[i]], -i))
    return ViewResult(best=names[idx], index=idx, scores=scores, t=int(t), confirmed=[names[i] for i in order])


def _usable_score(maps: Sequence[np.ndarray], score: str) -> str:
    """``score``, or "mean" where it is "relevant" and no map has a pixel above 0.5."""
    if score == "relevant" and not any(m.size and float(m.max()) > 0.5 for m in maps):
        return "mean"
    return score
