"""Temporal localization (paper §3.2, §6.1 and supplementary A.2), independent of how R was computed.

Given the relevancy R of every Gaussian g at every (sampled) timestep t:

1. Rel = {R > 0.5} over all (g, t); R_avg = mean of Rel.
2. |Rel_t| = #{g : R(g, t) > R_avg};  s_t = |Rel_t| / Σ_t' |Rel_t'|.
3. t is positive when s_t > k = 1/T (evaluated exactly in integers: |Rel_t| · T > Σ|Rel_t'|).
4. Dilate the binary array [s_t > k] (scipy.ndimage), take the longest positive run as the segment and
   its centre as the peak; every run is returned too.

Two degenerate cases the definition leaves open are answered explicitly (and documented in the
result's ``message``): when every relevant Gaussian has exactly the same score nothing is strictly
above R_avg, so the relevant ones are counted instead (that is ``R ≥ R_avg``); when every sampled
timestep has the same non-zero count (including T = 1) the strict threshold s_t > 1/T cannot select
anything, and every timestep is positive (the query is everywhere).

With a temporal stride only every k-th timestep is scored; each timestep takes the count of its
nearest scored timestep before normalizing, so s_t still has one entry per timestep.
"""
from __future__ import annotations

from typing import Callable, Optional, Sequence

import numpy as np
import torch
from scipy import ndimage

from .options import R_AVG_SAMPLES
from .results import TemporalResult

RELEVANT = 0.5


def counts_from_relevancy(scores) -> tuple[np.ndarray, float, int]:
    """Per-timestep counts of above-average relevant Gaussians.

    Args:
        scores: (T,N) relevancy (numpy or torch), one row per scored timestep.
    Returns:
        counts (T,) int64 = |Rel_t|, R_avg (float), number of relevant (g,t) pairs.
    """
    R = torch.as_tensor(scores)
    T = R.shape[0]
    rel = R > RELEVANT
    n_rel = int(rel.sum())
    if n_rel == 0:
        return np.zeros(T, dtype=np.int64), 0.0, 0
    r_avg = float(R[rel].double().sum() / n_rel)
    counts = (R > r_avg).sum(dim=tuple(range(1, R.ndim))).numpy().astype(np.int64)
    if counts.sum() == 0:  # every relevant score equal: R >= R_avg means "relevant"
        counts = rel.sum(dim=tuple(range(1, R.ndim))).numpy().astype(np.int64)
    return counts, r_avg, n_rel


def counts_from_code_histogram(code_scores, histogram) -> tuple[np.ndarray, float, int]:
    """Same as :func:`counts_from_relevancy` when Gaussians share K code relevancies.

    Args:
        code_scores: (K,) relevancy of each code.
        histogram: (T,K) number of Gaussians holding each code at each scored timestep.
    Returns:
        counts (T,), R_avg, number of relevant (g,t) pairs — a (T,K) reduction, no per-Gaussian work.
    """
    r = np.asarray(code_scores.double().numpy() if isinstance(code_scores, torch.Tensor) else code_scores,
                   dtype=np.float64)
    hist = np.asarray(histogram)
    T = hist.shape[0]
    per_code = hist.sum(axis=0, dtype=np.int64)  # (K,) Gaussians holding each code over the timesteps
    rel = r > RELEVANT
    n_rel = int(per_code[rel].sum())
    if n_rel == 0:
        return np.zeros(T, dtype=np.int64), 0.0, 0
    r_avg = float(per_code[rel] @ r[rel] / n_rel)
    above = r > r_avg
    counts = hist @ above.astype(hist.dtype)  # (T,K) @ (K,) matrix-vector: the whole per-query cost
    if counts.sum() == 0:
        counts = hist @ rel.astype(hist.dtype)
    return counts.astype(np.int64), r_avg, n_rel


# codes within this distance of 0.5 may hold relevant and irrelevant Gaussians alike; the band is several
# times the per-Gaussian error of a large codebook, so the relevant pairs it leaves out are negligible
# against R_avg
MEMBERSHIP_BAND = 0.1
R_AVG_Z = 3.0  # R_avg's confidence interval, in standard errors of its sampled estimate
R_AVG_MAX_SAMPLES_FACTOR = 16  # the sample grows 4x at a time up to this many times the first one
RESCORE_CHUNKS = 4  # an open timestep's band members are re-scored in this many random chunks
RESCORE_MIN_CHUNK = 64
#: a band holding at most this many (Gaussian, timestep) pairs is re-scored whole at once (about 1 s per
#: 100k on the reference machine)
EXACT_BAND_PAIRS = 50_000


