"""Per-timestep counts from a codebook, made exact where the temporal decisions depend on them.

:func:`counts_from_codes_refined` is :func:`~.temporal.counts_from_code_histogram` with exact scores
where the localization's decisions need them. R_avg and each timestep's decision (count above the
mean, s_t > 1/T) come nearly right from the codes:

1. R_avg from the code relevancies r_k, corrected by the exact scores of a uniform sample of (g, t)
   pairs: a control variate (each sampled pair's first-order relevancy around its code when the caller
   gives it, else its code's), stratified by the code's distance from 0.5 (finest near 0.5, where
   membership of Rel flips), the ``samples`` water-filled so that a stratum no larger than its share is
   scored whole (a small relevant set gets its exact R_avg). Pairs whose code is more than
   max(``MEMBERSHIP_BAND``, 2·margin) below 0.5 are taken as not relevant. Its standard error gives
   an interval of ±``R_AVG_Z`` errors.
2. Per timestep, the count above R_avg is taken from the codes, except for the members of the codes
   within ``margin`` of that interval (``margin`` widened to the 99th percentile of the deviations
   |exact − code| that step 1's sample shows near R_avg, :func:`adapted_margin`); those bound it from below and above. While a timestep's bounds
   straddle the mean count (the total of the current counts / T), its band members are re-scored
   exactly in random order, a chunk at a time (the first ``RESCORE_FIRST_FRACTION`` of them, each
   next one ``RESCORE_GROWTH`` times larger), each chunk narrowing the bounds. The re-scored members
   are a uniform sample of the timestep's band: their exact-minus-code differences correct the
   count of the members still pending (a control variate, as for R_avg), and a timestep whose
   corrected count lies more than ``row_z`` standard errors from the mean count is decided by it
   (``row_z`` = 0: by the bounds only). A fully re-scored timestep still open because of R_avg's
   interval gets a 4x larger sample (up to ``R_AVG_MAX_SAMPLES_FACTOR`` x). A band of at most
   ``exact_band_pairs`` members is re-scored whole first.
3. If ``tied_rows`` finds equally long longest segments, their s_t sums decide: from the bounds when
   they do not overlap, else from exact counts of every timestep in them.

So, against the total it returns, every timestep is decided as its exact count would be whenever every
member is within ``margin`` of its code's relevancy and R_avg lies in its interval (exact when
``samples`` covers every pair), except with a probability of about 1e-6 per timestep decided from its
sample; the total mixes exact counts and corrected estimates.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, NamedTuple, Optional

import numpy as np
import torch

from .options import R_AVG_SAMPLES
from .temporal import RELEVANT, counts_from_code_histogram

# codes within this distance of 0.5 may hold relevant and irrelevant Gaussians alike; the band is several
# times the per-Gaussian error of a large codebook, so the relevant pairs it leaves out are negligible
# against R_avg
MEMBERSHIP_BAND = 0.1
R_AVG_Z = 3.0  # R_avg's confidence interval, in standard errors of its sampled estimate
R_AVG_MAX_SAMPLES_FACTOR = 16  # the sample grows 4x at a time up to this many times the first one
#: an open timestep's first chunk of re-scored band members is this fraction of them (at least
#: ``RESCORE_MIN_CHUNK``); each later chunk is ``RESCORE_GROWTH`` times the one before
RESCORE_FIRST_FRACTION = 1 / 16
RESCORE_MIN_CHUNK = 64
RESCORE_GROWTH = 3
#: the band's margin is widened to this quantile of |exact − code| of R_avg's sampled pairs whose code lies
#: within ``ADAPT_WINDOW`` of R_avg (when at least ``ADAPT_MIN_PAIRS`` are), up to ``MAX_MARGIN``: a field
#: whose codes are coarse for the query gets the band its members need
ADAPT_QUANTILE = 0.99
ADAPT_WINDOW = 0.15
ADAPT_MIN_PAIRS = 100
MAX_MARGIN = 0.25
#: a timestep's decision is taken from its re-scored sample once its count is this many standard errors
#: from the mean count (a wrong decision then has a probability below 1e-6 per timestep)
ROW_DECISION_Z = 5.0
#: a band holding at most this many (Gaussian, timestep) pairs is re-scored whole at once (about 1 s per
#: 100k on the reference machine)
EXACT_BAND_PAIRS = 50_000


class RefinedCounts(NamedTuple):
    """What :func:`counts_from_codes_refined` returns."""

    counts: np.ndarray      # (S,) int64 count above R_avg per scored timestep
    r_avg: float
    relevant: int           # relevant (g, t) pairs, estimated
    rescored: int           # latents re-scored
    sampled: int            # latents sampled for R_avg
    undecided: np.ndarray   # (S,) bool: neither the bounds nor the sample settled the decision s_t > 1/T


def counts_from_codes_refined(code_scores, histogram, *, members: Callable[[np.ndarray, np.ndarray], tuple],
                              score: Callable[[np.ndarray], np.ndarray], sample: Callable[[list, list], list],
                              margin: float,
                              weights: Optional[np.ndarray] = None, samples: int = R_AVG_SAMPLES,
                              tied_rows: Optional[Callable[[np.ndarray], list]] = None,
                              exact_band_pairs: int = EXACT_BAND_PAIRS, row_z: float = ROW_DECISION_Z,
                              margin_quantile: float = ADAPT_QUANTILE) -> RefinedCounts:
    """:func:`counts_from_code_histogram` with exact scores where the localization's decisions need them.

    The steps and what they guarantee are in the module docstring.

    Args:
        code_scores: (K,) relevancy of each code.
        histogram: (S,K) Gaussians holding each code at each scored timestep.
        members: (codes (C,), rows (U,)) -> (rows (M,) into the S scored timesteps, codes (M,), handles (M,)):
            the Gaussians holding one of ``codes`` at the scored timesteps ``rows``.
        score: (handles (M,), window) -> (M,) their exact relevancy; with a window (low, high) a member
            whose relevancy is certainly <= low (> high) may get any value <= low (> high) instead: every
            threshold the band's decisions use lies in the window it is given (R_avg's first interval).
        sample: (list of codes (C_j,), list of sizes) -> list of (codes (M_j,), scores (M_j,)[, controls
            (M_j,)]): for each group of codes, exact relevancy of a uniform sample without replacement of
            that many of its members at the scored timesteps (all of them when fewer); one call for every
            stratum. Only relevant scores (> 0.5) are used as values: an irrelevant one may be any value
            <= 0.5. ``controls``, when given, are each member's first-order relevancy around its code,
            r_k + ∇r(c_k)·(z − c_k), whose sum over every member of a code (the code being the mean of its
            members) is r_k times their count: the control variate of R_avg then leaves only the
            second-order part of each deviation.
        margin: half-width of the band of codes around R_avg whose members are re-scored (0 = lookup).
        weights: (S,) timesteps each scored timestep stands for after stride expansion (default 1 each).
        samples: exact scores spent on R_avg.
        tied_rows: positive (S,) bool -> one array per longest segment when more than one is longest (else
            none): the scored row of each of its timesteps (see :func:`tied_segment_rows`).
        exact_band_pairs: a band with at most this many members is re-scored whole (0: never).
        row_z: standard errors between a timestep's corrected count and the mean count that decide it
            before its band is re-scored whole (0: never).
        margin_quantile: the band is widened to this quantile of the sampled deviations (see
            :func:`adapted_margin`; 0: ``margin`` as given).
    Returns:
        counts (S,), R_avg, number of relevant (g,t) pairs (estimated), latents re-scored, latents sampled,
        and the timesteps left undecided: every band member re-scored, R_avg's sample at its largest,
        and still their bounds straddle the mean count (their counts lie within R_avg's error of it:
        only the exact path decides them).
    """
    r = np.asarray(code_scores.double().numpy() if isinstance(code_scores, torch.Tensor) else code_scores,
                   dtype=np.float64)
    hist = np.asarray(histogram)
    if margin <= 0:
        counts, r_avg, n_rel = counts_from_code_histogram(r, hist)
        return RefinedCounts(counts, r_avg, n_rel, 0, 0, np.zeros(hist.shape[0], dtype=bool))
    S = hist.shape[0]
    w = np.ones(S, dtype=np.int64) if weights is None else np.asarray(weights, dtype=np.int64)
    T = int(w.sum())
    per_code = hist.sum(axis=0, dtype=np.int64)
    held = per_code > 0
    # 1. R_avg with a confidence interval; widened samples narrow it while a decision depends on it
    size = int(samples)
    estimate = _sampled_r_avg(r, per_code, held, sample, margin, size)
    r_avg, r_se, n_rel, sampled = estimate[:4]
    margin = adapted_margin(margin, estimate, margin_quantile)
    if n_rel == 0:
        return RefinedCounts(np.zeros(S, dtype=np.int64), 0.0, 0, 0, sampled, np.zeros(S, dtype=bool))
    r_low, r_high = r_avg - R_AVG_Z * r_se, r_avg + R_AVG_Z * r_se
    first = (r_low, r_high)
    # 2. counts above R_avg: by code outside the band, bounded inside it until re-scored
    band = _Band(r, hist, held, r_avg, first, margin, members, score)
    band.score_whole_if_at_most(exact_band_pairs)
    while True:  # the total is the estimate's; each row's own count is decided from its bounds or sample
        low, high = band.bounds(r_low, r_high)
        counts, variance, pending = band.estimate(r_avg)
        total = int(w @ counts)
        undecided = (low * T <= total) & (high * T > total)
        if row_z > 0:
            undecided &= ~_settled_by_sample(counts, variance, pending, total, w, row_z)
        todo = undecided & (pending > 0)
        if todo.any():
            band.score_next(np.nonzero(todo)[0])
        elif undecided.any() and size < R_AVG_MAX_SAMPLES_FACTOR * samples and r_se > 0:
            # those rows are exact: only R_avg's interval leaves them open, so estimate it again from a
            # 4x larger sample, keeping the interval inside the first one (the band was built for it)
            size *= 4
            estimate, r_se, n_rel, more = _sampled_r_avg(r, per_code, held, sample, margin, size)[:4]
            sampled += more
            r_avg, r_low, r_high = _narrowed_interval(estimate, r_se, first)
        else:
            break
    # 3. equally long longest segments, and the degenerate case of every relevant score equal
    counts = band.estimate(r_avg)[0]
    tied = tied_rows(counts * T > int(w @ counts)) if tied_rows is not None and counts.sum() > 0 else []
    if tied and _ties_need_exact_counts(band, tied, r_low, r_high):
        rows = np.unique(np.concatenate(tied))
        band.score_next(rows[band.unsure[rows] > 0], everything=True)
        counts = band.estimate(r_avg)[0]
    if counts.sum() == 0:  # every relevant score equal (see counts_from_relevancy): count the relevant
        band.rescore_without_window()
        undecided = np.zeros(S, dtype=bool)
        counts = (hist @ (band.outside & (r > RELEVANT)).astype(hist.dtype)).astype(np.int64) + band.above(RELEVANT)[0]
    return RefinedCounts(counts, r_avg, n_rel, band.rescored, sampled, undecided)


def _narrowed_interval(estimate: float, r_se: float, first: tuple[float, float]) -> tuple[float, float, float]:
    """R_avg and its interval from a new estimate, kept inside the first interval (the band was built for
    it); where the two disagree beyond their intervals, the newer estimate alone."""
    first_low, first_high = first
    r_avg = float(np.clip(estimate, first_low, first_high))
    r_low, r_high = max(first_low, estimate - R_AVG_Z * r_se), min(first_high, estimate + R_AVG_Z * r_se)
    if r_low > r_high:
        r_low = r_high = r_avg
    return r_avg, r_low, r_high


def _settled_by_sample(counts: np.ndarray, variance: np.ndarray, pending: np.ndarray, total: int,
                       weights: np.ndarray, z: float) -> np.ndarray:
    """(S,) bool: rows with pending members whose corrected count is more than ``z`` standard errors of
    the difference count·T − total from the mean count (the total's own error, the sum of every row's,
    included)."""
    T = int(weights.sum())
    finite = np.isfinite(variance)
    total_var = float(weights[finite].astype(np.float64) ** 2 @ variance[finite])
    se = np.sqrt(T * T * np.where(finite, variance, 0.0) + total_var)
    return finite & (pending > 0) & (np.abs(counts * T - total) > z * se)


def _ties_need_exact_counts(band: "_Band", tied: list[np.ndarray], r_low: float, r_high: float) -> bool:
    """Whether the bounds leave open which of the tied segments has the larger sum of s_t."""
    low, high = band.bounds(r_low, r_high)
    sums_low = np.array([low[rows].sum() for rows in tied])
    sums_high = np.array([high[rows].sum() for rows in tied])
    best = int(np.argmax(sums_low))
    return bool(np.any(np.delete(sums_high, best) >= sums_low[best]))


@dataclass
class _OpenRow:
    """A scored timestep's band members: those still pending (in random order) and those re-scored."""

    pending_codes: np.ndarray   # (P,) int64
    pending_handles: np.ndarray  # (P,) int64
    chunk: int                   # members the next chunk re-scores
    scores: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.float64))  # exact inside the window
    scored_codes: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    scored_handles: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))


