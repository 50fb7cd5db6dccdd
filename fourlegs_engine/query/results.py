"""Result types of the query engine (re-exported by ``query.engine`` and ``query``)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np


@dataclass
class TemporalResult:
    """When a query happens.

    Attributes:
        scores: (T,) s_t, the share of above-average relevant Gaussians at each timestep (sums to 1,
            or all zeros when nothing is relevant).
        positive: (T,) bool, s_t > 1/T.
        segments: every positive run after dilation, [(start, end)] inclusive, in time order.
        segment: the longest of them, or None.
        peak: the centre timestep of ``segment``, or None.
        found: whether any timestep is positive.
        message: why nothing was found (empty when found).
        r_avg: the mean relevancy of the relevant (R > 0.5) Gaussians (0 when there are none).
        num_relevant: how many (Gaussian, timestep) pairs have R > 0.5 (on the sampled timesteps).
        timesteps: the timesteps actually scored (all, or every k-th with a temporal stride).
        undecided: scored timesteps whose decision s_t > 1/T the codebook path left open: their counts lie
            within R_avg's error of the mean count, so the exact path (``path="exact"``) may decide them,
            and the segment ends next to them, otherwise (always empty on the exact path).
    """

    scores: np.ndarray
    positive: np.ndarray
    segments: list[tuple[int, int]]
    segment: Optional[tuple[int, int]]
    peak: Optional[int]
    found: bool
    message: str = ""
    r_avg: float = 0.0
    num_relevant: int = 0
    timesteps: Optional[np.ndarray] = None
    undecided: list[int] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {
            "found": bool(self.found), "message": self.message,
            "segment": None if self.segment is None else [int(self.segment[0]), int(self.segment[1])],
            "peak": None if self.peak is None else int(self.peak),
            "segments": [[int(a), int(b)] for a, b in self.segments],
            "scores": [float(s) for s in self.scores],
            "positive": [bool(p) for p in self.positive],
            "r_avg": float(self.r_avg), "num_relevant": int(self.num_relevant),
            "timesteps": None if self.timesteps is None else [int(t) for t in self.timesteps],
            "undecided": [int(t) for t in self.undecided],
        }


@dataclass
class ViewResult:
    """The best viewpoint: ``best`` camera name, its index, every camera's mean relevancy, and the cameras
    whose score is the full-resolution one when the others were scored at reduced resolution."""

    best: Optional[str]
    index: Optional[int]
    scores: dict[str, float]
    t: int
    confirmed: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {"best": self.best, "index": self.index, "t": int(self.t),
                "scores": {k: float(v) for k, v in self.scores.items()}, "confirmed": list(self.confirmed)}


@dataclass
class CentreResult:
    """Where the action is in one view: 2D centre of mass, its depth and the 3D point.

    Attributes:
        centre_px: (2,) pixel coordinates (x, y) of the relevancy centre of mass, or None.
        centre_3d: (3,) world point lifted with the rendered depth, or None.
        depth: camera-z depth used for the lift (0 when unknown).
        bbox: (x0, y0, x1, y1) inclusive pixel box of the best connected component, or None.
        camera: name of the view.
        t: timestep.
        message: why something is missing (empty otherwise).
    """

    centre_px: Optional[np.ndarray]
    centre_3d: Optional[np.ndarray]
    depth: float
    bbox: Optional[tuple[int, int, int, int]]
    camera: str
    t: int
    message: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {"centre_px": _list(self.centre_px), "centre_3d": _list(self.centre_3d),
                "depth": float(self.depth), "bbox": None if self.bbox is None else [int(v) for v in self.bbox],
                "camera": self.camera, "t": int(self.t), "message": self.message}


@dataclass
class Localization:
    """Everything ``QueryEngine.localize`` was asked for; parts not asked for stay None/empty."""

    query: str
    scene: str
    temporal: Optional[TemporalResult]
    best_view: Optional[str] = None
    view_scores: dict[str, float] = field(default_factory=dict)
    action_centre: Optional[np.ndarray] = None
    centre_px: Optional[np.ndarray] = None
    bbox: Optional[tuple[int, int, int, int]] = None
    timings: dict[str, float] = field(default_factory=dict)
    t: Optional[int] = None
    messages: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        tmp = self.temporal.to_dict() if self.temporal is not None else None
        return {
            "query": self.query, "scene": self.scene,
            "found": None if tmp is None else tmp["found"],
            "message": "" if tmp is None else tmp["message"],
            "segment": None if tmp is None else tmp["segment"],
            "peak": None if tmp is None else tmp["peak"],
            "segments": [] if tmp is None else tmp["segments"],
            "scores": [] if tmp is None else tmp["scores"],
            "temporal": tmp,
            "t": self.t,
            "best_view": self.best_view,
            "view_scores": {k: float(v) for k, v in self.view_scores.items()},
            "action_centre": _list(self.action_centre),
            "centre_px": _list(self.centre_px),
            "bbox": None if self.bbox is None else [int(v) for v in self.bbox],
            "timings": {k: float(v) for k, v in self.timings.items()},
            "messages": list(self.messages),
        }


def _list(a) -> Optional[list[float]]:
    return None if a is None else [float(v) for v in np.asarray(a).reshape(-1)]
