"""Grounding metrics: hand-computed cases, a float64 brute-force AP oracle, and edge cases."""
from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from fourlegs_engine.errors import InputError
from fourlegs_bench.metrics import (METRIC_NAMES, aggregate_views, average_precision, box_iou, format_percent,
                                          frames_from_segments, grounding_metrics, mask_to_box, mean_std,
                                          temporal_metrics, vap, viou)


def brute_force_ap(scores, labels, zero_division=0.0):
    """AP by definition: loop over every distinct score as a threshold (score >= tau is positive),
    from the highest down; AP = sum over thresholds of (recall gain) x (precision there)."""
    s = [float(v) for v in np.ravel(scores)]
    y = [bool(v) for v in np.ravel(labels)]
    npos = sum(y)
    if npos == 0:
        return zero_division
    ap, prev_recall = 0.0, 0.0
    for tau in sorted(set(s), reverse=True):
        chosen = [yi for si, yi in zip(s, y) if si >= tau]
        tp = sum(chosen)
        recall, precision = tp / npos, tp / len(chosen)
        ap += (recall - prev_recall) * precision
        prev_recall = recall
    return ap


# ------------------------------------------------------------------------------------------------ AP
def test_ap_hand_cases():
    assert average_precision([0.9, 0.8, 0.7, 0.6], [1, 0, 1, 0]) == pytest.approx(0.5 * 1 + 0.5 * 2 / 3)
    assert average_precision([0.9, 0.8, 0.7, 0.6], [0, 1, 0, 1]) == pytest.approx(0.5 * 1 / 2 + 0.5 * 2 / 4)
    assert average_precision([0.1, 0.2, 0.3], [0, 0, 1]) == 1.0
    # ties enter together: one threshold, precision 2/4 at recall 1
    assert average_precision([0.5, 0.5, 0.5, 0.5], [1, 0, 1, 0]) == 0.5
    # a tie across a positive and a negative at the top: precision 1/2 at recall 1/2, then 2/3 at 1
    assert average_precision([0.9, 0.9, 0.1], [1, 0, 1]) == pytest.approx(0.5 * 0.5 + 0.5 * 2 / 3)
    # (H,W) maps work the same as flat arrays
    m = np.array([[0.9, 0.1], [0.8, 0.2]])
    assert average_precision(m, m > 0.5) == 1.0


def test_ap_edge_cases():
    assert average_precision([0.3, 0.1, 0.7], [1, 1, 1]) == 1.0            # all positive
    assert average_precision([0.3, 0.1, 0.7], [0, 0, 0]) == 0.0            # no positive: zero_division
    assert average_precision([0.3, 0.1, 0.7], [0, 0, 0], zero_division=1.0) == 1.0
    assert average_precision(np.zeros((0,)), np.zeros((0,), bool)) == 0.0  # empty
    assert average_precision(np.zeros((4, 4)), np.eye(4, dtype=bool)) == 0.25  # constant map = prevalence
    with pytest.raises(InputError, match="scores: contains NaN or Inf"):
        average_precision([0.1, np.nan], [1, 0])
    with pytest.raises(InputError, match="labels: labels have shape"):
        average_precision(np.zeros((2, 3)), np.zeros((3, 2), bool))


scores_with_ties = hnp.arrays(np.float64, st.integers(1, 60), elements=st.integers(-3, 3).map(float))
scores_float32 = hnp.arrays(np.float32, st.integers(1, 60),
                            elements=st.floats(-1e3, 1e3, width=32, allow_nan=False, allow_infinity=False))


@given(data=st.data(), tied=st.booleans())
def test_ap_matches_brute_force(data, tied):
    scores = data.draw(scores_with_ties if tied else scores_float32)
    labels = data.draw(hnp.arrays(np.bool_, scores.shape))
    assert average_precision(scores, labels) == pytest.approx(brute_force_ap(scores, labels), abs=1e-12)


@given(data=st.data())
def test_ap_invariances(data):
    scores = data.draw(scores_with_ties)
    labels = data.draw(hnp.arrays(np.bool_, scores.shape))
    ap = average_precision(scores, labels)
    assert 0.0 <= ap <= 1.0
    perm = data.draw(st.permutations(range(scores.size)))
    assert average_precision(scores[perm], labels[perm]) == pytest.approx(ap, abs=1e-12)  # tie order irrelevant
    assert average_precision(np.exp(scores) * 5 - 2, labels) == pytest.approx(ap, abs=1e-12)  # monotone map
    if labels.any() and not labels.all():
        perfect = labels.astype(float) + 0.01 * scores
        assert average_precision(perfect, labels) == 1.0


