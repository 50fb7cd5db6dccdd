"""``QueryEngine``: when and where a text query happens in a scene with a distilled language field.

Paths (each selectable, each measured against the exact one by ``fourlegs bench accuracy-time``):

* temporal / per-Gaussian relevancy — ``path="exact"`` decodes every latent (streamed in chunks, never
  T x N x 768 at once); ``path="codebook"`` decodes only the K codes (once per engine) and scores
  Gaussians by lookup, a temporal query being a (T,K) histogram reduction; ``codebook_refine`` > 0
  re-scores exactly a sample (for R_avg) and, where a timestep's decision depends on them, the Gaussians
  of codes whose relevancy is that close to R_avg; ``path="sketch"`` (the default) bounds every pair's
  relevancy from a per-pair sketch of the relevancy head (:mod:`.sketch`) and scores exactly only the
  pairs whose bounds straddle a decision and a sample for R_avg (:mod:`.sketch_path`); its per-Gaussian
  relevancy is the sketch's value, exact where its bound straddles 0.5;
* ``temporal_stride`` scores every k-th timestep only;
* spatial maps — ``spatial="exact"`` renders the 128-channel latents, decodes every pixel and scores
  it (paper §3.2); ``spatial="fast"`` renders one channel, the per-Gaussian relevancy;
* ``resolution_scale`` renders the maps at a fraction of the camera resolution.

The engine is thin: :class:`~.scoring.LatentScorer` embeds and scores latents,
:class:`~.temporal_pass.ExactTemporalPass`, :class:`~.codebook_path.CodebookPath` and
:class:`~.sketch_path.SketchPath` answer the temporal question on their path, :class:`~.maps.SpatialMaps` renders the maps. Every public method counts its calls (and the heavy work it did: decoded latents, decoded pixels,
128- and 1-channel renders) in ``.stats`` so callers can prove nothing was computed that was not asked
for; ``localize(query, need)`` computes only the parts named in ``need``.
"""
from __future__ import annotations

import time
from collections import Counter, deque
from pathlib import Path
from concurrent.futures import ThreadPoolExecutor
from contextlib import closing
from typing import Any, Callable, Iterable, Iterator, Optional, Sequence

import numpy as np
import torch

from ..errors import InputError
from ..scene.camera import Camera
from ..scene.scene import Scene
from ..threads import kernel_thread_count, kernel_threads, torch_threads
from ..validate import check_number
from . import viewpoint
from .codebook import Codebook
from .codebook_path import CodebookPath
from .sketch_path import SketchPath
from .head import RelevancyHead
from .maps import MAP_OUTPUTS, SpatialMaps
from .options import MAX_CODEBOOK_SIZE, MAX_RESOLUTION_SCALE, MAX_SKETCH_RANK, MAX_TIMESTEP_ARGUMENT, QUERY_PATHS, \
    QueryOptions
from .results import CentreResult, Localization, TemporalResult, ViewResult
from .scoring import LatentScorer
from .temporal import localize_counts, sampled_timesteps
from .temporal_pass import ExactTemporalPass

__all__ = ["QueryEngine", "QueryOptions", "TemporalResult", "Localization", "ViewResult", "CentreResult"]

NEEDS = frozenset({"temporal", "best_view", "action_centre"})
GAUSSIAN_CACHE_SIZE = 16  # per-Gaussian relevancy vectors (query, t) kept for reuse