class _Band:
    """The codes within ``margin`` of R_avg's first interval and the exact re-scoring of their members,
    per scored timestep (row), a random chunk at a time (see :func:`counts_from_codes_refined`)."""

    def __init__(self, r: np.ndarray, hist: np.ndarray, held: np.ndarray, r_avg: float,
                 window: tuple[float, float], margin: float, members: Callable, score: Callable):
        r_low, r_high = window
        inside = held & (r > r_low - margin) & (r < r_high + margin)
        self.r = r
        self.codes = np.nonzero(inside)[0]
        self.hist = np.asarray(hist[:, self.codes], dtype=np.int64)  # (S,B)
        self.r_band = r[self.codes]
        self.outside = ~inside
        # outside the band a code is on the same side of every R in the (first) interval
        self.sure = (hist @ (self.outside & (r > r_avg)).astype(hist.dtype)).astype(np.int64)
        self.unsure = self.hist.sum(axis=1)
        self.window = window  # r_low, r_avg and r_high stay inside it
        self.members, self.score = members, score
        self.rows_open: dict[int, _OpenRow] = {}
        self.order_rng = np.random.default_rng(0)
        self.rescored = 0

    def open_rows(self, rows: np.ndarray) -> None:
        rows = np.array([i for i in rows if int(i) not in self.rows_open], dtype=np.int64)
        if rows.size == 0:
            return
        at, codes_of, handles = (np.asarray(x, dtype=np.int64) for x in self.members(self.codes, rows))
        for i in rows:
            mine = np.flatnonzero(at == i)
            mine = mine[self.order_rng.permutation(mine.size)]  # re-scored in random order: a uniform sample
            first = max(RESCORE_MIN_CHUNK, int(np.ceil(mine.size * RESCORE_FIRST_FRACTION)))
            self.rows_open[int(i)] = _OpenRow(codes_of[mine], handles[mine], first)

    def score_next(self, rows: np.ndarray, everything: bool = False) -> None:
        """Exact scores for the next chunk (or all) of the pending band members of ``rows``."""
        self.open_rows(rows)
        takes = []
        for i in rows:
            row = self.rows_open[int(i)]
            take = row.pending_handles.size if everything else min(row.chunk, row.pending_handles.size)
            if take:
                takes.append((row, take))
        if not takes:
            return
        exact = np.asarray(self.score(np.concatenate([row.pending_handles[:k] for row, k in takes]), self.window),
                           dtype=np.float64)
        self.rescored += int(exact.size)
        start = 0
        for row, k in takes:
            row.scores = np.concatenate([row.scores, exact[start:start + k]])
            row.scored_codes = np.concatenate([row.scored_codes, row.pending_codes[:k]])
            row.scored_handles = np.concatenate([row.scored_handles, row.pending_handles[:k]])
            row.pending_codes, row.pending_handles = row.pending_codes[k:], row.pending_handles[k:]
            row.chunk *= RESCORE_GROWTH
            start += k

    def above(self, threshold: float) -> tuple[np.ndarray, np.ndarray]:
        """(S,) band members above ``threshold`` (exact where re-scored, by code elsewhere) and (S,) still
        pending."""
        above = self.hist @ (self.r_band > threshold)
        pending = self.unsure.copy()
        for i, row in self.rows_open.items():
            above[i] = int((row.scores > threshold).sum()) + int((self.r[row.pending_codes] > threshold).sum())
            pending[i] = row.pending_codes.size
        return above, pending

    def estimate(self, threshold: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Counts above ``threshold`` with the pending members corrected by the re-scored ones.

        A row's re-scored members are a uniform sample of its band: the mean of (exact above) − (code
        above) over them, times the pending members, corrects the pending members' count by code. Its
        variance uses (flips + 2) / (n + 4) for the mean square of that difference (an upper estimate
        that stays above 0 when no flip was seen).

        Returns:
            counts (S,) int64 (within the row's hard bounds at ``threshold``), variance (S,) float64 of
            each count (0 when nothing is pending, inf for a row not opened), pending (S,) int64.
        """
        above, pending = self.above(threshold)
        counts = (self.sure + above).astype(np.int64)
        variance = np.where(self.unsure > 0, np.inf, 0.0)
        for i, row in self.rows_open.items():
            n, left = row.scores.size, row.pending_codes.size
            if left == 0:
                variance[i] = 0.0
            if n == 0 or left == 0:
                continue
            flips = (row.scores > threshold).astype(np.float64) - (self.r[row.scored_codes] > threshold)
            exact_part = self.sure[i] + int((row.scores > threshold).sum())
            corrected = counts[i] + left * float(flips.mean())
            counts[i] = int(np.clip(np.rint(corrected), exact_part, exact_part + left))
            mean_square = (float(np.abs(flips).sum()) + 2.0) / (n + 4.0)
            # the pending members' sum is the band's total less the re-scored sum: its error is that of
            # estimating the total from a sample of n of n + left without replacement
            variance[i] = (n + left) * left * mean_square / n
        return counts, variance, pending

    def score_whole_if_at_most(self, limit: int) -> None:
        """Score every band member now when there are at most ``limit`` of them (a small object's few codes):
        the counts, and the total each timestep is compared with, are then exact wherever every code outside
        the band has its members on its own side of R_avg, however far its members are from its score."""
        if 0 < int(self.unsure.sum()) <= int(limit):
            self.score_next(np.nonzero(self.unsure > 0)[0], everything=True)

    def bounds(self, r_low: float, r_high: float) -> tuple[np.ndarray, np.ndarray]:
        """(S,) lowest and highest count above any R in [r_low, r_high] the pending members allow."""
        low, high = self.sure.copy(), self.sure + self.unsure
        for i, row in self.rows_open.items():
            low[i] += int((row.scores > r_high).sum())
            high[i] = self.sure[i] + int((row.scores > r_low).sum()) + row.pending_codes.size
        return low, high

    def rescore_without_window(self) -> None:
        """Exact scores, without a window, of every member scored so far (0.5 may lie outside the window)."""
        for row in self.rows_open.values():
            if row.scored_handles.size:
                row.scores = np.asarray(self.score(row.scored_handles, None), dtype=np.float64)
                self.rescored += int(row.scored_handles.size)


class _RAvgEstimate(NamedTuple):
    r_avg: float          # 0 when no pair is relevant
    se: float             # its standard error
    relevant: int         # estimated |Rel|
    sampled: int          # latents sampled
    deviations: np.ndarray  # (M,) exact - code of the sampled pairs relevant by both, their codes' scores (M,)
    codes: np.ndarray


def _sampled_r_avg(r: np.ndarray, per_code: np.ndarray, held: np.ndarray, sample: Callable, margin: float,
                   samples: int) -> _RAvgEstimate:
    """R_avg = F / G over Rel from the code relevancies, corrected by the exact-minus-code differences of a
    stratified sample (a control variate), with its standard error (linearized ratio estimator)."""
    rel = r > RELEVANT
    F, G = float(per_code[rel] @ r[rel]), float(per_code[rel].sum())
    # strata by distance from 0.5, finest where membership flips most (water-filled: small ones whole)
    edges = np.array([-max(MEMBERSHIP_BAND, 2 * margin), -0.05, -0.02, -0.005, 0.005, 0.02, 0.05, 0.1, np.inf])
    which = np.searchsorted(edges, r - RELEVANT, side="right") - 1
    strata = [held & (which == i) for i in range(len(edges) - 1)]
    populations = [int(per_code[s].sum()) for s in strata]
    budget, requests = samples, []
    for i in np.argsort(populations, kind="stable"):  # small strata are scored whole, the rest share
        if populations[i] == 0:
            continue
        left = sum(1 for p in populations if p >= populations[i])
        size = max(1, min(populations[i], budget // max(left, 1)))
        budget -= size
        requests.append((int(i), size))
    drawn, deviations, deviation_codes = [], [], []
    answers = sample([np.nonzero(strata[i])[0] for i, _ in requests], [size for _, size in requests]) \
        if requests else []
    for (i, _), answer in zip(requests, answers):
        codes, exact = answer[0], np.asarray(answer[1], dtype=np.float64)
        if exact.size == 0:
            continue
        coded = r[np.asarray(codes, dtype=np.int64)]
        # the control: each pair's first-order value around its code where the sample has it (it sums over
        # a code's members to the code's relevancy times their count, as the code's own value does)
        control = coded if len(answer) < 3 or answer[2] is None else np.asarray(answer[2], dtype=np.float64)
        f = np.where(exact > RELEVANT, exact, 0.0) - np.where(coded > RELEVANT, control, 0.0)
        g = (exact > RELEVANT).astype(np.float64) - (coded > RELEVANT)
        F += populations[i] * float(f.mean())
        G += populations[i] * float(g.mean())
        drawn.append((populations[i], f, g))
        both = (exact > RELEVANT) & (coded > RELEVANT)
        deviations.append(exact[both] - coded[both])
        deviation_codes.append(coded[both])
    sampled = sum(f.size for _, f, _ in drawn)
    dev = np.concatenate(deviations) if deviations else np.zeros(0)
    dev_codes = np.concatenate(deviation_codes) if deviation_codes else np.zeros(0)
    if not G >= 0.5:  # not one relevant pair (to the sample's resolution)
        return _RAvgEstimate(0.0, 0.0, 0, sampled, dev, dev_codes)
    r_avg = F / G
    var = sum(P * P * max(0.0, 1.0 - f.size / P) * float(np.var(f - r_avg * g, ddof=1)) / f.size
              for P, f, g in drawn if f.size > 1)
    return _RAvgEstimate(float(np.clip(r_avg, RELEVANT, 1.0)), float(np.sqrt(var)) / G, int(round(G)), sampled,
                         dev, dev_codes)


def adapted_margin(margin: float, estimate: _RAvgEstimate, quantile: float) -> float:
    """The band's half-width: ``margin``, widened to the ``quantile`` of |exact − code| over the sampled
    pairs whose code lies within ``ADAPT_WINDOW`` of R_avg (the members whose side of R_avg a coarse code
    misjudges), at most ``MAX_MARGIN``; ``margin`` when ``quantile`` is 0 or fewer than
    ``ADAPT_MIN_PAIRS`` such pairs were sampled."""
    near = np.abs(estimate.codes - estimate.r_avg) < ADAPT_WINDOW
    if quantile <= 0 or int(near.sum()) < ADAPT_MIN_PAIRS:
        return float(margin)
    return float(max(margin, min(np.quantile(np.abs(estimate.deviations[near]), quantile), MAX_MARGIN)))
