"""``QueryEngine``: when and where a text query happens in a scene with a distilled language field.

Paths (each selectable, each measured against the exact one by ``fourlegs bench accuracy-time``):

* temporal / per-Gaussian relevancy — ``path="exact"`` decodes every latent (streamed in chunks, never
  T x N x 768 at once); ``path="codebook"`` decodes only the K codes (once per engine) and scores
  Gaussians by lookup, a temporal query being a (T,K) histogram reduction; ``codebook_refine`` > 0
  re-scores exactly a sample (for R_avg) and, where a timestep's decision depends on them, the Gaussians
  of codes whose relevancy is that close to R_avg;
* ``temporal_stride`` scores every k-th timestep only;
* spatial maps — ``spatial="exact"`` renders the 128-channel latents, decodes every pixel and scores
  it (paper §3.2); ``spatial="fast"`` renders one channel, the per-Gaussian relevancy;
* ``resolution_scale`` renders the maps at a fraction of the camera resolution.

Every public method counts its calls (and the heavy work it did: decoded latents, decoded pixels,
128- and 1-channel renders) in ``.stats`` so callers can prove nothing was computed that was not asked
for; ``localize(query, need)`` computes only the parts named in ``need``.
"""
from __future__ import annotations

import threading
import time
import zlib
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Callable, Iterable, Optional, Sequence

import numpy as np
import torch

from ..errors import InputError
from ..scene.camera import Camera
from ..scene.scene import Scene
from ..threads import torch_threads
from ..validate import check_number
from . import spatial, viewpoint
from .codebook import Codebook, ensure_codebook
from .head import RelevancyHead
from .options import MAX_CODEBOOK_SIZE, MAX_RESOLUTION_SCALE, MAX_TIMESTEP_ARGUMENT, QueryOptions
from .lerf import (as_tensor, l2_normalize, reference_set, relevancy, relevancy_many,
                        relevancy_of_unit_features)
from .rows import RowReader
from .results import CentreResult, Localization, TemporalResult, ViewResult
from .temporal import (RELEVANT, counts_from_code_histogram, counts_from_codes_refined,
                       counts_from_relevancy, localize_counts, sampled_timesteps, tied_segment_rows, timestep_weights)

__all__ = ["QueryEngine", "QueryOptions", "TemporalResult", "Localization", "ViewResult", "CentreResult"]

NEEDS = frozenset({"temporal", "best_view", "action_centre"})
GAUSSIAN_CACHE_SIZE = 16  # per-Gaussian relevancy vectors (query, t) kept for reuse
TEMPORAL_SCORE_BYTES = 512 << 20  # exact temporal scores (T·N float32 per query) kept for per-frame reuse
TEMPORAL_STREAMS = 2  # timesteps scored concurrently on the exact temporal path (CPU)


