"""Spatio-temporal grounding metrics of the 4-LEGS paper (§4.1), vectorized numpy in float64.

All metrics are fractions in [0, 1] (the paper prints percentages: use :func:`format_percent`).

Conventions (each one chosen so that no NaN can come out):

* **Frame sets** are boolean arrays over the T timesteps of a video (one view): ``pred_frames`` the
  frames the method marks positive, ``gt_frames`` the annotated ones. ``S_u = pred | gt`` and
  ``S_i = pred & gt``.
* **Boxes** are ``(x0, y0, x1, y1)`` in continuous pixel coordinates with ``x1, y1`` exclusive: a box
  covering pixel columns ``a..b`` has ``x0 = a, x1 = b + 1`` (see :func:`mask_to_box`). A missing box is
  ``None`` or a row of NaN and has IoU 0 with anything.
* **AP** is the step-wise (scikit-learn style) average precision ``AP = Σ_k (R_k − R_{k−1}) P_k`` over
  the distinct score values taken as thresholds in decreasing order (``score >= threshold`` is positive).
  Tied scores enter together: a threshold never splits a tie, so AP does not depend on the order of
  tied items. No positive label → AP = ``zero_division`` (default 0, as scikit-learn). All labels
  positive → AP = 1.
* **Empty denominators**: an empty union (neither prediction nor ground truth has a frame), no
  predicted frame (tPrec) or no ground-truth frame (tRec) give ``zero_division`` (default 0.0); a box
  pair with empty union has IoU ``zero_division``.
* **Over views**: :func:`mean_std` uses the population standard deviation (``ddof=0``) unless told.
"""
from __future__ import annotations

from typing import Any, Mapping, Optional, Sequence

import numpy as np

from fourlegs_engine.errors import InputError

METRIC_NAMES = ("vAP", "vIoU", "tIoU", "tRec", "tPrec", "tAP")


# ---------------------------------------------------------------------------------------------- boxes
def box_iou(pred: Any, gt: Any, *, zero_division: float = 0.0) -> np.ndarray:
    """IoU of boxes, broadcasting over leading dimensions.

    Args:
        pred, gt: (..., 4) boxes ``(x0, y0, x1, y1)``, x1/y1 exclusive; NaN rows mean "no box".
    Returns:
        (...) float64 IoU in [0, 1]; 0 where either box is missing, ``zero_division`` where the
        union has zero area.
    """
    a = np.asarray(pred, dtype=np.float64)
    b = np.asarray(gt, dtype=np.float64)
    if a.shape[-1:] != (4,) or b.shape[-1:] != (4,):
        raise InputError(f"boxes need 4 coordinates, got shapes {a.shape} and {b.shape}", field="boxes")
    if np.isinf(a).any() or np.isinf(b).any():
        raise InputError("box coordinates contain Inf", field="boxes")
    missing = np.isnan(a).any(-1) | np.isnan(b).any(-1)
    a = np.where(np.isnan(a), 0.0, a)
    b = np.where(np.isnan(b), 0.0, b)
    area_a = np.clip(a[..., 2] - a[..., 0], 0, None) * np.clip(a[..., 3] - a[..., 1], 0, None)
    area_b = np.clip(b[..., 2] - b[..., 0], 0, None) * np.clip(b[..., 3] - b[..., 1], 0, None)
    iw = np.clip(np.minimum(a[..., 2], b[..., 2]) - np.maximum(a[..., 0], b[..., 0]), 0, None)
    ih = np.clip(np.minimum(a[..., 3], b[..., 3]) - np.maximum(a[..., 1], b[..., 1]), 0, None)
    inter = iw * ih
    union = area_a + area_b - inter
    iou = np.where(union > 0, inter / np.where(union > 0, union, 1.0), zero_division)
    return np.where(missing, 0.0, iou)


def mask_to_box(mask: Any) -> Optional[np.ndarray]:
    """Tight box ``(x0, y0, x1, y1)`` (x1, y1 exclusive) of a (H,W) boolean mask; None if empty."""
    m = np.asarray(mask, dtype=bool)
    if m.ndim != 2:
        raise InputError(f"has shape {m.shape}, expected (H,W)", field="mask")
    cols = np.flatnonzero(m.any(axis=0))
    rows = np.flatnonzero(m.any(axis=1))
    if cols.size == 0:
        return None
    return np.array([cols[0], rows[0], cols[-1] + 1, rows[-1] + 1], dtype=np.float64)


