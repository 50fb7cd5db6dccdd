"""The codebook path of the query engine (``QueryOptions(path="codebook")``).

The K codes of a k-means codebook of the latents are decoded once per engine; a Gaussian's relevancy is
its code's, and a temporal query is a (T,K) histogram reduction. With a refine margin > 0 the temporal
decisions are made exact where they depend on it: R_avg is corrected by exact scores of sampled
Gaussians, and the Gaussians of codes within the margin of R_avg are re-scored exactly
(:func:`~.refined_counts.counts_from_codes_refined`).
"""
from __future__ import annotations

import zlib
from collections import Counter
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np
import torch

from ..scene.scene import Scene
from .codebook import MEMBER_MEANS, Codebook, ensure_codebook
from .lerf import l2_normalize, relevancy_of_unit_features
from .scoring import LatentScorer
from .refined_counts import MEMBERSHIP_BAND, counts_from_codes_refined
from .temporal import RELEVANT, counts_from_code_histogram, tied_segment_rows, timestep_weights

#: per query: counts (S,) int64 of relevant Gaussians per scored timestep, R_avg, number of relevant pairs,
#: and (S,) bool the scored timesteps whose decision s_t > 1/T the index left open
TemporalCounts = tuple[np.ndarray, float, int, np.ndarray]