# --------------------------------------------------------------------------------------------- boxes
def test_box_iou_hand_cases():
    assert box_iou([0, 0, 2, 2], [1, 1, 3, 3]) == pytest.approx(1 / 7)
    assert box_iou([0, 0, 2, 2], [0, 0, 2, 2]) == 1.0
    assert box_iou([0, 0, 2, 2], [2, 0, 4, 2]) == 0.0                     # touching edges
    assert box_iou([0, 0, 4, 4], [1, 1, 2, 2]) == pytest.approx(1 / 16)   # containment
    assert box_iou([1, 1, 1, 1], [1, 1, 1, 1]) == 0.0                     # empty union: zero_division
    assert box_iou([1, 1, 1, 1], [1, 1, 1, 1], zero_division=1.0) == 1.0
    assert box_iou([np.nan] * 4, [0, 0, 1, 1]) == 0.0                     # missing box
    got = box_iou(np.array([[0, 0, 2, 2], [0, 0, 1, 1]]), np.array([0, 0, 2, 2]))  # broadcasting
    np.testing.assert_allclose(got, [1.0, 0.25])
    with pytest.raises(InputError, match="4 coordinates"):
        box_iou([0, 0, 1], [0, 0, 1, 1])


def _raster(box, size=12):
    m = np.zeros((size, size), bool)
    m[box[1]:box[3], box[0]:box[2]] = True
    return m


box_coords = st.tuples(st.integers(0, 12), st.integers(0, 12), st.integers(0, 12), st.integers(0, 12)).map(
    lambda b: (min(b[0], b[2]), min(b[1], b[3]), max(b[0], b[2]), max(b[1], b[3])))


@given(a=box_coords, b=box_coords)
def test_box_iou_equals_pixel_count_iou(a, b):
    ma, mb = _raster(a), _raster(b)
    union = (ma | mb).sum()
    expected = (ma & mb).sum() / union if union else 0.0
    assert box_iou(a, b) == pytest.approx(expected, abs=1e-12)
    assert box_iou(b, a) == pytest.approx(expected, abs=1e-12)
    if ma.any():
        np.testing.assert_array_equal(mask_to_box(ma), a)  # tight box, x1/y1 exclusive


def test_mask_to_box():
    m = np.zeros((5, 6), bool)
    m[1, 2] = m[3, 4] = True
    np.testing.assert_array_equal(mask_to_box(m), [2, 1, 5, 4])
    assert mask_to_box(np.zeros((3, 3), bool)) is None


# ---------------------------------------------------------------------------------- vIoU / vAP
def test_viou_hand_case():
    T = 5
    pred = frames_from_segments([(1, 3)], T)
    gt = frames_from_segments([(2, 4)], T)
    pred_boxes = [None, [0, 0, 9, 9], [0, 0, 2, 2], [0, 0, 2, 2], None]
    gt_boxes = np.full((T, 4), np.nan)
    gt_boxes[2] = gt_boxes[3] = [0, 0, 2, 2]
    gt_boxes[3] = [1, 1, 3, 3]
    gt_boxes[4] = [0, 0, 1, 1]
    # S_u = {1,2,3,4}, S_i = {2,3}: (1 + 1/7) / 4
    assert viou(pred, gt, pred_boxes, gt_boxes) == pytest.approx((1 + 1 / 7) / 4)
    pred_boxes[3] = None  # predicted frame without a box counts 0
    assert viou(pred, gt, pred_boxes, gt_boxes) == pytest.approx(1 / 4)


def test_vap_hand_case_reads_only_the_intersection():
    T = 6
    pred = frames_from_segments([(0, 2)], T)
    gt = frames_from_segments([(1, 3)], T)
    mask = np.array([[1, 0], [1, 0]], bool)
    maps = {1: np.array([[0.9, 0.1], [0.8, 0.2]]),       # AP 1
            2: np.array([[0.9, 0.95], [0.1, 0.2]])}       # ranks: neg, pos, neg, pos -> 1/2*1/2 + 1/2*2/4 = 0.5
    masks = {1: mask, 2: mask}
    assert vap(pred, gt, maps, masks) == pytest.approx((1.0 + 0.5) / 4)   # S_u = {0,1,2,3}
    # a frame in S_i whose mask is empty contributes zero_division (0)
    masks[2] = np.zeros((2, 2), bool)
    assert vap(pred, gt, maps, masks) == pytest.approx(1.0 / 4)


def test_spatio_temporal_edge_cases():
    T = 4
    none = np.zeros(T, bool)
    some = frames_from_segments([(1, 2)], T)
    boxes = np.zeros((T, 4))
    maps = np.zeros((T, 2, 2))
    for fn, args in ((viou, (boxes, boxes)), (vap, (maps, maps > 0))):
        assert fn(none, none, *args) == 0.0                      # empty union: zero_division
        assert fn(none, none, *args, zero_division=1.0) == 1.0
        assert fn(none, some, *args) == 0.0                      # no predicted frame
        assert fn(some, none, *args) == 0.0                      # no ground-truth frame
    with pytest.raises(InputError, match="gt_frames: has shape"):
        viou(some, np.zeros(T + 1, bool), boxes, boxes)
    with pytest.raises(InputError, match=r"pred_boxes: has shape \(3, 4\), expected \(T=4, 4\)"):
        viou(some, some, boxes[:3], boxes)


