"""LERF relevancy of language features to a text query, in a numerically stable form.

The paper (eq. 4, following LERF) scores a decoded feature φ against a query embedding q and the
canonical phrase embeddings c::

    R(φ, q) = min_c exp(φ·q) / (exp(φ·q) + exp(φ·c))  =  min_c sigmoid(s (φ·q − φ·c))

with all vectors L2-normalized and the dot products scaled by s = 10 as in the public
implementations. Because the sigmoid is monotonic the minimum over c is the sigmoid of the smallest
margin, ``sigmoid(s min_c φ·(q − c))``; it is evaluated as ``exp(logsigmoid(·))`` (softplus form),
which never overflows however large the logits. Scene-specific negative phrases (the paper's suggested
fix for queries absent from a scene, §4.5) simply join the canonical set.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import InputError
from .options import RELEVANCY_SCALE

NORM_EPS = 1e-12


def as_tensor(x, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """numpy / list / tensor -> tensor of ``dtype`` (non-finite values become 0)."""
    t = torch.as_tensor(np.asarray(x) if not isinstance(x, torch.Tensor) else x)
    if not t.is_floating_point():
        t = t.to(dtype)
    t = t.to(dtype)
    return torch.nan_to_num(t, nan=0.0, posinf=0.0, neginf=0.0)


def l2_normalize(x: torch.Tensor, dim: int = -1) -> torch.Tensor:
    """Normalize along ``dim``; a zero vector stays zero (eps-guarded, no NaN)."""
    return x / x.norm(dim=dim, keepdim=True).clamp_min(NORM_EPS)


def reference_set(canon: torch.Tensor, negatives: Optional[torch.Tensor] = None) -> torch.Tensor:
    """(K,D) canonical embeddings plus optional (J,D) negatives -> (K+J, D), L2-normalized."""
    refs = canon if negatives is None or len(negatives) == 0 else torch.cat([canon, negatives.to(canon.dtype)], 0)
    if refs.ndim != 2 or refs.shape[0] == 0:
        raise InputError(f"needs at least one canonical phrase embedding, got shape {tuple(refs.shape)}",
                         field="canonical_phrases")
    return l2_normalize(refs)


def relevancy_margin(features, query, canon, negatives=None, *, scale: float = RELEVANCY_SCALE,
                     normalize_features: bool = True) -> torch.Tensor:
    """The logit of the relevancy: ``scale · (φ·q − max_c φ·c)``.

    Args:
        features: (M,D) language features φ (decoded latents or decoded rendered pixels).
        query: (D,) query embedding.
        canon: (K,D) canonical phrase embeddings.
        negatives: (J,D) extra negative phrase embeddings, or None.
    Returns:
        (M,) margins in the features' float dtype (float32 unless float64 is passed).
    """
    feats = as_tensor(features, torch.float64 if _is_f64(features) else torch.float32)
    if feats.ndim != 2:
        raise InputError(f"has shape {tuple(feats.shape)}, expected (M,D)", field="features")
    dtype = feats.dtype
    q = l2_normalize(as_tensor(query, dtype).reshape(-1))
    if q.shape[0] != feats.shape[1]:
        raise InputError(f"query has dimension {q.shape[0]}, features have {feats.shape[1]}", field="query")
    refs = reference_set(as_tensor(canon, dtype), None if negatives is None else as_tensor(negatives, dtype))
    if refs.shape[1] != feats.shape[1]:
        raise InputError(f"canonical embeddings have dimension {refs.shape[1]}, features have {feats.shape[1]}",
                         field="canonical_phrases")
    if normalize_features:
        feats = l2_normalize(feats)
    # φ·(q − c) rather than φ·q − φ·c: a query equal to a reference phrase gives exactly 0, not ±1 ulp
    return scale * (feats @ (q[None] - refs).T).min(dim=1).values


def relevancy(features, query, canon, negatives=None, *, scale: float = RELEVANCY_SCALE,
              normalize_features: bool = True) -> torch.Tensor:
    """LERF relevancy ``min_c sigmoid(scale (φ·q − φ·c))`` per feature row.

    Args:
        features: (M,D) features (torch or numpy; float64 input is scored in float64).
        query: (D,) query embedding; canon: (K,D) canonical embeddings; negatives: (J,D) or None.
        normalize_features: L2-normalize the features first (zero vectors stay zero -> R = 0.5).
    Returns:
        (M,) relevancy in [0, 1], always finite.
    """
    margin = relevancy_margin(features, query, canon, negatives, scale=scale,
                              normalize_features=normalize_features)
    return torch.exp(F.logsigmoid(margin))


def relevancy_of_unit_features(features: torch.Tensor, query: torch.Tensor, refs: torch.Tensor, *,
                               scale: float = RELEVANCY_SCALE) -> torch.Tensor:
    """Fast path of :func:`relevancy` for features already L2-normalized and finite (e.g. a decoded
    codebook, normalized once): (M,D), (D,) unit query, (K,D) unit references -> (M,) relevancy."""
    margin = scale * (features @ (query[None] - refs).T.to(features.dtype)).min(dim=1).values
    return torch.exp(F.logsigmoid(margin))


def relevancy_many(features: torch.Tensor, queries: torch.Tensor, refs: torch.Tensor, *,
                   scale: float = RELEVANCY_SCALE) -> torch.Tensor:
    """Relevancy of M features to Q queries in one matrix product.

    Args:
        features: (M,D) (normalized here; non-finite values become 0), queries: (Q,D) unit,
        refs: (K,D) unit canonical (+ negative) embeddings.
    Returns:
        (M,Q) relevancy.
    """
    feats = l2_normalize(torch.nan_to_num(features.float(), nan=0.0, posinf=0.0, neginf=0.0))
    Q, K = queries.shape[0], refs.shape[0]
    diffs = (queries[:, None, :] - refs[None, :, :]).reshape(Q * K, -1).to(feats.dtype)
    margin = scale * (feats @ diffs.T).reshape(-1, Q, K).min(dim=2).values
    return torch.exp(F.logsigmoid(margin))


def relevancy_reference(features: np.ndarray, query: np.ndarray, canon: np.ndarray,
                        negatives: Optional[np.ndarray] = None, scale: float = RELEVANCY_SCALE) -> np.ndarray:
    """Literal float64 transcription of the paper's formula (test oracle; overflows for huge logits).

    (M,D),(D,),(K,D),(J,D)|None -> (M,) = min_c exp(s φ·q) / (exp(s φ·q) + exp(s φ·c)).
    """
    def norm(a):
        a = np.asarray(a, dtype=np.float64)
        return a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), NORM_EPS)
    phi, q = norm(features), norm(query)
    refs = norm(canon if negatives is None or len(negatives) == 0 else np.concatenate([canon, negatives], 0))
    eq = np.exp(scale * phi @ q)[:, None]
    ec = np.exp(scale * phi @ refs.T)
    return (eq / (eq + ec)).min(axis=1)


def _is_f64(x) -> bool:
    return (isinstance(x, torch.Tensor) and x.dtype == torch.float64) or \
        (isinstance(x, np.ndarray) and x.dtype == np.float64)