def counts_from_codes_refined(code_scores, histogram, *, members: Callable[[np.ndarray, np.ndarray], tuple],
                              score: Callable[[np.ndarray], np.ndarray], sample: Callable[[list, list], list],
                              margin: float,
                              weights: Optional[np.ndarray] = None, samples: int = R_AVG_SAMPLES,
                              tied_rows: Optional[Callable[[np.ndarray], list]] = None,
                              exact_band_pairs: int = EXACT_BAND_PAIRS) -> tuple[np.ndarray, float, int, int, int]:
    """:func:`counts_from_code_histogram` with exact scores where the localization's decisions need them.

    R_avg and each timestep's decision (count above the mean, s_t > 1/T) come nearly right from the codes:

    1. R_avg from the code relevancies r_k, corrected by the exact scores of a uniform sample of (g, t)
       pairs: a control variate, stratified by the code's distance from 0.5 (finest near 0.5, where
       membership of Rel flips), the ``samples`` water-filled so that a stratum no larger than its share is
       scored whole (a small relevant set gets its exact R_avg). Pairs whose code is more than
       max(``MEMBERSHIP_BAND``, 2·margin) below 0.5 are taken as not relevant. Its standard error gives
       an interval of ±``R_AVG_Z`` errors.
    2. Per timestep, the count above R_avg is taken from the codes, except for the members of the codes
       within ``margin`` of that interval; those bound it from below and above. While a timestep's bounds
       straddle the mean count (the total of the current counts / T), its band members are re-scored
       exactly, a random 1/``RESCORE_CHUNKS`` of them at a time, each chunk narrowing the bounds. A
       fully re-scored timestep still open because of R_avg's interval gets a 4x larger sample (up to
       ``R_AVG_MAX_SAMPLES_FACTOR`` x). Members not re-scored count by their code (the lookup estimate,
       inside the bounds); a band of at most ``exact_band_pairs`` members is re-scored whole first.
    3. If ``tied_rows`` finds equally long longest segments, their s_t sums decide: from the bounds when
       they do not overlap, else from exact counts of every timestep in them.

    So, against the total it returns, every timestep is decided as its exact count would be whenever every
    member is within ``margin`` of its code's relevancy and R_avg lies in its interval (exact when
    ``samples`` covers every pair); the total mixes exact counts and lookup estimates.

    Args:
        code_scores: (K,) relevancy of each code.
        histogram: (S,K) Gaussians holding each code at each scored timestep.
        members: (codes (C,), rows (U,)) -> (rows (M,) into the S scored timesteps, codes (M,), handles (M,)):
            the Gaussians holding one of ``codes`` at the scored timesteps ``rows``.
        score: (handles (M,), window) -> (M,) their exact relevancy; with a window (low, high) a member
            whose relevancy is certainly <= low (> high) may get any value <= low (> high) instead: every
            threshold the band's decisions use lies in the window it is given (R_avg's first interval).
        sample: (list of codes (C_j,), list of sizes) -> list of (codes (M_j,), scores (M_j,)): for each
            group of codes, exact relevancy of a uniform sample without replacement of that many of its
            members at the scored timesteps (all of them when fewer); one call for every stratum. Only
            relevant scores (> 0.5) are used as values: an irrelevant one may be any value <= 0.5.
        margin: half-width of the band of codes around R_avg whose members are re-scored (0 = lookup).
        weights: (S,) timesteps each scored timestep stands for after stride expansion (default 1 each).
        samples: exact scores spent on R_avg.
        tied_rows: positive (S,) bool -> one array per longest segment when more than one is longest (else
            none): the scored row of each of its timesteps (see :func:`tied_segment_rows`).
        exact_band_pairs: a band with at most this many members is re-scored whole (0: never).
    Returns:
        counts (S,), R_avg, number of relevant (g,t) pairs (estimated), latents re-scored, latents sampled.
    """
    r = np.asarray(code_scores.double().numpy() if isinstance(code_scores, torch.Tensor) else code_scores,
                   dtype=np.float64)
    hist = np.asarray(histogram)
    if margin <= 0:
        counts, r_avg, n_rel = counts_from_code_histogram(r, hist)
        return counts, r_avg, n_rel, 0, 0
    S = hist.shape[0]
    w = np.ones(S, dtype=np.int64) if weights is None else np.asarray(weights, dtype=np.int64)
    T = int(w.sum())
    per_code = hist.sum(axis=0, dtype=np.int64)
    held = per_code > 0
    # 1. R_avg with a confidence interval; widened samples narrow it while a decision depends on it
    size = int(samples)
    r_avg, r_se, n_rel, sampled = _sampled_r_avg(r, per_code, held, sample, margin, size)
    if n_rel == 0:
        return np.zeros(S, dtype=np.int64), 0.0, 0, 0, sampled
    r_low, r_high = r_avg - R_AVG_Z * r_se, r_avg + R_AVG_Z * r_se
    first = (r_low, r_high)
    # 2. counts above R_avg: by code outside the band, bounded inside it until re-scored
    band = _Band(r, hist, held, r_avg, first, margin, members, score)
    band.score_whole_if_at_most(exact_band_pairs)
    while True:  # the total is the estimate's; each row's own count is decided from its bounds
        low, high = band.bounds(r_low, r_high)
        above, pending = band.above(r_avg)
        total = int(w @ (band.sure + above))
        undecided = (low * T <= total) & (high * T > total)
        todo = undecided & (pending > 0)
        if todo.any():
            band.score_next(np.nonzero(todo)[0])
        elif undecided.any() and size < R_AVG_MAX_SAMPLES_FACTOR * samples and r_se > 0:
            # those rows are exact: only R_avg's interval leaves them open, so estimate it again from a
            # 4x larger sample, keeping the interval inside the first one (the band was built for it)
            size *= 4
            estimate, r_se, n_rel, more = _sampled_r_avg(r, per_code, held, sample, margin, size)
            sampled += more
            r_avg, r_low, r_high = _narrowed_interval(estimate, r_se, first)
        else:
            break
    # 3. equally long longest segments, and the degenerate case of every relevant score equal
    counts = band.sure + band.above(r_avg)[0]
    tied = tied_rows(counts * T > int(w @ counts)) if tied_rows is not None and counts.sum() > 0 else []
    if tied and _ties_need_exact_counts(band, tied, r_low, r_high):
        rows = np.unique(np.concatenate(tied))
        band.score_next(rows[band.unsure[rows] > 0], everything=True)
        counts = band.sure + band.above(r_avg)[0]
    if counts.sum() == 0:  # every relevant score equal (see counts_from_relevancy): count the relevant
        band.rescore_without_window()
        counts = (hist @ (band.outside & (r > RELEVANT)).astype(hist.dtype)).astype(np.int64) + band.above(RELEVANT)[0]
    return counts, r_avg, n_rel, band.rescored, sampled