class CodebookPath:
    """Per-Gaussian relevancy and temporal counts by codebook lookup (see the module docstring).

    Args:
        scene: the scene the latents belong to.
        scorer: the exact scorer (decodes the codes and, when refining, the re-scored Gaussians).
        size: K. refine: the exact re-scoring margin (0: lookup only). samples: exact scores spent on R_avg.
        directory: where the codebook is loaded from / stored (None: built in memory).
        codebook: a prebuilt :class:`Codebook`.
        stats: the engine's counters (``codebook_load``, ``decoded_codes``, ``rescored_latents``,
            ``sampled_latents``).
    """

    def __init__(self, scene: Scene, scorer: LatentScorer, *, size: int, refine: float, samples: int,
                 directory: Optional[Path], codebook: Optional[Codebook], stats: Counter):
        self.scene = scene
        self.scorer = scorer
        self.size = int(size)
        self.refine = float(refine)
        self.samples = int(samples)
        self.directory = directory
        self.stats = stats
        self._codebook = codebook
        self._decoded_codes: Optional[torch.Tensor] = None
        self._code_scores: dict[str, torch.Tensor] = {}
        self._code_gradients: dict[str, np.ndarray] = {}  # (K,d) float64 ∇r at each code, per query

    def load(self, progress: Optional[Callable[[float, str], None]] = None) -> Codebook:
        """The codebook, loaded or (first use) built and stored; a build calls ``progress(fraction,
        stage)`` between its steps, and an exception it raises stops the build with nothing stored."""
        if self._codebook is None:
            self.stats["codebook_load"] += 1
            self._codebook = ensure_codebook(self.scorer.latents, self.size, self.directory, on_progress=progress)
        return self._codebook

    @property
    def codebook(self) -> Codebook:
        return self.load()

    def code_scores(self, query: str) -> torch.Tensor:
        """(K,) relevancy of every code (the decoded codebook is computed once per engine)."""
        if query not in self._code_scores:
            if self._decoded_codes is None:
                self._decoded_codes = l2_normalize(self.scorer.decode(self.codebook.centroids))
                self.stats["decoded_codes"] += int(self._decoded_codes.shape[0])
            self._code_scores[query] = relevancy_of_unit_features(
                self._decoded_codes, self.scorer.embed_query(query), self.scorer.references(),
                scale=self.scorer.relevancy_scale)
        return self._code_scores[query]

    def gaussian_relevancy(self, query: str, t: int) -> torch.Tensor:
        """(N,) relevancy of every Gaussian at ``t``: its code's; with a refine margin > 0, the Gaussians
        whose code is within ``MEMBERSHIP_BAND`` of 0.5 or above it (those a map's relevant part is made of)
        are scored exactly."""
        codes = torch.from_numpy(np.asarray(self.codebook.codes[t], dtype=np.int64))
        scores = self.code_scores(query)[codes]
        if self.refine > 0:
            candidates = torch.nonzero(scores > RELEVANT - MEMBERSHIP_BAND).flatten().numpy()
            if candidates.size:
                flat = int(t) * self.scene.num_gaussians + candidates.astype(np.int64)
                exact = self.scorer.score_any(query, flat)
                scores = scores.clone()
                scores[torch.from_numpy(candidates)] = torch.from_numpy(exact).to(scores.dtype)
                self.stats["rescored_latents"] += int(candidates.size)
        return scores

    def forget(self, query: str) -> None:
        """Drop the code relevancies cached for ``query``."""
        self._code_scores.pop(query, None)
        self._code_gradients.pop(query, None)

    # ------------------------------------------------------------------ temporal
    def temporal_counts(self, queries: Sequence[str], timesteps: np.ndarray, dilation: int,
                        report: Callable[[float, str], None]) -> list[TemporalCounts]:
        """Relevant-Gaussian counts per scored timestep for each query (refined when ``refine`` > 0)."""
        hist = self.codebook.histogram[timesteps]
        if self.refine <= 0:
            return [(*counts_from_code_histogram(self.code_scores(q).double().numpy(), hist),
                     np.zeros(len(timesteps), dtype=bool)) for q in queries]
        T = self.scene.num_timesteps
        weights = timestep_weights(timesteps, T)
        out = []
        for q in queries:
            rng = np.random.default_rng(zlib.crc32(q.encode("utf-8")))  # the same answer every time

            def rescore(flat: np.ndarray, window: tuple[float, float], q: str = q) -> np.ndarray:
                report(0.0, "re-scoring the uncertain Gaussians")
                return self.scorer.score_any(q, flat, window)

            refined = counts_from_codes_refined(
                self.code_scores(q).double().numpy(), hist,
                members=lambda codes, rows: self.band_members(codes, rows, timesteps), score=rescore,
                sample=lambda groups, sizes, q=q, rng=rng: self.sample_members(q, groups, sizes, timesteps, rng,
                                                                                (RELEVANT, np.inf)),
                margin=self.refine, weights=weights, samples=self.samples,
                tied_rows=lambda positive: tied_segment_rows(positive, timesteps, T, dilation))
            self.stats["rescored_latents"] += refined.rescored
            self.stats["sampled_latents"] += refined.sampled
            out.append((refined.counts, refined.r_avg, refined.relevant, refined.undecided))
        return out

    def band_members(self, codes: np.ndarray, rows: np.ndarray,
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

    def sample_members(self, query: str, groups: Sequence[np.ndarray], sizes: Sequence[int], timesteps: np.ndarray,
                       rng: np.random.Generator, window: Optional[tuple[float, float]] = None
                       ) -> list[tuple[np.ndarray, np.ndarray]]:
        """For each group of codes, exact relevancy of a uniform sample without replacement of that many
        Gaussians holding one of its codes at one of the sorted scored ``timesteps`` (all of them when
        there are no more); every group is decoded in one batch (``window``: see
        :meth:`LatentScorer.score_latents`).

        Returns:
            per group: their codes (M_j,) int64, scores (M_j,) float64, and their first-order relevancies
            around their codes (M_j,) float64 (:meth:`first_order`; None with a temporal stride or without
            a head).
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
        flat = np.concatenate(flats) if flats else np.zeros(0, dtype=np.int64)
        scores, latents = self.scorer.score_any_rows(query, flat, window)
        # a code is the mean of its members over every timestep: with every timestep scored, the members'
        # first-order relevancies sum to the code's (see refined_counts), so they can stand in as the control
        controls = None if strided else self.first_order(query, np.concatenate(code_ofs) if code_ofs else
                                                         np.zeros(0, dtype=np.int64), latents)
        bounds = np.cumsum([0] + [f.shape[0] for f in flats])
        return [(c, scores[a:b], None if controls is None else controls[a:b])
                for c, a, b in zip(code_ofs, bounds[:-1], bounds[1:])]

    def first_order(self, query: str, codes: np.ndarray, latents: np.ndarray) -> Optional[np.ndarray]:
        """(M,) float64 r_k + ∇r(c_k)·(z − c_k) of latents ``latents`` (M,d) holding ``codes`` (M,): their
        relevancy expanded to first order around their codes; None when the field's decoder has no
        :class:`~.head.RelevancyHead` to differentiate, or the codes are not their members' means."""
        head = self.scorer.head
        if head is None or self.codebook.meta.get("centroids") != MEMBER_MEANS:
            return None
        if query not in self._code_gradients:
            self._code_gradients[query] = head.relevancy_gradient(
                torch.from_numpy(np.asarray(self.codebook.centroids)), self.scorer.embed_query(query),
                self.scorer.references(), scale=self.scorer.relevancy_scale).numpy()
        codes = np.asarray(codes, dtype=np.int64)
        offset = latents.astype(np.float64) - np.asarray(self.codebook.centroids, dtype=np.float64)[codes]
        return (self.code_scores(query).double().numpy()[codes]
                + np.einsum("md,md->m", offset, self._code_gradients[query][codes]))