# ------------------------------------------------------------------------------------------ temporal
def test_temporal_hand_case():
    T = 6
    pred = frames_from_segments([(0, 2)], T)
    gt = frames_from_segments([(1, 4)], T)
    scores = np.array([0.3, 0.25, 0.2, 0.05, 0.15, 0.05])
    m = temporal_metrics(pred, gt, scores)
    assert m["tIoU"] == pytest.approx(2 / 5) and m["tRec"] == pytest.approx(2 / 4)
    assert m["tPrec"] == pytest.approx(2 / 3)
    # ranking: 0.3(-) 0.25(+) 0.2(+) 0.15(+) 0.05(+,-) tied
    expected = 0.25 * 1 / 2 + 0.25 * 2 / 3 + 0.25 * 3 / 4 + 0.25 * 4 / 6
    assert m["tAP"] == pytest.approx(expected)
    assert m["tAP"] == pytest.approx(brute_force_ap(scores, gt))


def test_temporal_edge_cases_are_defined():
    T = 5
    none, gt = np.zeros(T, bool), frames_from_segments([(1, 2)], T)
    m = temporal_metrics(none, gt)                                # no predicted frames
    assert m == {"tIoU": 0.0, "tRec": 0.0, "tPrec": 0.0, "tAP": pytest.approx(2 / 5)}
    m = temporal_metrics(none, none, np.arange(T))                # empty union
    assert m == {"tIoU": 0.0, "tRec": 0.0, "tPrec": 0.0, "tAP": 0.0}
    m = temporal_metrics(np.ones(T, bool), np.ones(T, bool))      # all positive
    assert m == {"tIoU": 1.0, "tRec": 1.0, "tPrec": 1.0, "tAP": 1.0}
    m = temporal_metrics([0, 1, 1, 0, 0], gt)                     # 0/1 integers accepted
    assert m["tIoU"] == 1.0
    with pytest.raises(InputError, match="pred_frames: must be a boolean array"):
        temporal_metrics([0, 2, 1, 0, 0], gt)
    with pytest.raises(InputError, match="scores: has shape"):
        temporal_metrics(gt, gt, np.zeros(3))


@given(pred=hnp.arrays(np.bool_, 12), gt=hnp.arrays(np.bool_, 12))
def test_temporal_matches_set_definitions(pred, gt):
    P = {t for t in range(12) if pred[t]}
    G = {t for t in range(12) if gt[t]}
    m = temporal_metrics(pred, gt)
    ratio = lambda a, b: len(a) / len(b) if b else 0.0  # noqa: E731
    assert m["tIoU"] == pytest.approx(ratio(P & G, P | G))
    assert m["tRec"] == pytest.approx(ratio(P & G, G))
    assert m["tPrec"] == pytest.approx(ratio(P & G, P))
    assert all(np.isfinite(v) and 0 <= v <= 1 for v in m.values())


def test_grounding_metrics_all_six():
    T = 4
    pred = gt = frames_from_segments([(1, 2)], T)
    masks = np.zeros((T, 3, 3), bool)
    masks[:, 1, 1] = True
    boxes = np.array([mask_to_box(m) for m in masks])
    out = grounding_metrics(pred, gt, scores=pred.astype(float), relevancy_maps=masks.astype(float),
                            gt_masks=masks, pred_boxes=boxes, gt_boxes=boxes)
    assert set(out) == set(METRIC_NAMES) and all(v == 1.0 for v in out.values())


# ----------------------------------------------------------------------------------------- over views
def test_mean_std_and_formatting():
    assert mean_std([0.5, 0.7]) == (pytest.approx(0.6), pytest.approx(0.1))
    assert mean_std([0.5, 0.7], ddof=1)[1] == pytest.approx(np.sqrt(0.02))
    assert mean_std([0.42]) == (0.42, 0.0)
    assert mean_std([0.42], ddof=1) == (0.42, 0.0)
    with pytest.raises(InputError, match="no values"):
        mean_std([])
    with pytest.raises(InputError, match="NaN"):
        mean_std([0.1, np.nan])
    agg = aggregate_views([{"vAP": 0.5, "tIoU": 1.0}, {"vAP": 0.7, "tIoU": 1.0, "extra": 3}])
    assert set(agg) == {"vAP", "tIoU"} and agg["vAP"] == (pytest.approx(0.6), pytest.approx(0.1))
    assert format_percent(0.587, 0.006) == "58.7 ± 0.6" and format_percent(0.6083) == "60.8"


def test_brute_force_oracle_itself_on_enumerated_cases():
    """The oracle agrees with the textbook formula on every labelling of 4 distinct scores."""
    scores = np.array([0.4, 0.3, 0.2, 0.1])
    for labels in itertools.product([0, 1], repeat=4):
        y = np.array(labels, bool)
        if not y.any():
            continue
        ranks = np.flatnonzero(y) + 1                      # 1-based ranks of positives
        textbook = np.mean([(i + 1) / r for i, r in enumerate(ranks)])
        assert brute_force_ap(scores, y) == pytest.approx(textbook)
        assert average_precision(scores, y) == pytest.approx(textbook)