class QueryEngine:
    """Answer text queries on one scene.

    Args:
        scene: the scene (geometry and cameras).
        field: the distilled language field (``.latents`` (T,N,d), ``.decode(M,d)->(M,D)``,
            ``.canonical_phrases``).
        text_encoder: ``encode_text(list[str]) -> (n,D)`` of the encoder the field was distilled from.
        options: :class:`~.options.QueryOptions` (paths, strides, scales; default: exact everywhere).
        codebook: a prebuilt :class:`Codebook` (else loaded from / stored in ``codebook_dir``, by default
            the bundle's ``language/`` directory, or built in memory); the sketch path's index lives in the
            same directory.
    """

    def __init__(self, scene: Scene, field: Any, text_encoder: Any, options: Optional[QueryOptions] = None, *,
                 codebook: Optional[Codebook] = None, codebook_dir: Optional[Path] = None):
        options = options if options is not None else QueryOptions()
        _check_options(options)
        latents = getattr(field, "latents", None)
        if latents is None:
            raise InputError("the scene has no distilled language field (run `fourlegs distill` first)",
                             file=scene.root, field="language")
        T, N = scene.num_timesteps, scene.num_gaussians
        if tuple(latents.shape[:2]) != (T, N):
            raise InputError(f"latents have shape {tuple(latents.shape)}, the scene has T={T}, N={N}",
                             file=scene.root, field="language.latents")
        self.options = options
        self.scene = scene
        self.field = field
        self.text_encoder = text_encoder
        self.path = options.path
        self.temporal_stride = int(options.temporal_stride)
        self.spatial = options.spatial
        self.dilation = int(options.dilation)
        self.camera_split = options.camera_split
        self.stats: Counter = Counter()
        self._progress: Optional[Callable[[float, str], None]] = None
        self._progress_span = (0.0, 1.0)
        self.scorer = LatentScorer(field, text_encoder, negatives=options.negatives,
                                   relevancy_scale=options.relevancy_scale, chunk=options.chunk,
                                   latent_dtype=None if options.latent_dtype is None else np.dtype(options.latent_dtype),
                                   stats=self.stats)
        index_dir = codebook_dir if codebook_dir is not None else (
            Path(scene.root) / "language" if scene.root is not None else None)
        self.codebook_path = CodebookPath(
            scene, self.scorer, size=options.codebook_size, refine=options.codebook_refine,
            samples=options.codebook_samples, codebook=codebook, stats=self.stats, directory=index_dir)
        self.sketch_path = SketchPath(scene, self.scorer, rank=options.sketch_rank, samples=options.codebook_samples,
                                      directory=index_dir, stats=self.stats)
        self.temporal_pass = ExactTemporalPass(self.scorer, N, self.stats)
        self.maps = SpatialMaps(scene, self.scorer, self._gaussian_relevancy_many, fast=options.spatial == "fast",
                                resolution_scale=options.resolution_scale, render_options=options.render_options,
                                render_backend=options.render_backend, stats=self.stats)
        self._gaussian_cache: dict[tuple[str, int], torch.Tensor] = {}

    # ------------------------------------------------------------------ embeddings
    @property
    def latents(self) -> Any:
        return self.field.latents

    @property
    def head(self) -> Optional[RelevancyHead]:
        """Relevancy straight from latents (None when the field's decoder has no such form)."""
        return self.scorer.head

    def embed_query(self, query: str) -> torch.Tensor:
        """(D,) L2-normalized embedding of ``query`` (cached)."""
        return self.scorer.embed_query(query)

    def reference_embeddings(self) -> tuple[torch.Tensor, Optional[torch.Tensor]]:
        """Canonical (K,D) and negative (J,D)|None phrase embeddings."""
        return self.scorer.reference_embeddings()

    def background_relevancy(self, query: str) -> float:
        """Relevancy of an empty pixel on the exact path (its rendered latent is 0)."""
        return self.scorer.background_relevancy(query)

    def forget_query(self, query: str) -> None:
        """Drop every score cached for ``query`` (code relevancies, per-Gaussian and temporal scores,
        background relevancy), keeping its text embedding: the next call redoes the query's own work."""
        self.scorer.forget(query)
        self.codebook_path.forget(query)
        self.sketch_path.forget(query)
        self.temporal_pass.forget(query)
        for key in [k for k in self._gaussian_cache if k[0] == query]:
            del self._gaussian_cache[key]

    # ------------------------------------------------------------------ codebook
    @property
    def codebook(self) -> Codebook:
        return self.codebook_path.codebook

    def load_codebook(self, progress: Optional[Callable[[float, str], None]] = None) -> Codebook:
        """The codebook, loaded or (first use) built and stored (see :meth:`CodebookPath.load`)."""
        return self.codebook_path.load(progress)

    def load_index(self, progress: Optional[Callable[[float, str], None]] = None) -> None:
        """Load (or on first use build and store) the index the query path answers from: the sketch on the
        sketch path (the codebook when the field has no relevancy head), the codebook on the codebook path,
        nothing on the exact path."""
        if self.path == "sketch" and self.sketch_path.available:
            self.sketch_path.load(progress)
        elif self.path in ("codebook", "sketch"):
            self.codebook_path.load(progress)

    # ------------------------------------------------------------------ per Gaussian
    def gaussian_relevancy(self, query: str, t: int) -> torch.Tensor:
        """(N,) relevancy of every Gaussian at timestep ``t`` (decoded volumetric latents)."""
        self.stats["gaussian_relevancy"] += 1
        return self._gaussian_relevancy(query, self.scene.gaussians.check_timestep(t)).clone()

    def _gaussian_relevancy(self, query: str, t: int) -> torch.Tensor:
        key = (query, int(t))
        if key in self._gaussian_cache:  # e.g. one fast map per camera in a best-view search
            return self._gaussian_cache[key]
        kept = self.temporal_pass.scores_at(query, t)
        if kept is not None:  # decoded once by the temporal pass
            return torch.from_numpy(kept)
        if self.path == "sketch":
            sketched = self.sketch_path.relevancy_at(query, t)
            if sketched is not None:  # kept by the sketch path's temporal pass
                return sketched
        if self.scene.num_gaussians == 0:
            out = torch.zeros(0)
        elif self.path == "codebook" or (self.path == "sketch" and not self.sketch_path.available):
            out = self.codebook_path.gaussian_relevancy(query, t)
        elif self.path == "sketch":
            out = self.sketch_path.gaussian_relevancy(query, t)
        else:
            out = self.scorer.score_latents(self.scorer.read_latents(t), self.embed_query(query))
        self._gaussian_cache[key] = out
        while len(self._gaussian_cache) > GAUSSIAN_CACHE_SIZE:
            self._gaussian_cache.pop(next(iter(self._gaussian_cache)))
        return out

    def _gaussian_relevancy_many(self, queries: list[str], t: int) -> torch.Tensor:
        """(N,Q) float32 relevancy of every Gaussian at ``t`` for several queries; the latents of
        ``t`` are decoded at most once for all queries not already cached."""
        missing = [q for q in dict.fromkeys(queries) if (q, int(t)) not in self._gaussian_cache
                   and self.temporal_pass.scores_at(q, t) is None]
        if self.path == "exact" and len(missing) > 1 and self.scene.num_gaussians:
            lat = self.scorer.read_latents(int(t))
            qs = torch.stack([self.embed_query(q) for q in missing])
            chunk = self.scorer.chunk
            scores = torch.cat([self.scorer.score_latents_many(lat[s:s + chunk], qs)
                                for s in range(0, lat.shape[0], chunk)])           # (N, len(missing))
            self.stats["decoded_latents"] += int(lat.shape[0])
            for j, q in enumerate(missing):
                self._gaussian_cache[(q, int(t))] = scores[:, j].contiguous()
            while len(self._gaussian_cache) > max(GAUSSIAN_CACHE_SIZE, len(missing)):
                self._gaussian_cache.pop(next(iter(self._gaussian_cache)))
        if not queries:
            return torch.zeros(self.scene.num_gaussians, 0)
        return torch.stack([self._gaussian_relevancy(q, t).to(torch.float32) for q in queries], 1)

    # ------------------------------------------------------------------ temporal
    def temporal(self, query: str, *, stride: Optional[int] = None) -> TemporalResult:
        """When ``query`` happens: s_t, positive timesteps, segments, the longest one and its peak."""
        self.stats["temporal"] += 1
        return self._temporal([query], stride)[0]

    def temporal_many(self, queries: Sequence[str], *, stride: Optional[int] = None) -> list[TemporalResult]:
        """:meth:`temporal` for several queries, decoding each latent once (exact path)."""
        self.stats["temporal_many"] += 1
        return self._temporal(list(queries), stride)

    def _temporal(self, queries: list[str], stride: Optional[int]) -> list[TemporalResult]:
        T, N = self.scene.num_timesteps, self.scene.num_gaussians
        ts = sampled_timesteps(T, stride or self.temporal_stride)
        if N == 0:
            counts = [(np.zeros(len(ts), np.int64), 0.0, 0, np.zeros(len(ts), bool))] * len(queries)
        elif self.path == "sketch" and self.sketch_path.available:
            counts = self.sketch_path.temporal_counts(queries, ts, self._report)
        elif self.path in ("codebook", "sketch"):
            counts = self.codebook_path.temporal_counts(queries, ts, self.dilation, self._report)
        else:
            counts = self.temporal_pass.counts(queries, ts, self._report)
        return [localize_counts(c, ts, T, dilation=self.dilation, r_avg=a, num_relevant=n, query=q,
                                num_gaussians=N, undecided=u) for q, (c, a, n, u) in zip(queries, counts)]

    # ------------------------------------------------------------------ spatial
    def relevancy_map(self, query: str, camera: Camera, t: int, fast: Optional[bool] = None,
                      outputs: Iterable[str] = MAP_OUTPUTS, *, scale: Optional[float] = None) -> dict[str, np.ndarray]:
        """Per-pixel relevancy of ``query`` seen from ``camera`` at timestep ``t`` (exact or fast, see
        :mod:`.maps`).

        Returns:
            dict with the requested keys among "relevancy", "depth", "alpha": (H,W) float32 arrays at
            the (scaled) camera resolution.
        """
        self.stats["relevancy_map"] += 1
        maps = self.relevancy_maps([query], camera, t, fast=fast, outputs=outputs, scale=scale)
        if "relevancy" in maps:
            maps["relevancy"] = maps["relevancy"][0]
        return maps

    def relevancy_maps(self, queries: Sequence[str], camera: Camera, t: int, fast: Optional[bool] = None,
                       outputs: Iterable[str] = MAP_OUTPUTS, *, scale: Optional[float] = None) -> dict[str, np.ndarray]:
        """Like :meth:`relevancy_map` for several queries with one render and one per-pixel decode.

        Returns:
            "relevancy" (Q,H,W), "depth" (H,W), "alpha" (H,W) float32 (the requested ones).
        """
        self.stats["relevancy_maps"] += 1
        return self.maps.relevancy_maps(queries, camera, t, fast=fast, outputs=outputs, scale=scale)

    def cameras_at(self, t: int, split: Optional[str] = None) -> list[Camera]:
        return self.scene.cameras.cameras(t, split or self.camera_split)

    def best_view(self, query: str, t: int, cameras: Optional[Sequence[Camera]] = None) -> ViewResult:
        """The camera with the highest ``view_score`` (the relevant pixels' mass, or the paper's mean relevancy,
        §6.1) at timestep ``t``: every camera scored at
        ``view_scale`` of the map resolution, the ``view_confirm`` best re-scored at the map resolution."""
        self.stats["best_view"] += 1
        cams = list(cameras) if cameras is not None else self.cameras_at(t)
        # the relevant mass needs only the pixels above 0.5: fast maps of the relevant region give it
        # exactly; when no view has any, the score falls back to the mean, which needs the whole maps
        region = self.options.view_score == "relevant" and self.spatial == "fast"
        result, relevant_seen = self._best_view(query, t, cams, relevant_only=region)
        if region and not relevant_seen:
            result, _ = self._best_view(query, t, cams, relevant_only=False)
        return result

    def _best_view(self, query: str, t: int, cams: list[Camera], *, relevant_only: bool) -> tuple[ViewResult, bool]:
        """The best view from maps (``relevant_only``: see :meth:`.SpatialMaps.relevancy_maps`), and whether
        any map had a pixel above 0.5."""
        coarse = self.options.view_scale < 1.0 and len(cams) > self.options.view_confirm
        steps = len(cams) + (self.options.view_confirm if coarse else 0)
        seen, relevant_seen = [0], [False]

        def maps_of(batch: Sequence[Camera], reduced: bool) -> list[np.ndarray]:
            scale = self.maps.resolution_scale * (self.options.view_scale if reduced else 1.0)

            def render(cam: Camera) -> np.ndarray:
                return self.maps.relevancy_maps([query], cam, t, outputs=("relevancy",), scale=scale,
                                                relevant_only=relevant_only)["relevancy"][0]

            if self.maps.fast:  # scored and cached here, only read by the renders on the worker threads
                self._gaussian_relevancy_many([query], t)
                self.scorer.background_relevancy(query)
            maps = []
            with closing(self._map_in_threads(render, batch)) as views:  # closed (queue dropped) on a cancel
                for m in views:
                    self._report(seen[0] / max(1, steps), "scoring the views at reduced size" if reduced
                                 else "rendering the views")
                    seen[0] += 1
                    self.stats["view_maps_reduced" if reduced else "view_maps"] += 1
                    self.stats["relevancy_map"] += 1
                    relevant_seen[0] = relevant_seen[0] or bool(m.size and m.max() > 0.5)
                    maps.append(m)
            return maps

        if not coarse:
            result = viewpoint.best_view_of_maps(cams, maps_of(cams, False), t, self.options.view_score)
        else:
            result = viewpoint.best_view_confirmed(cams, maps_of, t, self.options.view_confirm,
                                                   self.options.view_score)
        return result, relevant_seen[0]

    def _map_in_threads(self, render: Callable[[Camera], np.ndarray], cams: Sequence[Camera]) -> Iterator[np.ndarray]:
        """``render(camera)`` of each camera, yielded in order in the calling thread (which reports progress
        and may cancel between them). With fast maps the views are rendered concurrently on the
        kernels' worker threads, each render single-threaded: a reduced view is too small for its own
        tiles to keep several threads busy. At most ``workers`` renders run ahead of the caller; those
        are dropped or finished when it stops early."""
        workers = min(kernel_thread_count(), len(cams))
        if workers < 2 or not self.maps.fast:
            for cam in cams:
                yield render(cam)
            return
        pool = ThreadPoolExecutor(workers)
        queued: deque = deque()
        try:
            with torch_threads(1), kernel_threads(1):
                for cam in cams:  # at most ``workers`` renders ahead of the caller
                    queued.append(pool.submit(render, cam))
                    if len(queued) > workers:
                        yield queued.popleft().result()
                while queued:
                    yield queued.popleft().result()
        finally:
            pool.shutdown(wait=True, cancel_futures=True)

    def action_centre(self, query: str, t: int, camera: Camera) -> CentreResult:
        """Centre of mass of the best relevant component of the relevancy map, lifted to 3D with the rendered
        depth; plus that component's box (the centre lies inside it)."""
        self.stats["action_centre"] += 1
        return self.maps.action_centre(self.relevancy_map(query, camera, t), camera, t)

    # ------------------------------------------------------------------ progress
    def _report(self, fraction: float, stage: str) -> None:
        """Tell the progress callback of the running :meth:`localize` (if any) how far it is; the
        callback stops the computation by raising (e.g. :class:`~fourlegs_engine.errors.Cancelled`)."""
        if self._progress is not None:
            lo, hi = self._progress_span
            self._progress(lo + (hi - lo) * min(max(float(fraction), 0.0), 1.0), stage)

    def localize(self, query: str, need: Iterable[str] = ("temporal",), *, t: Optional[int] = None,
                 camera: Optional[Camera] = None,
                 progress: Optional[Callable[[float, str], None]] = None) -> Localization:
        """See :meth:`_localize`. ``progress(fraction in [0, 1], stage)`` is called between timesteps of
        the temporal pass, rescoring chunks and rendered views; an exception it raises (e.g.
        :class:`~fourlegs_engine.errors.Cancelled`) stops the localization and propagates."""
        previous = self._progress, self._progress_span
        self._progress = progress
        try:
            return self._localize(query, need, t=t, camera=camera)
        finally:
            self._progress, self._progress_span = previous

    def _span(self, lo: float, hi: float) -> None:
        self._progress_span = (lo, hi)
        self._report(0.0, "")

    def _localize(self, query: str, need: Iterable[str] = ("temporal",), *, t: Optional[int] = None,
                  camera: Optional[Camera] = None) -> Localization:
        """Compute only what ``need`` names ({"temporal", "best_view", "action_centre"}).

        The spatial parts are evaluated at ``t`` (default: the temporal peak, which then requires the
        temporal localization) and the action centre in ``camera`` (default: the best view, which then
        requires the best-view search). Parts not asked for and not required stay None.
        """
        need = set(need)
        unknown = need - NEEDS
        if unknown:
            raise InputError(f"unknown localization parts {sorted(unknown)} ({', '.join(sorted(NEEDS))})",
                             field="need")
        self.stats["localize"] += 1
        loc = Localization(query=query, scene=self.scene.name, temporal=None)
        spatial_needed = bool(need & {"best_view", "action_centre"})
        if "temporal" in need or (spatial_needed and t is None):
            t0 = time.perf_counter()
            self._span(0.0, 0.7 if spatial_needed else 1.0)
            loc.temporal = self.temporal(query)
            loc.timings["temporal"] = time.perf_counter() - t0
            if not loc.temporal.found and loc.temporal.message:
                loc.messages.append(loc.temporal.message)
        if not spatial_needed:
            return loc
        if t is None:
            t = loc.temporal.peak if loc.temporal is not None and loc.temporal.found else None
        if t is None:
            loc.messages.append("no temporal peak: spatial localization skipped")
            return loc
        loc.t = int(t)
        view_cam = camera
        if "best_view" in need or ("action_centre" in need and camera is None):
            t0 = time.perf_counter()
            self._span(0.7, 0.95 if "action_centre" in need else 1.0)
            cams = self.cameras_at(int(t))
            view = self.best_view(query, int(t), cams)
            loc.timings["best_view"] = time.perf_counter() - t0
            loc.best_view, loc.view_scores = view.best, view.scores
            if view.index is not None and view_cam is None:
                view_cam = cams[view.index]
        if "action_centre" in need:
            if view_cam is None:
                loc.messages.append("no camera to localize the action centre in")
                return loc
            t0 = time.perf_counter()
            self._span(0.95, 1.0)
            centre = self.action_centre(query, int(t), view_cam)
            loc.timings["action_centre"] = time.perf_counter() - t0
            loc.action_centre, loc.centre_px, loc.bbox = centre.centre_3d, centre.centre_px, centre.bbox
            if centre.message:
                loc.messages.append(centre.message)
        return loc


