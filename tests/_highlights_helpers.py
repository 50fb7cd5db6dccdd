"""Shared fixtures of the highlight tests: a tiny scene and a counting fake localizer.

The fake localizer answers from known ground truth (segment, peak, action centre, best view) and
counts, like the real ``QueryEngine.stats``, every part it computes — so tests can prove that the
planner asks for nothing the plan's effects do not need.
"""
from __future__ import annotations

import math
from collections import Counter
from typing import Optional, Sequence

import numpy as np
from fourlegs_engine.query.results import Localization, TemporalResult
from fourlegs_engine.scene import Camera, CameraRig, GaussianSequence, Scene

WIDTH, HEIGHT = 320, 180


def ring_cameras(n: int = 6, radius: float = 4.0, height: float = 1.6, target=(0.0, 0.0, 0.8),
                 focal: float = 260.0) -> list[Camera]:
    """n cameras on a circle around ``target``, looking at it (OpenCV, world up +z)."""
    cams = []
    for i in range(n):
        a = 2 * math.pi * i / n
        eye = (radius * math.cos(a), radius * math.sin(a), height)
        cams.append(Camera.look_at(eye, target, width=WIDTH, height=HEIGHT, focal=focal, name=f"cam{i:02d}"))
    return cams


def tiny_scene(T: int = 48, fps: float = 30.0, cameras: Optional[Sequence[Camera]] = None, name: str = "tiny") -> Scene:
    """A small dynamic scene: a floor patch of Gaussians and a 'ball' flying through the air."""
    rng = np.random.default_rng(0)
    floor = np.concatenate([rng.uniform(-1.5, 1.5, (60, 2)), np.zeros((60, 1))], axis=1)
    t = np.arange(T)[:, None]
    ball = np.stack([np.linspace(-1.0, 1.0, T), np.zeros(T), 0.3 + 1.2 * np.sin(np.linspace(0, math.pi, T))], 1)
    ball = ball[:, None, :] + rng.normal(0, 0.03, (1, 12, 3))
    means = np.concatenate([np.broadcast_to(floor, (T, 60, 3)), ball], axis=1).astype(np.float32)
    N = means.shape[1]
    rot = np.zeros((T, N, 4), np.float32)
    rot[..., 0] = 1
    colors = np.concatenate([np.full((60, 3), 0.5), np.tile([[0.9, 0.3, 0.1]], (12, 1))]).astype(np.float32)
    g = GaussianSequence(means=means, rotations=rot, log_scales=np.full((N, 3), math.log(0.08), np.float32),
                         opacity_logits=np.full(N, 2.0, np.float32), colors=colors)
    cams = list(cameras) if cameras is not None else ring_cameras()
    return Scene(gaussians=g, cameras=CameraRig.static(cams, [], T), name=name, fps=fps)


class FakeLocalizer:
    """Answers ``localize(query, need)`` from ground truth and counts what it computes."""

    def __init__(self, scene: Scene, *, segment=(14, 30), peak=None, centre=(0.1, 0.0, 1.3),
                 best_view: Optional[str] = "cam01", found: bool = True):
        self.scene = scene
        self.segment = tuple(segment) if segment is not None else None
        self.peak = peak if peak is not None else (None if segment is None else (segment[0] + segment[1]) // 2)
        self.centre = None if centre is None else np.asarray(centre, dtype=np.float64)
        self.best = best_view
        self.found = found
        self.stats: Counter = Counter()
        self.needs: list[set[str]] = []

    def temporal(self, query: str) -> TemporalResult:
        self.stats["temporal"] += 1
        T = self.scene.num_timesteps
        scores = np.zeros(T)
        positive = np.zeros(T, bool)
        if not self.found:
            return TemporalResult(scores, positive, [], None, None, False, "no Gaussian is relevant to the query")
        a, b = self.segment
        positive[a:b + 1] = True
        scores[a:b + 1] = 1.0 / (b - a + 1)
        return TemporalResult(scores, positive, [self.segment], self.segment, self.peak, True, "")

    def best_view(self, query: str, t: int):
        self.stats["best_view"] += 1
        self.stats["relevancy_map"] += self.scene.cameras.num_cameras("train")  # one map per camera
        return self.best

    def action_centre(self, query: str, t: int, camera) -> Optional[np.ndarray]:
        self.stats["action_centre"] += 1
        self.stats["relevancy_map"] += 1
        return self.centre

    def localize(self, query: str, need: set[str]) -> Localization:
        self.stats["localize"] += 1
        self.needs.append(set(need))
        tmp = self.temporal(query) if "temporal" in need else None
        t = tmp.peak if tmp is not None and tmp.peak is not None else 0
        found = tmp is None or tmp.found
        best = self.best_view(query, t) if ("best_view" in need or "action_centre" in need) and found else None
        centre = self.action_centre(query, t, best) if "action_centre" in need and found else None
        return Localization(query=query, scene=self.scene.name, temporal=tmp, best_view=best,
                            action_centre=centre, t=t)

    def relevancy_map(self, query: str, camera: Camera, t: int, fast: bool = False,
                      outputs=("relevancy", "depth", "alpha")) -> dict:
        """A blob around the projected action centre (stands in for a rendered relevancy map)."""
        self.stats["relevancy_map"] += 1
        H, W = camera.height, camera.width
        yy, xx = np.mgrid[0:H, 0:W] + 0.5
        uv, z = camera.project(self.centre[None])
        sigma = 0.08 * max(H, W)
        rel = np.exp(-((xx - uv[0, 0]) ** 2 + (yy - uv[0, 1]) ** 2) / (2 * sigma ** 2)) * float(z[0] > 0)
        return {"relevancy": rel.astype(np.float32)}
