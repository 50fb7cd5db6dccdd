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

from typing import Optional, Sequence

import numpy as np
import torch
from scipy import ndimage

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
                    num_relevant: int = 0, query: str = "", num_gaussians: Optional[int] = None,
                    undecided: Optional[np.ndarray] = None) -> TemporalResult:
    """s_t, positives, segments, the longest segment and its peak from per-timestep counts.

    Args:
        counts: (S,) |Rel_t| at the scored timesteps.
        timesteps: (S,) which timesteps were scored (sorted).
        num_timesteps: T of the scene.
        dilation: radius (timesteps) of the binary dilation applied before extracting runs.
        undecided: (S,) bool, the scored timesteps whose decision the counts leave open (see
            :class:`TemporalResult`).
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
                          timesteps=np.asarray(timesteps, dtype=np.int64),
                          undecided=[] if undecided is None else
                          [int(t) for t in np.asarray(timesteps, dtype=np.int64)[np.asarray(undecided, dtype=bool)]])


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
