"""The 4D method (4-LEGS) in the grounding benchmark: answers from the distilled 4D language field.

Temporal localization is view-independent (computed once per query on the volumetric latents, paper
§3.2) and every view uses the same frames; spatial maps are per view (exact: rendered 128-channel
latents decoded per pixel; fast: 1-channel per-Gaussian relevancy render). One render and one decode
per (view, timestep) serves all queries; a view's maps are kept while that view is scored.
"""
from __future__ import annotations

import time
from typing import Any

import numpy as np

from fourlegs_engine.query.engine import QueryEngine, QueryOptions
from .query_fixtures import scene_with_field
from fourlegs_engine.query.spatial import best_component_bbox
from fourlegs_engine.scene.camera import Camera
from .baseline2d import ViewPrediction, inclusive_to_exclusive

METHOD_NAME = "4D (4-LEGS)"


class FourLegsMethod:
    """Grounding with :class:`~fourlegs_engine.query.engine.QueryEngine`.

    Args:
        context: the benchmark context (scene, queries, encoders).
        field: a language field to use (default: the bundle's, distilled with the context's video
            encoder if missing).
        engine_options: fields of :class:`QueryOptions` (path, spatial, temporal_stride, ...), and
            ``codebook`` / ``codebook_dir`` of :class:`QueryEngine`.
    """

    name = METHOD_NAME

    def __init__(self, context: Any, field: Any = None, *, shared: dict | None = None,
                 temporal_key: Any = None, map_key: Any = None, **engine_options: Any):
        """``shared`` (with ``temporal_key`` / ``map_key``) lets several configurations that compute
        identical temporal results or maps reuse them; each reuse is charged the seconds it took."""
        scene = context.scene
        if field is None:
            scene, field, _ = scene_with_field(scene, context.video_encoder, progress=context.progress)
        prebuilt = {k: engine_options.pop(k) for k in ("codebook", "codebook_dir") if k in engine_options}
        self.engine = QueryEngine(scene, field, context.text_encoder, QueryOptions.exact(codebook_refine=0.0).replace(**engine_options), **prebuilt)
        self.queries = list(context.queries)
        self._temporal = None
        self._maps: dict[int, np.ndarray] = {}
        self._maps_camera: str | None = None
        self.timings = {"temporal": 0.0, "maps": 0.0}
        self.shared = shared
        self.temporal_key = temporal_key
        self.map_key = map_key

    def temporal(self):
        if self._temporal is None:
            key = ("temporal", self.temporal_key)
            if self.shared is not None and self.temporal_key is not None and key in self.shared:
                self._temporal, seconds = self.shared[key]
            else:
                start = time.perf_counter()
                self._temporal = dict(zip(self.queries, self.engine.temporal_many(self.queries)))
                seconds = time.perf_counter() - start
                if self.shared is not None and self.temporal_key is not None:
                    self.shared[key] = (self._temporal, seconds)
            self.timings["temporal"] += seconds
        return self._temporal

    def _view_maps(self, camera: Camera, t: int) -> np.ndarray:
        """(Q,H,W) float16 relevancy of every query at ``t`` in ``camera`` at full camera resolution."""
        if self._maps_camera != camera.name:
            self._maps, self._maps_camera = {}, camera.name
        if t not in self._maps:
            key = ("maps", self.map_key, camera.name, t)
            if self.shared is not None and self.map_key is not None and key in self.shared:
                self._maps[t], seconds = self.shared[key]
            else:
                start = time.perf_counter()
                rel = self.engine.relevancy_maps(self.queries, camera, t, outputs=("relevancy",))["relevancy"]
                if rel.shape[1:] != (camera.height, camera.width):
                    rel = _upsample(rel, camera.height, camera.width)
                self._maps[t] = rel.astype(np.float16)
                seconds = time.perf_counter() - start
                if self.shared is not None and self.map_key is not None:
                    self.shared[key] = (self._maps[t], seconds)
            self.timings["maps"] += seconds
        return self._maps[t]

    def predict_view(self, context: Any, camera: Camera) -> dict[str, ViewPrediction]:
        out = {}
        for qi, text in enumerate(self.queries):
            res = self.temporal()[text]
            out[text] = ViewPrediction(
                frames=np.asarray(res.positive, dtype=bool), scores=np.asarray(res.scores, dtype=np.float64),
                relevancy_map=lambda t, qi=qi, cam=camera: self._view_maps(cam, int(t))[qi].astype(np.float32),
                box=lambda t, qi=qi, cam=camera: inclusive_to_exclusive(
                    best_component_bbox(self._view_maps(cam, int(t))[qi].astype(np.float32))))
        return out


def _upsample(maps: np.ndarray, height: int, width: int) -> np.ndarray:
    """(Q,h,w) -> (Q,H,W) bilinear (maps rendered at a reduced resolution scale)."""
    import torch
    import torch.nn.functional as F

    t = torch.from_numpy(np.ascontiguousarray(maps, dtype=np.float32))[None]
    return F.interpolate(t, size=(height, width), mode="bilinear", align_corners=False)[0].numpy()


def register() -> None:
    from .grounding import _METHODS, register_method

    if METHOD_NAME not in _METHODS:
        register_method(METHOD_NAME, FourLegsMethod)
