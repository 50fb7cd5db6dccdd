"""The sketch path of the query engine (``QueryOptions(path="sketch")``): temporal counts from the per-pair
sketch of :mod:`.sketch`, exact where a decision depends on it.

For one query the sketch gives every scored pair's margin m within a radius ρ (the exact path's margin
lies in m ± ρ; relevancy = sigmoid(margin), so "relevancy > θ" is "margin > logit θ"). Then:

1. **Rel** (relevancy > 0.5, margin > 0): a pair with m − ρ > 0 is in it, one with m + ρ ≤ 0 is not;
   the few in between are scored exactly. |Rel| is exact.
2. **R_avg** = mean relevancy over Rel: the sketch's values sigmoid(m) of the pairs certainly in Rel
   (their errors are a few 1e-5), corrected by the exact-minus-sketch differences of a sample of them
   drawn with probability proportional to each one's error bound (importance sampling: every draw's
   weighted difference is bounded), plus the exact values of the pairs scored in step 1. Its standard error
   gives an interval of ±``R_AVG_Z`` errors (a probability of about 6e-5 that R_avg lies outside it);
   when the sample covers every pair R_avg is exact.
3. **Counts** above R_avg per timestep: a pair whose interval lies above logit(R_high) counts, one below
   logit(R_low) does not, the rest are scored exactly. An exact value inside R_avg's interval is counted
   against the estimate; a timestep whose count, and the mean count, can move across each other as R_avg
   moves in its interval is undecided;
   undecided timesteps get a 4x larger sample (up to ``R_AVG_MAX_SAMPLES_FACTOR`` x), which narrows the
   interval.

Every count is the exact path's whenever R_avg lies in its interval (the sample's error, about 1e-6 at
the default sample on the real capture, is the only approximation), and the timesteps that interval
leaves open are reported as undecided.
"""
from __future__ import annotations

import math
import zlib
from collections import Counter
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np
import torch

from ..scene.scene import Scene
from .codebook_path import TemporalCounts
from .refined_counts import R_AVG_MAX_SAMPLES_FACTOR
from .scoring import LatentScorer
from .sketch import PairSketch, ensure_sketch
from .temporal import RELEVANT, timestep_weights


#: R_avg's interval, in standard errors of its sampled correction
R_AVG_Z = 4.0
#: a certain pair's draw probability is at least this fraction of the mean (bounds every draw's weight)
IMPORTANCE_FLOOR = 1e-3
#: per-Gaussian relevancy kept from temporal passes for the maps (T·N float32 per query)
KEPT_RELEVANCY_BYTES = 256 << 20


