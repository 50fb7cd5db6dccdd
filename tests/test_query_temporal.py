"""Temporal localization: the definition (float64 oracle), segments, and the edge cases."""
from __future__ import annotations

import numpy as np
from hypothesis import given, strategies as st
from hypothesis.extra.numpy import arrays

from fourlegs_engine.query.temporal import (counts_from_code_histogram, counts_from_relevancy, dilate,
                                            expand_counts, localize_counts, localize_relevancy, runs,
                                            sparkline)


def oracle_scores(R: np.ndarray) -> np.ndarray:
    """Supplementary A.2 written literally with Python sets/loops in float64."""
    All = [(t, g, float(R[t, g])) for t in range(R.shape[0]) for g in range(R.shape[1])]
    Rel = [r for _, _, r in All if r > 0.5]
    if not Rel:
        return np.zeros(R.shape[0])
    r_avg = sum(Rel) / len(Rel)
    counts = np.array([sum(1 for g in range(R.shape[1]) if R[t, g] > r_avg) for t in range(R.shape[0])], float)
    return counts / counts.sum() if counts.sum() else None  # all relevant scores tie: undefined


def test_matches_the_literal_definition():
    rng = np.random.default_rng(1)
    R = rng.uniform(0, 1, size=(9, 40)) ** 2
    R[3:6, :25] = rng.uniform(0.8, 1.0, size=(3, 25))
    res = localize_relevancy(R, dilation=0)
    np.testing.assert_allclose(res.scores, oracle_scores(R), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(res.positive, oracle_scores(R) > 1 / 9)
    assert res.found and res.segment == (3, 5) and res.peak == 4
    assert abs(res.scores.sum() - 1) < 1e-12


def test_dilation_merges_gaps_and_longest_segment_wins():
    positive = np.array([0, 1, 0, 1, 1, 0, 0, 0, 1, 0, 0], bool)
    assert runs(positive) == [(1, 1), (3, 4), (8, 8)]
    assert runs(dilate(positive, 1)) == [(0, 5), (7, 9)]
    counts = np.where(positive, 10, 1)
    res = localize_counts(counts, np.arange(11), 11, dilation=1)
    assert res.segments == [(0, 5), (7, 9)] and res.segment == (0, 5) and res.peak == 2


def test_one_frame_segment():
    counts = np.ones(7, np.int64)
    counts[4] = 20
    res = localize_counts(counts, np.arange(7), 7, dilation=0)
    assert res.segments == [(4, 4)] and res.segment == (4, 4) and res.peak == 4


def test_segments_touching_both_ends():
    counts = np.array([9, 9, 1, 1, 1, 1, 9, 9, 9])
    res = localize_counts(counts, np.arange(9), 9, dilation=0)
    assert res.segments == [(0, 1), (6, 8)] and res.segment == (6, 8) and res.peak == 7
    res = localize_counts(counts, np.arange(9), 9, dilation=3)  # dilation is clipped at the ends
    assert res.segments == [(0, 8)] and res.peak == 4


def test_undecided_scored_rows_are_reported_as_their_timesteps():
    counts = np.array([9, 5, 1, 1, 9])
    res = localize_counts(counts, np.array([0, 3, 6, 9, 12]), 13, dilation=0,
                          undecided=np.array([False, True, False, False, True]))
    assert res.undecided == [3, 12] and res.to_dict()["undecided"] == [3, 12]
    assert localize_counts(counts, np.arange(5), 5).undecided == []


def test_no_relevant_gaussian_is_a_normal_answer():
    R = np.full((5, 30), 0.5)  # exactly 0.5 is not > 0.5
    res = localize_relevancy(R, query="a dragon")
    assert not res.found and res.segment is None and res.peak is None and res.segments == []
    assert np.all(res.scores == 0) and "not found" in res.message and "dragon" in res.message
    assert res.to_dict()["segment"] is None


def test_every_gaussian_relevant_with_equal_scores():
    R = np.full((6, 10), 0.9)
    res = localize_relevancy(R)
    assert np.all(np.isfinite(res.scores)) and np.allclose(res.scores, 1 / 6)
    assert res.found and res.segment == (0, 5) and res.positive.all() and "whole sequence" in res.message


def test_every_gaussian_relevant_with_varying_scores():
    R = np.full((6, 10), 0.6)
    R[2, :7] = 0.99
    res = localize_relevancy(R, dilation=0)
    np.testing.assert_allclose(res.scores, oracle_scores(R))
    assert res.segment == (2, 2)


def test_single_timestep():
    res = localize_relevancy(np.array([[0.2, 0.9, 0.7]]))
    assert res.found and res.segment == (0, 0) and res.peak == 0 and res.scores.tolist() == [1.0]
    res = localize_relevancy(np.array([[0.2, 0.3]]))
    assert not res.found and res.scores.tolist() == [0.0]


def test_no_gaussians():
    res = localize_relevancy(np.zeros((4, 0)))
    assert not res.found and res.scores.shape == (4,) and np.all(res.scores == 0)
    assert "no Gaussians" in res.message


def test_histogram_counts_equal_per_gaussian_counts():
    rng = np.random.default_rng(3)
    K, T, N = 12, 7, 50
    code_r = rng.uniform(0, 1, K)
    codes = rng.integers(0, K, size=(T, N))
    hist = np.stack([np.bincount(c, minlength=K) for c in codes])
    c1, a1, n1 = counts_from_code_histogram(code_r, hist)
    c2, a2, n2 = counts_from_relevancy(code_r[codes])
    np.testing.assert_array_equal(c1, c2)
    assert n1 == n2 and abs(a1 - a2) < 1e-12


def test_stride_holds_the_nearest_sample():
    full = expand_counts(np.array([5, 7, 9]), np.array([0, 4, 8]), 10)
    np.testing.assert_array_equal(full, [5, 5, 5, 7, 7, 7, 7, 9, 9, 9])
    R = np.full((3, 4), 0.2)
    R[1, :3] = 0.9
    res = localize_relevancy(R, timesteps=[0, 4, 8], num_timesteps=10, dilation=0)
    assert res.segment == (3, 6) and len(res.scores) == 10


def test_sparkline():
    assert sparkline([0, 0.5, 1.0]) == " ▄█"
    assert len(sparkline(np.random.default_rng(0).uniform(size=500), width=60)) == 60
    assert sparkline([0, 0]) == "  "


@given(arrays(np.float64, st.tuples(st.integers(1, 12), st.integers(0, 20)), elements=st.floats(0, 1)),
       st.integers(0, 3))
def test_property_scores_are_a_distribution_or_zero(R, dilation):
    res = localize_relevancy(R, dilation=dilation)
    assert np.all(np.isfinite(res.scores)) and np.all(res.scores >= 0)
    assert abs(res.scores.sum() - 1) < 1e-9 or res.scores.sum() == 0
    assert res.found == (res.segment is not None) == (res.peak is not None)
    if res.found:
        a, b = res.segment
        assert 0 <= a <= res.peak <= b < R.shape[0]
        assert all(0 <= s <= e < R.shape[0] for s, e in res.segments)
        expect = oracle_scores(R)
        if not res.message and expect is not None:
            np.testing.assert_allclose(res.scores, expect, atol=1e-12)