def _check_options(options: QueryOptions) -> None:
    """InputError for an option out of its range, before any work."""
    if options.path not in QUERY_PATHS:
        raise InputError(f"unknown query path {options.path!r} ({', '.join(QUERY_PATHS)})", field="path")
    check_number(options.sketch_rank, "sketch_rank", low=1, high=MAX_SKETCH_RANK, integer=True)
    if options.spatial not in ("exact", "fast"):
        raise InputError(f"unknown spatial path {options.spatial!r} (exact, fast)", field="spatial")
    check_number(options.resolution_scale, "resolution_scale", low=0, high=MAX_RESOLUTION_SCALE, low_open=True)
    check_number(options.view_scale, "view_scale", low=0, high=1, low_open=True)
    if options.view_score not in viewpoint.VIEW_SCORES:
        raise InputError(f"must be one of {', '.join(viewpoint.VIEW_SCORES)}, got {options.view_score!r}",
                         field="view_score")
    check_number(options.view_confirm, "view_confirm", low=1, high=MAX_TIMESTEP_ARGUMENT, integer=True)
    check_number(options.temporal_stride, "temporal_stride", low=1, high=MAX_TIMESTEP_ARGUMENT, integer=True)
    check_number(options.dilation, "dilation", low=0, high=MAX_TIMESTEP_ARGUMENT, integer=True)
    check_number(options.codebook_size, "codebook_size", low=1, high=MAX_CODEBOOK_SIZE, integer=True)
    if not (np.isfinite(options.codebook_refine) and 0.0 <= options.codebook_refine <= 1.0):
        raise InputError(f"codebook refine margin must be in [0, 1], got {options.codebook_refine}",
                         field="codebook_refine")
    if int(options.codebook_samples) < 2:
        raise InputError(f"codebook samples must be >= 2, got {options.codebook_samples}", field="codebook_samples")