class SketchPath:
    """Temporal counts from the per-pair sketch (see the module docstring).

    Args:
        scene: the scene the latents belong to. scorer: the exact scorer (its head builds the sketch and
            scores the pairs the sketch leaves open).
        rank: the sketch's rank. samples: exact scores spent on R_avg's first estimate.
        directory: where the sketch is loaded from / stored (None: built in memory).
        stats: the engine's counters (``sketch_load``, ``rescored_latents``, ``sampled_latents``).
    """

    def __init__(self, scene: Scene, scorer: LatentScorer, *, rank: int, samples: int, directory: Optional[Path],
                 stats: Counter):
        self.scene = scene
        self.scorer = scorer
        self.rank = int(rank)
        self.samples = int(samples)
        self.directory = directory
        self.stats = stats
        self._sketch: Optional[PairSketch] = None
        # per query: the scored timesteps and their (S, N) per-Gaussian relevancy, kept from the temporal pass
        self._relevancy: dict[str, tuple[dict[int, int], np.ndarray]] = {}

    @property
    def available(self) -> bool:
        """Whether the field's decoder has the head the sketch needs (else the engine uses the codebook path)."""
        return self.scorer.head is not None

    def load(self, progress: Optional[Callable[[float, str], None]] = None) -> PairSketch:
        """The sketch, loaded or (first use) built and stored; ``progress(fraction, stage)`` as the build goes
        (an exception it raises stops the build with nothing stored)."""
        if self._sketch is None:
            self.stats["sketch_load"] += 1
            self._sketch = ensure_sketch(self.scorer.head, self.scorer.references(), self.scorer.latents,
                                         self.directory, self.rank, on_progress=progress)
        return self._sketch

    def temporal_counts(self, queries: Sequence[str], timesteps: np.ndarray,
                        report: Callable[[float, str], None]) -> list[TemporalCounts]:
        """Relevant-Gaussian counts per scored timestep, R_avg, |Rel| and the undecided timesteps, per query."""
        sketch = self.load()
        timesteps = np.asarray(timesteps, dtype=np.int64)
        weights = timestep_weights(timesteps, self.scene.num_timesteps)
        out = []
        for q in queries:
            report(0.0, "sketching every Gaussian's relevancy")
            margin, radius = sketch.margins(self.scorer.head, self.scorer.embed_query(q), self.scorer.relevancy_scale,
                                            timesteps)
            rng = np.random.default_rng(zlib.crc32(q.encode("utf-8")))  # the same answer every time
            pairs = _Pairs(margin, radius, lambda idx, q=q: self._score(q, timesteps, idx, report))
            out.append(_counts(pairs, weights, self.samples, rng))
            self.stats["rescored_latents"] += pairs.rescored
            self.stats["sampled_latents"] += pairs.sampled
            self._keep(q, timesteps, pairs)
        return out

    def _keep(self, query: str, timesteps: np.ndarray, pairs: "_Pairs") -> None:
        """Keep the per-Gaussian relevancy the temporal pass has (up to ``KEPT_RELEVANCY_BYTES``): the sketch's
        values, exact where step 1 scored them (their bounds straddle 0.5) — what
        :meth:`gaussian_relevancy` returns, so the maps of its timesteps need no work of their own."""
        m, rad = pairs.margin, pairs.radius
        if m.nbytes > KEPT_RELEVANCY_BYTES:
            return
        values = torch.sigmoid(torch.from_numpy(m)).numpy()
        open_at_half = (m - rad <= 0.0) & (m + rad > 0.0)
        values[open_at_half] = pairs.exact[open_at_half]
        self._relevancy.pop(query, None)
        self._relevancy[query] = ({int(t): i for i, t in enumerate(timesteps)}, values)
        while sum(v.nbytes for _, v in self._relevancy.values()) > KEPT_RELEVANCY_BYTES:
            self._relevancy.pop(next(iter(self._relevancy)))

    def relevancy_at(self, query: str, t: int) -> Optional[torch.Tensor]:
        """(N,) :meth:`gaussian_relevancy` of ``query`` at ``t`` if a temporal pass kept it, else None."""
        rows, values = self._relevancy.get(query, ({}, None))
        i = rows.get(int(t))
        return None if i is None else torch.from_numpy(values[i])

    def _score(self, query: str, timesteps: np.ndarray, idx: np.ndarray,
               report: Callable[[float, str], None]) -> np.ndarray:
        """Exact relevancy of the pairs at row-major indices ``idx`` of the (S, N) scored pairs."""
        report(0.0, "scoring the Gaussians the sketch leaves open")
        N = self.scene.num_gaussians
        rows, g = np.divmod(np.asarray(idx, dtype=np.int64), N)
        return self.scorer.score_any(query, timesteps[rows] * N + g)

    def gaussian_relevancy(self, query: str, t: int) -> torch.Tensor:
        """(N,) relevancy of every Gaussian at ``t``: the sketch's value sigmoid(m), within its bound of the
        exact one (a few 1e-4 at most where the sketch is good), and the exact value where the bound leaves
        open which side of 0.5 it is on (those a map's relevant part is decided by)."""
        sketch = self.load()
        margin, radius = sketch.margins(self.scorer.head, self.scorer.embed_query(query), self.scorer.relevancy_scale,
                                        np.array([int(t)]))
        values = torch.sigmoid(torch.from_numpy(margin[0]))
        open_idx = np.flatnonzero((margin[0] - radius[0] <= 0.0) & (margin[0] + radius[0] > 0.0))
        if open_idx.size:
            exact = self.scorer.score_any(query, int(t) * self.scene.num_gaussians + open_idx)
            values[torch.from_numpy(open_idx)] = torch.from_numpy(exact).to(values.dtype)
            self.stats["rescored_latents"] += int(open_idx.size)
        return values

    def forget(self, query: str) -> None:
        """Drop the per-Gaussian relevancy kept for ``query``."""
        self._relevancy.pop(query, None)


class _Pairs:
    """The (S, N) scored pairs of one query: sketched margins and radii, and the exact relevancies known
    so far (NaN where not scored)."""

    def __init__(self, margin: np.ndarray, radius: np.ndarray, score: Callable[[np.ndarray], np.ndarray]):
        self.margin, self.radius = margin, radius
        self.exact = np.full(margin.shape, np.nan, dtype=np.float64)
        self._score = score
        self.rescored = 0
        self.sampled = 0

    def scored(self, idx: np.ndarray, *, sample: bool = False) -> np.ndarray:
        """Exact relevancies at row-major indices ``idx`` (scoring those not known yet)."""
        flat = self.exact.reshape(-1)
        todo = idx[np.isnan(flat[idx])]
        if todo.size:
            flat[todo] = self._score(todo)
            if sample:
                self.sampled += int(todo.size)
            else:
                self.rescored += int(todo.size)
        return flat[idx]


def _logit(p: float) -> float:
    if p <= 0.0:
        return -math.inf
    if p >= 1.0:
        return math.inf
    return math.log(p) - math.log1p(-p)