def _boxes(boxes: Any, T: int, name: str) -> np.ndarray:
    """Sequence of T boxes (None allowed) -> (T,4) float64 with NaN rows for missing boxes."""
    if isinstance(boxes, np.ndarray) and boxes.dtype != object:
        arr = boxes.astype(np.float64)
    else:
        arr = np.stack([np.full(4, np.nan) if b is None else np.asarray(b, dtype=np.float64).reshape(4)
                        for b in boxes]) if len(boxes) else np.zeros((0, 4))
    if arr.shape != (T, 4):
        raise InputError(f"has shape {arr.shape}, expected (T={T}, 4)", field=name)
    return arr


# ------------------------------------------------------------------------------------------------- AP
def average_precision(scores: Any, labels: Any, *, zero_division: float = 0.0) -> float:
    """Step-wise average precision of ``scores`` ranking ``labels`` (any matching shapes).

    ``AP = Σ_k (R_k − R_{k−1}) P_k`` with one threshold per distinct score (ties enter together).

    Args:
        scores: (...) finite real scores, higher = more likely positive (e.g. a relevancy map (H,W)).
        labels: (...) booleans of the same shape (e.g. the ground-truth mask).
    Returns:
        AP in [0, 1] (float); ``zero_division`` when there is no positive label.
    """
    s = np.asarray(scores, dtype=np.float64).reshape(-1)
    y = np.asarray(labels)
    if y.shape != np.shape(scores):
        raise InputError(f"labels have shape {y.shape}, scores {np.shape(scores)}", field="labels")
    y = y.reshape(-1).astype(bool)
    if not np.isfinite(s).all():
        raise InputError("contains NaN or Inf", field="scores")
    positives = int(y.sum())
    if positives == 0:
        return float(zero_division)
    order = np.argsort(-s, kind="stable")
    s_sorted = s[order]
    tp = np.cumsum(y[order], dtype=np.int64)
    ends = np.append(np.flatnonzero(np.diff(s_sorted)), s.size - 1)  # last item of each tie group
    precision = tp[ends] / (ends + 1.0)
    new_positives = np.diff(tp[ends], prepend=0)  # recall step of each tie group, times `positives`
    # One division at the end keeps a perfect ranking at exactly 1.0 (summing 1/P steps drifts).
    return float(np.sum(new_positives * precision) / positives)


# -------------------------------------------------------------------------------------------- frames
def _frames(frames: Any, name: str, T: Optional[int] = None) -> np.ndarray:
    arr = np.asarray(frames)
    if arr.ndim != 1 or (T is not None and arr.shape[0] != T):
        raise InputError(f"has shape {arr.shape}, expected (T{'=' + str(T) if T is not None else ''},)", field=name)
    if arr.dtype != bool:
        if not np.isin(arr, (0, 1)).all():
            raise InputError("must be a boolean array over timesteps", field=name)
        arr = arr.astype(bool)
    return arr


def frames_from_segments(segments: Sequence[Sequence[int]], num_timesteps: int) -> np.ndarray:
    """(T,) bool from inclusive ``[(start, end), ...]`` segments (clipped to 0..T-1)."""
    out = np.zeros(num_timesteps, dtype=bool)
    for start, end in segments:
        out[max(int(start), 0):min(int(end), num_timesteps - 1) + 1] = True
    return out


def _ratio(num: float, den: float, zero_division: float) -> float:
    return float(num / den) if den > 0 else float(zero_division)


# ---------------------------------------------------------------------------------- spatio-temporal
def viou(pred_frames: Any, gt_frames: Any, pred_boxes: Any, gt_boxes: Any, *,
         zero_division: float = 0.0) -> float:
    """vIoU = (1/|S_u|) Σ_{t∈S_i} IoU(pred_box_t, gt_box_t).

    Args:
        pred_frames, gt_frames: (T,) bool.
        pred_boxes, gt_boxes: (T,4) arrays or length-T sequences of boxes / None; only frames in S_i
            are used, other rows may hold anything (NaN, None).
    """
    p = _frames(pred_frames, "pred_frames")
    g = _frames(gt_frames, "gt_frames", p.shape[0])
    union, inter = p | g, p & g
    if not union.any():
        return float(zero_division)
    T = p.shape[0]
    pb, gb = _boxes(pred_boxes, T, "pred_boxes"), _boxes(gt_boxes, T, "gt_boxes")
    return float(box_iou(pb[inter], gb[inter]).sum() / union.sum())