class QueryEngine:
    """Answer text queries on one scene.

    Args:
        scene: the scene (geometry and cameras).
        field: the distilled language field (``.latents`` (T,N,d), ``.decode(M,d)->(M,D)``,
            ``.canonical_phrases``).
        text_encoder: ``encode_text(list[str]) -> (n,D)`` of the encoder the field was distilled from.
        options: :class:`~.options.QueryOptions` (paths, strides, scales; default: exact everywhere).
        codebook: a prebuilt :class:`Codebook` (else loaded from / stored in ``codebook_dir``, by default
            the bundle's ``language/`` directory, or built in memory).
    """

    def __init__(self, scene: Scene, field: Any, text_encoder: Any, options: Optional[QueryOptions] = None, *,
                 codebook: Optional[Codebook] = None, codebook_dir: Optional[Path] = None):
        options = options if options is not None else QueryOptions()
        self.options = options
        self._progress: Optional[Callable[[float, str], None]] = None
        self._progress_span = (0.0, 1.0)
        (path, codebook_size, codebook_refine, codebook_samples, negatives, temporal_stride, spatial,
         resolution_scale, dilation, chunk, latent_dtype, camera_split, render_options, render_backend,
         relevancy_scale) = (options.path, options.codebook_size, options.codebook_refine,
                             options.codebook_samples, options.negatives, options.temporal_stride,
                             options.spatial, options.resolution_scale, options.dilation, options.chunk,
                             options.latent_dtype, options.camera_split, options.render_options,
                             options.render_backend, options.relevancy_scale)
        if path not in ("exact", "codebook"):
            raise InputError(f"unknown query path {path!r} (exact, codebook)", field="path")
        if spatial not in ("exact", "fast"):
            raise InputError(f"unknown spatial path {spatial!r} (exact, fast)", field="spatial")
        check_number(resolution_scale, "resolution_scale", low=0, high=MAX_RESOLUTION_SCALE, low_open=True)
        check_number(temporal_stride, "temporal_stride", low=1, high=MAX_TIMESTEP_ARGUMENT, integer=True)
        check_number(dilation, "dilation", low=0, high=MAX_TIMESTEP_ARGUMENT, integer=True)
        check_number(codebook_size, "codebook_size", low=1, high=MAX_CODEBOOK_SIZE, integer=True)
        latents = getattr(field, "latents", None)
        if latents is None:
            raise InputError("the scene has no distilled language field (run `fourlegs distill` first)",
                             file=scene.root, field="language")
        T, N = scene.num_timesteps, scene.num_gaussians
        if tuple(latents.shape[:2]) != (T, N):
            raise InputError(f"latents have shape {tuple(latents.shape)}, the scene has T={T}, N={N}",
                             file=scene.root, field="language.latents")
        self.scene = scene
        self.field = field
        self.text_encoder = text_encoder
        self.path = path
        self.codebook_size = int(codebook_size)
        if not (np.isfinite(codebook_refine) and 0.0 <= codebook_refine <= 1.0):
            raise InputError(f"codebook refine margin must be in [0, 1], got {codebook_refine}",
                             field="codebook_refine")
        self.codebook_refine = float(codebook_refine)
        if int(codebook_samples) < 2:
            raise InputError(f"codebook samples must be >= 2, got {codebook_samples}", field="codebook_samples")
        self.codebook_samples = int(codebook_samples)
        self.codebook_dir = codebook_dir if codebook_dir is not None else (
            Path(scene.root) / "language" if scene.root is not None else None)
        self._codebook = codebook
        self.negatives = tuple(str(n) for n in negatives if str(n).strip())
        self.temporal_stride = int(temporal_stride)
        self.spatial = spatial
        self.resolution_scale = float(resolution_scale)
        self.dilation = int(dilation)
        self.chunk = int(chunk)
        self.latent_dtype = None if latent_dtype is None else np.dtype(latent_dtype)
        self.camera_split = camera_split
        self.render_options = render_options
        self.render_backend = render_backend
        self.relevancy_scale = float(relevancy_scale)
        self.stats: Counter = Counter()
        self._text_cache: dict[str, torch.Tensor] = {}
        self._refs: Optional[tuple[torch.Tensor, Optional[torch.Tensor]]] = None
        self._decoded_codes: Optional[torch.Tensor] = None
        self._row_reader: Optional[RowReader] = None
        self._head: Any = None  # RelevancyHead, False when the decoder has none, None before the first use
        self._code_scores: dict[str, torch.Tensor] = {}
        self._background_score: dict[str, float] = {}
        self._gaussian_cache: dict[tuple[str, int], torch.Tensor] = {}
        # per-Gaussian scores the exact temporal pass already computed: query -> {t: (N,) row}
        self._temporal_scores: dict[str, dict[int, np.ndarray]] = {}

    # ------------------------------------------------------------------ embeddings
    @property
    def latents(self):
        return self.field.latents

    def _encode(self, texts: list[str]) -> torch.Tensor:
        missing = [t for t in texts if t not in self._text_cache]
        if missing:
            self.stats["encode_text"] += 1
            with torch.inference_mode():
                emb = as_tensor(self.text_encoder.encode_text(missing))
            for text, e in zip(missing, emb):
                self._text_cache[text] = l2_normalize(e)
        return torch.stack([self._text_cache[t] for t in texts]) if texts else torch.zeros(0)

    def embed_query(self, query: str) -> torch.Tensor:
        """(D,) L2-normalized embedding of ``query`` (cached)."""
        if not isinstance(query, str) or not query.strip():
            raise InputError("the query text is empty", field="query")
        return self._encode([query])[0]

    def reference_embeddings(self) -> tuple[torch.Tensor, Optional[torch.Tensor]]:
        """Canonical (K,D) and negative (J,D)|None phrase embeddings."""
        if self._refs is None:
            canon = list(getattr(self.field, "canonical_phrases", None) or ())
            if not canon:
                from ..language import CANONICAL_PHRASES  # noqa: WPS433 (fallback only)
                canon = list(CANONICAL_PHRASES)
            c = self._encode(canon)
            n = self._encode(list(self.negatives)) if self.negatives else None
            self._refs = (c, n)
        return self._refs

    def _score(self, features: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        canon, neg = self.reference_embeddings()
        return relevancy(features, q, canon, neg, scale=self.relevancy_scale)

    def _score_many(self, features: torch.Tensor, qs: torch.Tensor) -> torch.Tensor:
        """(M,D) features, (Q,D) unit queries -> (M,Q) relevancy (one matrix product)."""
        canon, neg = self.reference_embeddings()
        return relevancy_many(features, qs, reference_set(canon, neg), scale=self.relevancy_scale)

    def forget_query(self, query: str) -> None:
        """Drop every score cached for ``query`` (code relevancies, per-Gaussian and temporal scores,
        background relevancy), keeping its text embedding: the next call redoes the query's own work."""
        self._code_scores.pop(query, None)
        self._background_score.pop(query, None)
        self._temporal_scores.pop(query, None)
        for key in [k for k in self._gaussian_cache if k[0] == query]:
            del self._gaussian_cache[key]

    # ------------------------------------------------------------------ decoding
    def _read_latents(self, t: int) -> np.ndarray:
        x = self.latents[t]
        dtype = self.latent_dtype or np.float32
        return np.asarray(x, dtype=dtype)

    def _decode(self, latents: np.ndarray | torch.Tensor) -> torch.Tensor:
        """(M,d) latents -> (M,D) decoded features, float32."""
        x = torch.as_tensor(latents)
        if x.dtype != torch.float32:
            x = x.to(torch.float32)
        with torch.inference_mode():
            out = self.field.decode(x)
        return as_tensor(out)

    @property
    def head(self) -> Optional[RelevancyHead]:
        """Relevancy straight from latents (None when the field's decoder has no such form)."""
        if self._head is None:
            self._head = RelevancyHead.from_decoder(getattr(self.field, "decoder", None)) or False
        return self._head or None

    def _score_latents_many(self, latents: np.ndarray | torch.Tensor, qs: torch.Tensor) -> torch.Tensor:
        """(M,d) latents (per Gaussian or rendered per pixel), (Q,D) unit queries -> (M,Q) relevancy of
        their decoded features; one chunk (at most ``self.chunk`` rows) at a time by the caller."""
        head = self.head
        if head is None:
            return self._score_many(self._decode(latents), qs)
        canon, neg = self.reference_embeddings()
        with torch.inference_mode():
            return head.relevancy_many(torch.as_tensor(latents), qs, reference_set(canon, neg),
                                       scale=self.relevancy_scale).cpu()

    def _score_latents(self, latents: np.ndarray, q: torch.Tensor,
                       window: Optional[tuple[float, float]] = None) -> torch.Tensor:
        """(M,d) latents -> (M,) relevancy, decoded in chunks of ``self.chunk``.

        With a ``window`` (low, high) a row whose relevancy is certainly outside it may get a bound instead
        that compares with every threshold in the window as its relevancy does (see
        :meth:`RelevancyHead.relevancy_windowed`; counted in ``stats["bounded_latents"]``)."""
        M = latents.shape[0]
        out = torch.empty(M, dtype=torch.float32)
        head = self.head if window is not None else None
        if head is not None:
            canon, neg = self.reference_embeddings()
            refs = reference_set(canon, neg)
        for s in range(0, M, self.chunk):
            if head is None:
                out[s:s + self.chunk] = self._score_latents_many(latents[s:s + self.chunk], q[None])[:, 0]
                continue
            with torch.inference_mode():
                values, exact = head.relevancy_windowed(torch.as_tensor(latents[s:s + self.chunk]), q, refs,
                                                        scale=self.relevancy_scale, window=window)
            out[s:s + self.chunk] = values.cpu()
            self.stats["bounded_latents"] += int((~exact).sum())
        self.stats["decoded_latents"] += M
        return out

    # ------------------------------------------------------------------ codebook
    @property
    def codebook(self) -> Codebook:
        return self.load_codebook()

    def load_codebook(self, progress: Optional[Callable[[float, str], None]] = None) -> Codebook:
        """The codebook, loaded or (first use) built and stored; a build calls ``progress(fraction,
        stage)`` between its steps, and an exception it raises stops the build with nothing stored."""
        if self._codebook is None:
            self.stats["codebook_load"] += 1
            self._codebook = ensure_codebook(self.latents, self.codebook_size, self.codebook_dir,
                                             on_progress=progress)
        return self._codebook

    def _codes_scores(self, query: str) -> torch.Tensor:
        """(K,) relevancy of every code (the decoded codebook is computed once per engine)."""
        if query not in self._code_scores:
            if self._decoded_codes is None:
                self._decoded_codes = l2_normalize(self._decode(self.codebook.centroids))
                self.stats["decoded_codes"] += int(self._decoded_codes.shape[0])
            canon, neg = self.reference_embeddings()
            refs = reference_set(canon, neg)
            self._code_scores[query] = relevancy_of_unit_features(
                self._decoded_codes, self.embed_query(query), refs, scale=self.relevancy_scale)
        return self._code_scores[query]

    def _rows(self) -> RowReader:
        """Reader of scattered latent rows (``os.pread`` on a memory-mapped field: see :mod:`.rows`)."""
        if self._row_reader is None:
            self._row_reader = RowReader(self.latents)
        return self._row_reader

    def _band_members(self, codes: np.ndarray, rows: np.ndarray,
                      timesteps: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every Gaussian holding one of ``codes`` at the scored timesteps ``timesteps[rows]``.

        Returns:
            rows (M,) int64 index into ``timesteps``, codes (M,) int64, flat indices t*N+g (M,) int64.
        """
        N = self.scene.num_gaussians
        rows = np.sort(np.asarray(rows, dtype=np.int64))
        wanted = np.asarray(timesteps, dtype=np.int64)[rows]  # sorted, as the scored timesteps are
        flat, code_of = self.codebook.members_with_codes(codes)
        keep = np.isin(flat // N, wanted)
        flat, code_of = flat[keep], code_of[keep]
        return rows[np.searchsorted(wanted, flat // N)], code_of, flat

    def _score_any(self, query: str, flat: np.ndarray, window: Optional[tuple[float, float]] = None) -> np.ndarray:
        """(M,) float64 exact relevancy of the Gaussians at flat indices t*N+g, in any order (with a
        ``window``: bounds where certainly outside it, see :meth:`_score_latents`)."""
        flat = np.asarray(flat, dtype=np.int64)
        order = np.argsort(flat, kind="stable")  # reads in file order
        scores = np.empty(flat.shape[0], dtype=np.float64)
        scores[order] = self._score_pairs(query, flat[order], window)
        return scores

    def _sample_members(self, query: str, groups: Sequence[np.ndarray], sizes: Sequence[int], timesteps: np.ndarray,
                        rng: np.random.Generator, window: Optional[tuple[float, float]] = None
                        ) -> list[tuple[np.ndarray, np.ndarray]]:
        """For each group of codes, exact relevancy of a uniform sample without replacement of that many
        Gaussians holding one of its codes at one of the sorted scored ``timesteps`` (all of them when
        there are no more); every group is decoded in one batch (``window``: see :meth:`_score_latents`).

        Returns:
            per group: their codes (M_j,) int64, scores (M_j,) float64.
        """
        N, T = self.scene.num_gaussians, self.scene.num_timesteps
        timesteps = np.asarray(timesteps, dtype=np.int64)
        flats, code_ofs = [], []
        strided = len(timesteps) != T
        for codes, size in zip(groups, sizes):
            # members are indexed over every timestep: draw enough to keep ``size`` at the scored ones
            draw = size
            if strided:
                scored = int(np.asarray(self.codebook.histogram)[timesteps][:, np.asarray(codes)].sum())
                draw = int(np.ceil(size * T / max(len(timesteps), 1) * 1.25)) + 32 if size < scored else 1 << 62
            flat, code_of = self.codebook.sample_members(codes, draw, rng)
            if strided:
                keep = np.isin(flat // N, timesteps)
                flat, code_of = flat[keep][:size], code_of[keep][:size]
            flats.append(flat)
            code_ofs.append(code_of)
        scores = self._score_any(query, np.concatenate(flats) if flats else np.zeros(0, dtype=np.int64), window)
        bounds = np.cumsum([0] + [f.shape[0] for f in flats])
        return [(c, scores[a:b]) for c, a, b in zip(code_ofs, bounds[:-1], bounds[1:])]

    def _score_pairs(self, query: str, flat: np.ndarray, window: Optional[tuple[float, float]] = None) -> np.ndarray:
        """(M,) float64 exact relevancy of the Gaussians at sorted flat indices t*N+g (``window``: see
        :meth:`_score_latents`)."""
        lat = self._rows().read(flat, dtype=self.latent_dtype or np.float32)
        if lat.shape[0] == 0:
            return np.zeros(0, dtype=np.float64)
        return self._score_latents(lat, self.embed_query(query), window).double().numpy()

    # ------------------------------------------------------------------ per Gaussian
    def gaussian_relevancy(self, query: str, t: int) -> torch.Tensor:
        """(N,) relevancy of every Gaussian at timestep ``t`` (decoded volumetric latents)."""
        self.stats["gaussian_relevancy"] += 1
        return self._gaussian_relevancy(query, self.scene.gaussians.check_timestep(t)).clone()

    def _gaussian_relevancy(self, query: str, t: int) -> torch.Tensor:
        key = (query, int(t))
        if key in self._gaussian_cache:  # e.g. one fast map per camera in a best-view search
            return self._gaussian_cache[key]
        if int(t) in self._temporal_scores.get(query, {}):  # decoded once by the temporal pass
            return torch.from_numpy(self._temporal_scores[query][int(t)])
        if self.scene.num_gaussians == 0:
            out = torch.zeros(0)
        elif self.path == "codebook":
            codes = torch.from_numpy(np.asarray(self.codebook.codes[t], dtype=np.int64))
            out = self._codes_scores(query)[codes]
        else:
            out = self._score_latents(self._read_latents(t), self.embed_query(query))
        self._gaussian_cache[key] = out
        while len(self._gaussian_cache) > GAUSSIAN_CACHE_SIZE:
            self._gaussian_cache.pop(next(iter(self._gaussian_cache)))
        return out

    def _gaussian_relevancy_many(self, queries: list[str], t: int) -> torch.Tensor:
        """(N,Q) float32 relevancy of every Gaussian at ``t`` for several queries; the latents of
        ``t`` are decoded at most once for all queries not already cached."""
        missing = [q for q in dict.fromkeys(queries) if (q, int(t)) not in self._gaussian_cache
                   and int(t) not in self._temporal_scores.get(q, {})]
        if self.path == "exact" and len(missing) > 1 and self.scene.num_gaussians:
            lat = self._read_latents(int(t))
            qs = torch.stack([self.embed_query(q) for q in missing])
            scores = torch.cat([self._score_latents_many(lat[s:s + self.chunk], qs)
                                for s in range(0, lat.shape[0], self.chunk)])           # (N, len(missing))
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
        Q = len(queries)
        if N == 0:
            stats = [(np.zeros(len(ts), np.int64), 0.0, 0)] * Q
        elif self.path == "codebook" and self.codebook_refine > 0:
            hist = self.codebook.histogram[ts]
            weights = timestep_weights(ts, T)
            stats = []
            for q in queries:
                rng = np.random.default_rng(zlib.crc32(q.encode("utf-8")))  # the same answer every time
                c, a, n, rescored, sampled = counts_from_codes_refined(
                    self._codes_scores(q).double().numpy(), hist,
                    members=lambda codes, rows: self._band_members(codes, rows, ts),
                    score=lambda flat, window, q=q: self._reported(self._score_any, q, flat, window),
                    sample=lambda groups, sizes, q=q, rng=rng: self._sample_members(q, groups, sizes, ts, rng,
                                                                                     (RELEVANT, np.inf)),
                    margin=self.codebook_refine, weights=weights, samples=self.codebook_samples,
                    tied_rows=lambda positive: tied_segment_rows(positive, ts, T, self.dilation))
                self.stats["rescored_latents"] += rescored
                self.stats["sampled_latents"] += sampled
                stats.append((c, a, n))
        elif self.path == "codebook":
            hist = self.codebook.histogram[ts]
            stats = [counts_from_code_histogram(self._codes_scores(q).double().numpy(), hist) for q in queries]
        else:
            qs = torch.stack([self.embed_query(q) for q in queries])
            self.reference_embeddings()  # encoded here, not by two streams at once
            scores = np.empty((Q, len(ts), N), dtype=np.float32)
            bookkeeping = threading.Lock()  # progress in start order and the decode count, across streams
            started = [0]

            def score_timestep(i: int) -> None:
                with bookkeeping:
                    self._report(started[0] / len(ts), "scoring timesteps")
                    started[0] += 1
                lat = self._read_latents(int(ts[i]))
                for s in range(0, N, self.chunk):
                    scores[:, i, s:s + self.chunk] = self._score_latents_many(lat[s:s + self.chunk], qs).T.numpy()
                with bookkeeping:
                    self.stats["decoded_latents"] += N

            self._for_each_timestep(score_timestep, len(ts))
            stats = [counts_from_relevancy(scores[j]) for j in range(Q)]
            per_query = len(ts) * N * 4
            for j, q in enumerate(queries if per_query <= TEMPORAL_SCORE_BYTES else []):
                # later per-timestep lookups (fast maps, desaturation frames) reuse them
                self._temporal_scores.pop(q, None)
                self._temporal_scores[q] = {int(t): scores[j, i] for i, t in enumerate(ts)}
                while len(self._temporal_scores) * per_query > TEMPORAL_SCORE_BYTES:
                    self._temporal_scores.pop(next(iter(self._temporal_scores)))
        return [localize_counts(c, ts, T, dilation=self.dilation, r_avg=a, num_relevant=n, query=q,
                                num_gaussians=N) for q, (c, a, n) in zip(queries, stats)]

    def _for_each_timestep(self, work, count: int) -> None:
        """Run ``work(i)`` for i in range(count). On the CPU with two or more torch threads the
        timesteps run on :data:`TEMPORAL_STREAMS` concurrent streams of fewer torch threads each: a
        timestep's scoring is a few large products between many elementwise tensor ops, which one
        stream on two threads spends largely at thread barriers. Each timestep's result is computed
        alone, so it is the same whichever stream runs it."""
        threads = torch.get_num_threads()
        on_cpu = self.head is None or self.head.device.type == "cpu"
        streams = min(TEMPORAL_STREAMS, threads, count)
        if not on_cpu or streams < 2:
            for i in range(count):
                work(i)
            return
        stop = threading.Event()  # after a failure (or a cancel raised by work) the queued timesteps are skipped

        def guarded(i: int) -> None:
            if stop.is_set():
                return
            try:
                work(i)
            except BaseException:
                stop.set()
                raise

        with torch_threads(max(1, threads // streams)), ThreadPoolExecutor(streams) as pool:
            list(pool.map(guarded, range(count)))

    # ------------------------------------------------------------------ spatial
    def _camera(self, camera: Camera, scale: Optional[float]) -> Camera:
        s = self.resolution_scale if scale is None else float(scale)
        return camera if s == 1.0 else camera.scaled(s)

    def _rasterize(self, t: int, camera: Camera, features: torch.Tensor, outputs: tuple[str, ...]) -> dict:
        from ..render import rasterize  # render is left of query in the data flow
        frame = self.scene.gaussians.at(t)
        with torch.inference_mode():
            return rasterize(frame.means, frame.rotations, frame.log_scales, frame.opacity_logits, camera,
                             features=features, outputs=outputs, options=self.render_options,
                             backend=self.render_backend)

    def background_relevancy(self, query: str) -> float:
        """Relevancy of an empty pixel on the exact path (its rendered latent is 0)."""
        if query not in self._background_score:
            d = int(self.latents.shape[-1])
            self._background_score[query] = float(
                self._score(self._decode(torch.zeros(1, d)), self.embed_query(query))[0])
        return self._background_score[query]

    def relevancy_map(self, query: str, camera: Camera, t: int, fast: Optional[bool] = None,
                      outputs: Iterable[str] = ("relevancy", "depth", "alpha"), *,
                      scale: Optional[float] = None) -> dict[str, np.ndarray]:
        """Per-pixel relevancy of ``query`` seen from ``camera`` at timestep ``t``.

        Exact (paper §3.2): render the (N,d) latents, decode every pixel, score it. Fast: render the
        (N,1) per-Gaussian relevancy; empty pixels take the exact path's background value, so
        ``map = Σ w_i R_i + (1 − alpha) R_bg``.

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
                       outputs: Iterable[str] = ("relevancy", "depth", "alpha"), *,
                       scale: Optional[float] = None) -> dict[str, np.ndarray]:
        """Like :meth:`relevancy_map` for several queries with one render and one per-pixel decode.

        Returns:
            "relevancy" (Q,H,W), "depth" (H,W), "alpha" (H,W) float32 (the requested ones).
        """
        self.stats["relevancy_maps"] += 1
        t = self.scene.gaussians.check_timestep(t)
        outputs = tuple(outputs)
        unknown = set(outputs) - {"relevancy", "depth", "alpha"}
        if unknown:
            raise InputError(f"unknown map outputs {sorted(unknown)} (relevancy, depth, alpha)", field="outputs")
        fast = (self.spatial == "fast") if fast is None else bool(fast)
        cam = self._camera(camera, scale)
        H, W, Q = cam.height, cam.width, len(queries)
        qs = torch.stack([self.embed_query(q) for q in queries]) if Q else torch.zeros(0)
        r_bg = torch.tensor([self.background_relevancy(q) for q in queries], dtype=torch.float32)
        if self.scene.num_gaussians == 0:
            empty = {"relevancy": r_bg[:, None, None].expand(Q, H, W).numpy().copy(),
                     "depth": np.zeros((H, W), np.float32), "alpha": np.zeros((H, W), np.float32)}
            return {k: empty[k] for k in outputs}
        render_outputs = ("features", "alpha") + (("depth",) if "depth" in outputs else ())
        if fast:
            per_gaussian = self._gaussian_relevancy_many(list(queries), t)
            out = self._rasterize(t, cam, per_gaussian, render_outputs)
            self.stats["render_relevancy"] += 1
            alpha = out["alpha"].reshape(H, W)
            rel = out["features"].reshape(H, W, Q).permute(2, 0, 1) + \
                (1.0 - alpha).clamp(0.0, 1.0)[None] * r_bg[:, None, None]
        else:
            lat = torch.from_numpy(self._read_latents(t).astype(np.float32, copy=False))
            out = self._rasterize(t, cam, lat, render_outputs)
            self.stats["render_features"] += 1
            pix = out["features"].reshape(H * W, -1)
            # pixels no Gaussian covers render the zero latent: decoded once (its row's result does not
            # depend on the batch), every other pixel in chunks
            covered = torch.nonzero(pix.any(dim=1)).flatten()
            rel = self._score_latents_many(torch.zeros(1, pix.shape[1]), qs).T.expand(Q, H * W).contiguous()
            for s in range(0, covered.numel(), self.chunk):
                rows = covered[s:s + self.chunk]
                rel[:, rows] = self._score_latents_many(pix[rows], qs).T
            self.stats["decoded_pixels"] += covered.numel() + 1
            rel = rel.reshape(Q, H, W)
            alpha = out["alpha"].reshape(H, W)
        result = {"relevancy": rel.clamp(0.0, 1.0), "alpha": alpha}
        if "depth" in outputs:
            result["depth"] = out["depth"].reshape(H, W)
        return {k: np.nan_to_num(result[k].detach().cpu().numpy().astype(np.float32)) for k in outputs}

    def cameras_at(self, t: int, split: Optional[str] = None) -> list[Camera]:
        return self.scene.cameras.cameras(t, split or self.camera_split)

    def best_view(self, query: str, t: int, cameras: Optional[Sequence[Camera]] = None) -> ViewResult:
        """The camera with the highest mean relevancy at timestep ``t`` (paper §6.1)."""
        self.stats["best_view"] += 1
        cams = list(cameras) if cameras is not None else self.cameras_at(t)
        seen = [0]

        def relevancy_of(cam: Camera) -> np.ndarray:
            self._report(seen[0] / max(1, len(cams)), "rendering the views")
            seen[0] += 1
            return self.relevancy_map(query, cam, t, outputs=("relevancy",))["relevancy"]

        return viewpoint.best_view(cams, relevancy_of, t)

    def action_centre(self, query: str, t: int, camera: Camera) -> CentreResult:
        """2D centre of mass of the relevancy map, lifted to 3D with the rendered depth; plus the bbox."""
        self.stats["action_centre"] += 1
        maps = self.relevancy_map(query, camera, t)
        cam = self._camera(camera, None)
        centre = spatial.centre_of_mass(maps["relevancy"])
        point, depth = spatial.lift_centre(cam, centre, maps["depth"], maps["alpha"], maps["relevancy"])
        box = spatial.best_component_bbox(maps["relevancy"])
        message = "" if point is not None else "no rendered surface under the relevant pixels; no 3D centre"
        scale = cam.width / camera.width
        return CentreResult(centre_px=None if centre is None else centre / scale, centre_3d=point, depth=depth,
                            bbox=None if box is None else _scale_box(box, scale), camera=camera.name, t=t,
                            message=message)

    # ------------------------------------------------------------------ all together
    # ------------------------------------------------------------------ progress
    def _report(self, fraction: float, stage: str) -> None:
        """Tell the progress callback of the running :meth:`localize` (if any) how far it is; the
        callback stops the computation by raising (e.g. :class:`~fourlegs_engine.errors.Cancelled`)."""
        if self._progress is not None:
            lo, hi = self._progress_span
            self._progress(lo + (hi - lo) * min(max(float(fraction), 0.0), 1.0), stage)

    def _reported(self, fn: Callable, *args):
        """``fn(*args)`` after giving the progress callback a chance to stop the computation."""
        self._report(0.0, "re-scoring the uncertain Gaussians")
        return fn(*args)

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


def _scale_box(box: tuple[int, int, int, int], scale: float) -> tuple[int, int, int, int]:
    if scale == 1.0:
        return box
    x0, y0, x1, y1 = box
    return (int(np.floor(x0 / scale)), int(np.floor(y0 / scale)), int(np.ceil((x1 + 1) / scale)) - 1,
            int(np.ceil((y1 + 1) / scale)) - 1)