def _counts(pairs: _Pairs, weights: np.ndarray, samples: int, rng: np.random.Generator) -> TemporalCounts:
    """Steps 1-3 of the module docstring for one query."""
    m, rad = pairs.margin, pairs.radius
    S, N = m.shape
    T = int(weights.sum())
    # 1. Rel: certain from the sketch, or scored
    sure_in = m - rad > 0.0
    open_in = np.flatnonzero(~sure_in & (m + rad > 0.0))
    open_values = pairs.scored(open_in)
    open_rel = open_in[open_values > RELEVANT]
    n_sure = int(sure_in.sum())
    n_rel = n_sure + int(open_rel.size)
    if n_rel == 0:
        return np.zeros(S, dtype=np.int64), 0.0, 0, np.zeros(S, dtype=bool)
    # 2. R_avg: sketch values of the certain pairs, corrected by a sample of them drawn where the sketch
    # can be off (probability ∝ its error bound sigmoid'(m)·ρ: each draw's weighted difference is bounded)
    sure_idx = np.flatnonzero(sure_in)
    sure_values = torch.sigmoid(torch.from_numpy(m.reshape(-1)[sure_idx])).double().numpy()
    sketch_sum = float(sure_values.sum())
    open_sum = float(pairs.exact.reshape(-1)[open_rel].sum())
    bound = sure_values * (1.0 - sure_values) * rad.reshape(-1)[sure_idx]
    bound = np.maximum(bound, IMPORTANCE_FLOOR * float(bound.mean())) if n_sure else bound
    estimate = _Correction(pairs, sure_idx, sure_values, bound / bound.sum() if n_sure else bound, rng)
    size = max(2, samples)
    first: Optional[tuple[float, float]] = None
    while True:
        correction, correction_se = estimate.grow_to(size)
        r_avg, r_se = (sketch_sum + correction + open_sum) / n_rel, correction_se / n_rel
        r_low, r_high = r_avg - R_AVG_Z * r_se, r_avg + R_AVG_Z * r_se
        if first is not None:
            if max(first[0], r_low) <= min(first[1], r_high):  # a larger sample's interval, kept inside the first
                r_avg = float(np.clip(r_avg, *first))
                r_low, r_high = max(first[0], r_low), min(first[1], r_high)
            else:  # the two samples disagree beyond their errors: every value either allows stays possible
                r_low, r_high = min(first[0], r_low), max(first[1], r_high)
        else:
            first = (r_low, r_high)
        counts, low, high = _above(pairs, r_avg, r_low, r_high)
        # a timestep is open when some R_avg in the interval can put it on either side of the mean count
        undecided = (low * T <= int(weights @ high)) & (high * T > int(weights @ low))
        if not undecided.any() or estimate.exact or size >= R_AVG_MAX_SAMPLES_FACTOR * max(2, samples):
            break
        size *= 4
    if counts.sum() == 0:  # every relevant score equal (see counts_from_relevancy): count the relevant
        rel = sure_in.copy().reshape(-1)
        rel[open_rel] = True
        counts = rel.reshape(S, N).sum(axis=1).astype(np.int64)
        undecided = np.zeros(S, dtype=bool)
    return counts, float(r_avg), n_rel, undecided


class _Correction:
    """Σ (exact − sketch) over the certain pairs of Rel: an importance-sampling estimate with replacement
    (draw probabilities ``p``) and its standard error, or the exact sum once the draws would cover them all."""

    def __init__(self, pairs: _Pairs, idx: np.ndarray, sketch: np.ndarray, p: np.ndarray,
                 rng: np.random.Generator):
        self.pairs, self.idx, self.sketch, self.p, self.rng = pairs, idx, sketch, p, rng
        self.draws = np.zeros(0, dtype=np.int64)
        self.cdf: Optional[np.ndarray] = None
        self.exact = idx.size == 0

    def grow_to(self, size: int) -> tuple[float, float]:
        if self.exact or size >= self.idx.size:  # every pair: the exact sum
            self.exact = True
            return float((self.pairs.scored(self.idx, sample=True) - self.sketch).sum()), 0.0
        more = size - self.draws.size
        if more > 0:
            if self.cdf is None:
                self.cdf = np.cumsum(self.p)
            picked = np.searchsorted(self.cdf, self.rng.random(more) * self.cdf[-1], side="right")
            self.draws = np.concatenate([self.draws, np.minimum(picked, self.idx.size - 1)])
        diff = self.pairs.scored(self.idx[self.draws], sample=True) - self.sketch[self.draws]
        weighted = diff / self.p[self.draws]
        return float(weighted.mean()), float(weighted.std(ddof=1)) / math.sqrt(self.draws.size)


def _above(pairs: _Pairs, r_avg: float, r_low: float, r_high: float
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per row: the count above ``r_avg``, and its bounds over R_avg in [r_low, r_high] (exact values
    scored where the sketch cannot decide)."""
    m, rad = pairs.margin, pairs.radius
    S, N = m.shape
    sure_above = m - rad > _logit(r_high)
    open_idx = np.flatnonzero(~sure_above & (m + rad > _logit(r_low)))
    values = pairs.scored(open_idx)
    rows = open_idx // N
    low = sure_above.sum(axis=1).astype(np.int64) + np.bincount(rows[values > r_high], minlength=S)
    point = low + np.bincount(rows[(values > r_avg) & (values <= r_high)], minlength=S)
    high = low + np.bincount(rows[(values > r_low) & (values <= r_high)], minlength=S)
    return point.astype(np.int64), low, high.astype(np.int64)