def _narrowed_interval(estimate: float, r_se: float, first: tuple[float, float]) -> tuple[float, float, float]:
    """R_avg and its interval from a new estimate, kept inside the first interval (the band was built for
    it); where the two disagree beyond their intervals, the newer estimate alone."""
    first_low, first_high = first
    r_avg = float(np.clip(estimate, first_low, first_high))
    r_low, r_high = max(first_low, estimate - R_AVG_Z * r_se), min(first_high, estimate + R_AVG_Z * r_se)
    if r_low > r_high:
        r_low = r_high = r_avg
    return r_avg, r_low, r_high


def _ties_need_exact_counts(band: "_Band", tied: list[np.ndarray], r_low: float, r_high: float) -> bool:
    """Whether the bounds leave open which of the tied segments has the larger sum of s_t."""
    low, high = band.bounds(r_low, r_high)
    sums_low = np.array([low[rows].sum() for rows in tied])
    sums_high = np.array([high[rows].sum() for rows in tied])
    best = int(np.argmax(sums_low))
    return bool(np.any(np.delete(sums_high, best) >= sums_low[best]))


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
        # row -> [pending codes, pending handles, scores so far (exact inside the window), chunk, scored handles]
        self.rows_open: dict[int, list] = {}
        self.order_rng = np.random.default_rng(0)
        self.rescored = 0

    def open_rows(self, rows: np.ndarray) -> None:
        rows = np.array([i for i in rows if int(i) not in self.rows_open], dtype=np.int64)
        if rows.size == 0:
            return
        at, codes_of, handles = (np.asarray(x, dtype=np.int64) for x in self.members(self.codes, rows))
        for i in rows:
            mine = np.flatnonzero(at == i)
            mine = mine[self.order_rng.permutation(mine.size)]  # re-scored in random order, a chunk at a time
            self.rows_open[int(i)] = [codes_of[mine], handles[mine], np.zeros(0, dtype=np.float64),
                                      max(RESCORE_MIN_CHUNK, -(-mine.size // RESCORE_CHUNKS)),
                                      np.zeros(0, dtype=np.int64)]

    def score_next(self, rows: np.ndarray, everything: bool = False) -> None:
        """Exact scores for the next chunk (or all) of the pending band members of ``rows``."""
        self.open_rows(rows)
        takes = []
        for i in rows:
            codes_i, handles_i, _, chunk, _ = self.rows_open[int(i)]
            take = handles_i.size if everything else min(chunk, handles_i.size)
            if take:
                takes.append((int(i), take))
        if not takes:
            return
        exact = np.asarray(self.score(np.concatenate([self.rows_open[i][1][:k] for i, k in takes]), self.window),
                           dtype=np.float64)
        self.rescored += int(exact.size)
        start = 0
        for i, k in takes:
            entry = self.rows_open[i]
            entry[2] = np.concatenate([entry[2], exact[start:start + k]])
            entry[4] = np.concatenate([entry[4], entry[1][:k]])
            entry[0], entry[1] = entry[0][k:], entry[1][k:]
            start += k

    def above(self, threshold: float) -> tuple[np.ndarray, np.ndarray]:
        """(S,) band members above ``threshold`` (exact where re-scored, by code elsewhere) and (S,) still
        pending."""
        above = self.hist @ (self.r_band > threshold)
        pending = self.unsure.copy()
        for i, (codes_i, _, exact_i, _, _) in self.rows_open.items():
            above[i] = int((exact_i > threshold).sum()) + int((self.r[codes_i] > threshold).sum())
            pending[i] = codes_i.size
        return above, pending

    def score_whole_if_at_most(self, limit: int) -> None:
        """Score every band member now when there are at most ``limit`` of them (a small object's few codes):
        the counts, and the total each timestep is compared with, are then exact wherever every code outside
        the band has its members on its own side of R_avg, however far its members are from its score."""
        if 0 < int(self.unsure.sum()) <= int(limit):
            self.score_next(np.nonzero(self.unsure > 0)[0], everything=True)

    def bounds(self, r_low: float, r_high: float) -> tuple[np.ndarray, np.ndarray]:
        """(S,) lowest and highest count above any R in [r_low, r_high] the pending members allow."""
        low, high = self.sure.copy(), self.sure + self.unsure
        for i, (codes_i, _, exact_i, _, _) in self.rows_open.items():
            low[i] += int((exact_i > r_high).sum())
            high[i] = self.sure[i] + int((exact_i > r_low).sum()) + codes_i.size
        return low, high

    def rescore_without_window(self) -> None:
        """Exact scores, without a window, of every member scored so far (0.5 may lie outside the window)."""
        for entry in self.rows_open.values():
            if entry[4].size:
                entry[2] = np.asarray(self.score(entry[4], None), dtype=np.float64)
                self.rescored += int(entry[4].size)


def _sampled_r_avg(r: np.ndarray, per_code: np.ndarray, held: np.ndarray, sample: Callable, margin: float,
                   samples: int) -> tuple[float, float, int, int]:
    """R_avg = F / G over Rel from the code relevancies, corrected by the exact-minus-code differences of a
    stratified sample (a control variate), with its standard error (linearized ratio estimator).

    Returns:
        R_avg (0 when no pair is relevant), its standard error, estimated |Rel|, latents sampled.
    """
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
    drawn = []
    answers = sample([np.nonzero(strata[i])[0] for i, _ in requests], [size for _, size in requests]) \
        if requests else []
    for (i, _), (codes, exact) in zip(requests, answers):
        exact = np.asarray(exact, dtype=np.float64)
        if exact.size == 0:
            continue
        coded = r[np.asarray(codes, dtype=np.int64)]
        f = np.where(exact > RELEVANT, exact, 0.0) - np.where(coded > RELEVANT, coded, 0.0)
        g = (exact > RELEVANT).astype(np.float64) - (coded > RELEVANT)
        F += populations[i] * float(f.mean())
        G += populations[i] * float(g.mean())
        drawn.append((populations[i], f, g))
    sampled = sum(f.size for _, f, _ in drawn)
    if not G >= 0.5:  # not one relevant pair (to the sample's resolution)
        return 0.0, 0.0, 0, sampled
    r_avg = F / G
    var = sum(P * P * max(0.0, 1.0 - f.size / P) * float(np.var(f - r_avg * g, ddof=1)) / f.size
              for P, f, g in drawn if f.size > 1)
    return float(np.clip(r_avg, RELEVANT, 1.0)), float(np.sqrt(var)) / G, int(round(G)), sampled


def timestep_weights(timesteps, num_timesteps: int) -> np.ndarray:
    """(S,) how many of the ``num_timesteps`` timesteps each scored timestep stands for (see expand_counts)."""
    S = len(timesteps)
    return np.bincount(expand_counts(np.arange(S), timesteps, num_timesteps), minlength=S)[:S]


def tied_segment_rows(positive: np.ndarray, timesteps, num_timesteps: int, dilation: int) -> list[np.ndarray]:
    """For each longest segment, when more than one is longest: the scored row of each of its timesteps
    (their counts sum to the segment's share of s_t, which breaks the tie); else an empty list.

    Args:
        positive: (S,) bool positivity of the scored timesteps.
    """
    full = expand_counts(np.asarray(positive, dtype=np.int64), timesteps, num_timesteps) > 0
    segments = runs(dilate(full, dilation))
    longest = max((b - a for a, b in segments), default=0)
    tied = [(a, b) for a, b in segments if b - a == longest]
    if len(tied) < 2:
        return []
    row_of = expand_counts(np.arange(len(timesteps)), timesteps, num_timesteps)
    return [row_of[a:b + 1] for a, b in tied]


def expand_counts(counts: np.ndarray, timesteps: np.ndarray, num_timesteps: int) -> np.ndarray:
    """Counts at sampled ``timesteps`` -> (T,) counts, each timestep taking its nearest sample."""
    counts = np.asarray(counts, dtype=np.int64)
    timesteps = np.asarray(timesteps, dtype=np.int64)
    if len(timesteps) == num_timesteps:
        return counts
    if len(timesteps) == 0:
        return np.zeros(num_timesteps, dtype=np.int64)
    t = np.arange(num_timesteps)
    idx = np.clip(np.searchsorted(timesteps, t), 0, len(timesteps) - 1)
    left = np.clip(idx - 1, 0, len(timesteps) - 1)
    nearer_left = np.abs(t - timesteps[left]) <= np.abs(timesteps[idx] - t)
    return counts[np.where(nearer_left, left, idx)]


def runs(binary: np.ndarray) -> list[tuple[int, int]]:
    """Inclusive (start, end) of every run of True, in order."""
    labels, n = ndimage.label(np.asarray(binary, dtype=bool))
    if n == 0:
        return []
    objs = ndimage.find_objects(labels)
    return [(int(s[0].start), int(s[0].stop - 1)) for s in objs]


def dilate(positive: np.ndarray, radius: int) -> np.ndarray:
    """Binary dilation of a 1-D array by ``radius`` timesteps on each side (scipy.ndimage)."""
    positive = np.asarray(positive, dtype=bool)
    if radius <= 0 or positive.size == 0:
        return positive.copy()
    return ndimage.binary_dilation(positive, structure=np.ones(2 * radius + 1, dtype=bool))


def pick_segment(segments: Sequence[tuple[int, int]], scores: np.ndarray) -> Optional[tuple[int, int]]:
    """The longest run; ties go to the larger total s_t, then to the earlier run."""
    if not segments:
        return None
    return max(segments, key=lambda ab: (ab[1] - ab[0], float(np.sum(scores[ab[0]:ab[1] + 1])), -ab[0]))


def localize_counts(counts, timesteps, num_timesteps: int, *, dilation: int = 1, r_avg: float = 0.0,
                    num_relevant: int = 0, query: str = "", num_gaussians: Optional[int] = None) -> TemporalResult:
    """s_t, positives, segments, the longest segment and its peak from per-timestep counts.

    Args:
        counts: (S,) |Rel_t| at the scored timesteps.
        timesteps: (S,) which timesteps were scored (sorted).
        num_timesteps: T of the scene.
        dilation: radius (timesteps) of the binary dilation applied before extracting runs.
    """
    T = int(num_timesteps)
    full = expand_counts(counts, timesteps, T)
    total = int(full.sum())
    scores = full / total if total > 0 else np.zeros(T, dtype=np.float64)
    message = ""
    if total == 0:
        positive = np.zeros(T, dtype=bool)
        if num_gaussians == 0:
            message = "the scene has no Gaussians; nothing can be localized"
        elif T == 0:
            message = "the scene has no timesteps"
        else:
            message = (f"no Gaussian is more relevant to {query!r} than the canonical phrases "
                       "(every relevancy <= 0.5): not found")
    elif np.all(full == full[0]):
        positive = np.ones(T, dtype=bool)
        message = ("every timestep has the same share of relevant Gaussians (s_t = 1/T), "
                   "so the whole sequence is returned")
    else:
        positive = full * T > total
    segments = runs(dilate(positive, dilation))
    segment = pick_segment(segments, scores)
    peak = None if segment is None else (segment[0] + segment[1]) // 2
    return TemporalResult(scores=scores.astype(np.float64), positive=positive, segments=segments,
                          segment=segment, peak=peak, found=segment is not None, message=message,
                          r_avg=float(r_avg), num_relevant=int(num_relevant),
                          timesteps=np.asarray(timesteps, dtype=np.int64))


def localize_relevancy(scores, *, timesteps=None, num_timesteps: Optional[int] = None, dilation: int = 1,
                       query: str = "") -> TemporalResult:
    """Temporal localization straight from a (S,N) relevancy array (reference path, used by tests)."""
    R = torch.as_tensor(np.asarray(scores) if not isinstance(scores, torch.Tensor) else scores)
    S = R.shape[0]
    timesteps = np.arange(S) if timesteps is None else np.asarray(timesteps)
    T = S if num_timesteps is None else num_timesteps
    counts, r_avg, n_rel = counts_from_relevancy(R)
    return localize_counts(counts, timesteps, T, dilation=dilation, r_avg=r_avg, num_relevant=n_rel,
                           query=query, num_gaussians=int(R.shape[1]) if R.ndim > 1 else None)


def sampled_timesteps(num_timesteps: int, stride: int) -> np.ndarray:
    """Every ``stride``-th timestep starting at 0: (S,) int64."""
    return np.arange(0, int(num_timesteps), max(1, int(stride)), dtype=np.int64)


def sparkline(scores: Sequence[float], width: int = 80) -> str:
    """Unicode sparkline of s_t (resampled to at most ``width`` characters by max-pooling).

    NaN and -inf draw as the lowest block, +inf as the highest finite score (or the top block).
    """
    blocks = " ▁▂▃▄▅▆▇█"
    s = np.asarray(scores, dtype=np.float64).reshape(-1)
    if s.size == 0:
        return ""
    finite = s[np.isfinite(s)]
    s = np.nan_to_num(s, nan=0.0, neginf=0.0, posinf=max(float(finite.max()), 0.0) if finite.size and
                      finite.max() > 0 else 1.0)
    if s.size > width:
        edges = np.linspace(0, s.size, width + 1).astype(int)
        s = np.array([s[a:max(b, a + 1)].max() for a, b in zip(edges[:-1], edges[1:])])
    top = s.max()
    if top <= 0:
        return blocks[0] * s.size
    return "".join(blocks[int(round(v / top * (len(blocks) - 1)))] for v in s)