def vap(pred_frames: Any, gt_frames: Any, relevancy_maps: Any, gt_masks: Any, *,
        zero_division: float = 0.0) -> float:
    """vAP = (1/|S_u|) Σ_{t∈S_i} AP(relevancy_map_t, gt_mask_t) (pixel-level AP per frame).

    Args:
        pred_frames, gt_frames: (T,) bool.
        relevancy_maps: indexable by t -> (H,W) scores (only frames in S_i are read, so a lazy
            sequence or a dict {t: map} works).
        gt_masks: indexable by t -> (H,W) bool.
    A frame in S_i whose mask is empty contributes AP = ``zero_division``.
    """
    p = _frames(pred_frames, "pred_frames")
    g = _frames(gt_frames, "gt_frames", p.shape[0])
    union, inter = p | g, p & g
    if not union.any():
        return float(zero_division)
    total = sum(average_precision(relevancy_maps[int(t)], gt_masks[int(t)], zero_division=zero_division)
                for t in np.flatnonzero(inter))
    return float(total / union.sum())


def temporal_metrics(pred_frames: Any, gt_frames: Any, scores: Any = None, *,
                     zero_division: float = 0.0) -> dict[str, float]:
    """tIoU = |S_i|/|S_u|, tRec = |S_i|/|gt|, tPrec = |S_i|/|pred|, tAP = AP(scores, gt_frames).

    Args:
        pred_frames, gt_frames: (T,) bool.
        scores: (T,) per-frame scores s_t (the paper's temporal relevance); None -> the binary
            prediction is used as the score.
    """
    p = _frames(pred_frames, "pred_frames")
    g = _frames(gt_frames, "gt_frames", p.shape[0])
    s = p.astype(np.float64) if scores is None else np.asarray(scores, dtype=np.float64)
    if s.shape != p.shape:
        raise InputError(f"has shape {s.shape}, expected {p.shape}", field="scores")
    inter = float((p & g).sum())
    return {"tIoU": _ratio(inter, float((p | g).sum()), zero_division),
            "tRec": _ratio(inter, float(g.sum()), zero_division),
            "tPrec": _ratio(inter, float(p.sum()), zero_division),
            "tAP": average_precision(s, g, zero_division=zero_division)}


def grounding_metrics(pred_frames: Any, gt_frames: Any, *, scores: Any = None, relevancy_maps: Any = None,
                      gt_masks: Any = None, pred_boxes: Any = None, gt_boxes: Any = None,
                      zero_division: float = 0.0) -> dict[str, float]:
    """All six metrics of one video (one view); vAP / vIoU only when their inputs are given."""
    out: dict[str, float] = {}
    if relevancy_maps is not None and gt_masks is not None:
        out["vAP"] = vap(pred_frames, gt_frames, relevancy_maps, gt_masks, zero_division=zero_division)
    if pred_boxes is not None and gt_boxes is not None:
        out["vIoU"] = viou(pred_frames, gt_frames, pred_boxes, gt_boxes, zero_division=zero_division)
    out.update(temporal_metrics(pred_frames, gt_frames, scores, zero_division=zero_division))
    return out


# ------------------------------------------------------------------------------------------ over views
def mean_std(values: Any, *, ddof: int = 0) -> tuple[float, float]:
    """Mean and standard deviation (population, ``ddof=0``, by default) of per-view values."""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if v.size == 0:
        raise InputError("no values to average", field="values")
    if not np.isfinite(v).all():
        raise InputError("contains NaN or Inf", field="values")
    std = float(np.std(v, ddof=ddof)) if v.size > ddof else 0.0
    return float(np.mean(v)), std


def aggregate_views(per_view: Sequence[Mapping[str, float]], *, ddof: int = 0) -> dict[str, tuple[float, float]]:
    """{metric: (mean, std)} over views, for every metric present in all views."""
    if not per_view:
        raise InputError("no views to aggregate", field="per_view")
    names = [k for k in per_view[0] if all(k in v for v in per_view)]
    return {k: mean_std([v[k] for v in per_view], ddof=ddof) for k in names}


def format_percent(mean: float, std: Optional[float] = None, digits: int = 1) -> str:
    """``0.587, 0.006 -> '58.7 ± 0.6'`` (the paper's style)."""
    text = f"{100 * mean:.{digits}f}"
    return text if std is None else f"{text} ± {100 * std:.{digits}f}"
