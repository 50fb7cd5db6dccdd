"""Relevancy: the stable form against the literal float64 formula, and its numerical edges."""
from __future__ import annotations

import numpy as np
import torch
from hypothesis import given, strategies as st
from hypothesis.extra.numpy import arrays

from fourlegs_engine.query.lerf import relevancy, relevancy_margin, relevancy_reference

rng = np.random.default_rng(0)


def _unit(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def test_matches_float64_reference_on_random_features():
    feats = rng.normal(size=(200, 32))
    q = rng.normal(size=32)
    canon = rng.normal(size=(4, 32))
    neg = rng.normal(size=(2, 32))
    for negatives in (None, neg):
        got = relevancy(torch.tensor(feats, dtype=torch.float64), q, canon, negatives).numpy()
        ref = relevancy_reference(feats, q, canon, negatives)
        np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-14)
        got32 = relevancy(feats.astype(np.float32), q, canon, negatives).numpy()
        np.testing.assert_allclose(got32, ref, atol=2e-6)


def test_min_over_canonical_is_the_worst_phrase():
    q = np.eye(3)[0]
    canon = np.stack([np.eye(3)[1], _unit(np.array([1.0, 0.5, 0.0]))])
    phi = np.array([[1.0, 0.0, 0.0]])
    # margins: 1 - 0 = 1 and 1 - 1/sqrt(1.25); the second is smaller, so it decides
    expect = 1 / (1 + np.exp(-10 * (1 - 1 / np.sqrt(1.25))))
    assert abs(float(relevancy(phi, q, canon)[0]) - expect) < 1e-6


def test_huge_and_tiny_logits_stay_finite_and_saturate():
    q = np.eye(4)[0]
    canon = np.eye(4)[1:3]
    phi = np.stack([np.eye(4)[0], np.eye(4)[1], np.eye(4)[3]]) * 1e30  # huge norms normalize away
    for scale in (1e6, 1e30, 1e-30):
        r = relevancy(phi, q, canon, scale=scale).numpy()
        assert np.all(np.isfinite(r)) and np.all((r >= 0) & (r <= 1))
        if scale > 1:
            np.testing.assert_allclose(r, [1.0, 0.0, 0.5], atol=1e-6)
        else:
            np.testing.assert_allclose(r, 0.5, atol=1e-6)
    # the literal formula overflows here; the stable one does not
    with np.errstate(over="ignore", invalid="ignore"):
        assert not np.all(np.isfinite(relevancy_reference(phi, q, canon, scale=1e6)))
    # tiny features are still directions; below the 1e-12 norm guard they count as zero (R = 0.5)
    tiny = np.array([[1e-9, 0, 0, 0], [1e-30, 0, 0, 0]], dtype=np.float64)
    np.testing.assert_allclose(relevancy(torch.tensor(tiny), q, canon).numpy(),
                               [1 / (1 + np.exp(-10)), 0.5], atol=1e-9)


def test_zero_norm_features_score_one_half():
    r = relevancy(np.zeros((5, 8)), rng.normal(size=8), rng.normal(size=(4, 8))).numpy()
    np.testing.assert_array_equal(r, 0.5)


def test_nan_features_do_not_escape():
    feats = np.full((3, 8), np.nan)
    feats[1] = np.inf
    r = relevancy(feats, rng.normal(size=8), rng.normal(size=(4, 8))).numpy()
    assert np.all(np.isfinite(r))


def test_query_equal_to_canonical_phrase_is_never_relevant():
    canon = _unit(rng.normal(size=(4, 16)))
    feats = rng.normal(size=(500, 16))
    r = relevancy(feats, canon[2], canon).numpy()
    assert r.max() <= 0.5 + 1e-7
    assert not np.any(r > 0.5)


def test_negative_phrases_only_lower_relevancy():
    feats, q = rng.normal(size=(300, 16)), rng.normal(size=16)
    canon, neg = rng.normal(size=(4, 16)), rng.normal(size=(3, 16))
    plain = relevancy(feats, q, canon).numpy()
    with_neg = relevancy(feats, q, canon, neg).numpy()
    assert np.all(with_neg <= plain + 1e-7)
    assert np.any(with_neg < plain - 1e-3)


@given(arrays(np.float64, (6, 5), elements=st.floats(-1e6, 1e6, allow_nan=False)),
       arrays(np.float64, (5,), elements=st.floats(-1e3, 1e3, allow_nan=False)),
       st.floats(1e-3, 1e8))
def test_property_bounded_finite_and_monotone_in_margin(feats, q, scale):
    canon = np.eye(5)[:2]
    r = relevancy(torch.tensor(feats), q, canon, scale=scale).numpy()
    m = relevancy_margin(torch.tensor(feats), q, canon, scale=scale).numpy()
    assert np.all(np.isfinite(r)) and np.all((r >= 0) & (r <= 1))
    order = np.argsort(m, kind="stable")
    assert np.all(np.diff(r[order]) >= -1e-12)


def test_unit_feature_fast_path_equals_general_form():
    from fourlegs_engine.query.lerf import l2_normalize, reference_set, relevancy_of_unit_features
    feats = l2_normalize(torch.tensor(rng.normal(size=(100, 12))))
    q = l2_normalize(torch.tensor(rng.normal(size=12)))
    canon, neg = torch.tensor(rng.normal(size=(4, 12))), torch.tensor(rng.normal(size=(2, 12)))
    fast = relevancy_of_unit_features(feats, q, reference_set(canon, neg))
    np.testing.assert_allclose(fast.numpy(), relevancy(feats, q, canon, neg).numpy(), atol=1e-12)


def test_many_queries_in_one_product_equal_one_at_a_time():
    from fourlegs_engine.query.lerf import l2_normalize, reference_set, relevancy_many
    feats = torch.tensor(rng.normal(size=(50, 12)))
    feats[0] = 0
    qs = l2_normalize(torch.tensor(rng.normal(size=(3, 12))))
    canon = torch.tensor(rng.normal(size=(4, 12)))
    many = relevancy_many(feats, qs, reference_set(canon)).numpy()
    for j in range(3):
        np.testing.assert_allclose(many[:, j], relevancy(feats.float(), qs[j], canon).numpy(), atol=1e-6)
    assert many[0].tolist() == [0.5, 0.5, 0.5]
