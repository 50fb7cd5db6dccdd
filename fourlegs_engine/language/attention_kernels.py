"""Fused CPU kernels (numba) for the neighbourhood attention of the ``optimize`` distillation.

:func:`~.attention.neighbour_attend` needs, for every Gaussian i and its k neighbours j,
a_ij = softmax_j(q̃_i·l_j) and m_i = Σ_j a_ij l_j. Written with tensors, that gathers an (N,k,d) copy of
the latents (1 GB at 100k Gaussians × 20 × 128) in the forward pass, again when checkpointing
recomputes it, and scatters another one in the backward pass, which made an optimizer step take
seconds. These kernels read the neighbour rows in place and keep only the (N,k) weights for the
backward pass:

    forward:   a_ij = softmax_j(q̃_i·l_j),  m_i = Σ_j a_ij l_j
    backward:  δ_ij = a_ij (g_i·l_j − Σ_j' a_ij' g_i·l_j'),  ∂q̃_i = Σ_j δ_ij l_j,
               ∂l_j += a_ij g_i + δ_ij q̃_i   (summed over every row i that has j as a neighbour)

Rows are split into two fixed halves that run concurrently (the kernels release the GIL); the backward
halves scatter into their own ∂l buffers, summed in a fixed order, so the result does not depend on the
thread count. The gathered torch form stays the reference (tested against it in float64, and gradcheck).
"""
from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import torch

from ..jit_cache import JIT_CACHE

try:  # pragma: no cover - exercised when numba is missing
    import numba
except ImportError:  # pragma: no cover
    numba = None


def available() -> bool:
    return numba is not None


def usable(*tensors: torch.Tensor) -> bool:
    """numba present, CPU float32/float64 tensors of one dtype."""
    return (numba is not None and all(t.device.type == "cpu" for t in tensors)
            and len({t.dtype for t in tensors}) == 1 and tensors[0].dtype in (torch.float32, torch.float64))


def _forward_py(lo, hi, q_tilde, latents, nbr, weights, mixed):  # pragma: no cover - compiled by numba
    k = nbr.shape[1]
    d = latents.shape[1]
    logits = np.empty(k, dtype=np.float64)
    for i in range(lo, hi):
        top = -np.inf
        for j in range(k):
            n = nbr[i, j]
            s = 0.0
            for c in range(d):
                s += q_tilde[i, c] * latents[n, c]
            logits[j] = s
            if s > top:
                top = s
        total = 0.0
        for j in range(k):
            e = math.exp(logits[j] - top)
            logits[j] = e
            total += e
        for c in range(d):
            mixed[i, c] = 0.0
        for j in range(k):
            a = logits[j] / total
            weights[i, j] = a
            n = nbr[i, j]
            for c in range(d):
                mixed[i, c] += a * latents[n, c]


def _backward_py(lo, hi, q_tilde, latents, nbr, weights, grad_mixed, grad_q, grad_lat):  # pragma: no cover
    k = nbr.shape[1]
    d = latents.shape[1]
    dots = np.empty(k, dtype=np.float64)
    for i in range(lo, hi):
        mean = 0.0
        for j in range(k):
            n = nbr[i, j]
            s = 0.0
            for c in range(d):
                s += grad_mixed[i, c] * latents[n, c]
            dots[j] = s
            mean += weights[i, j] * s
        for c in range(d):
            grad_q[i, c] = 0.0
        for j in range(k):
            a = weights[i, j]
            delta = a * (dots[j] - mean)
            n = nbr[i, j]
            for c in range(d):
                grad_q[i, c] += delta * latents[n, c]
                grad_lat[n, c] += a * grad_mixed[i, c] + delta * q_tilde[i, c]


# reassociation lets LLVM vectorize the d-long dot products; nothing here relies on inf/NaN semantics
_FASTMATH = {"reassoc", "contract"}
_forward = numba.njit(nogil=True, cache=JIT_CACHE, fastmath=_FASTMATH)(_forward_py) if numba is not None else None
_backward = numba.njit(nogil=True, cache=JIT_CACHE, fastmath=_FASTMATH)(_backward_py) if numba is not None else None


def _halves(n: int) -> list[tuple[int, int]]:
    mid = n // 2
    return [(0, mid), (mid, n)] if n > 1 else [(0, n)]


def _run(fn, jobs: list[tuple[Any, ...]]) -> None:
    if torch.get_num_threads() >= 2 and len(jobs) > 1:
        with ThreadPoolExecutor(len(jobs)) as pool:
            list(pool.map(lambda job: fn(*job), jobs))
    else:
        for job in jobs:
            fn(*job)


class NeighbourAttend(torch.autograd.Function):
    """(q̃ (N,d), latents (N,d), neighbours (N,k) int64) -> (N,d) Σ_j softmax_j(q̃_i·l_j) l_j."""

    @staticmethod
    def forward(ctx: Any, q_tilde: torch.Tensor, latents: torch.Tensor, neighbours: torch.Tensor) -> torch.Tensor:
        q = q_tilde.detach().contiguous()
        lat = latents.detach().contiguous()
        nbr = neighbours.detach().to(torch.int64).contiguous()
        n = q.shape[0]
        weights = torch.empty(n, nbr.shape[1], dtype=q.dtype)
        mixed = torch.empty_like(q)
        qa, la, na, wa, ma = q.numpy(), lat.numpy(), nbr.numpy(), weights.numpy(), mixed.numpy()
        _run(_forward, [(lo, hi, qa, la, na, wa, ma) for lo, hi in _halves(n)])
        ctx.save_for_backward(q, lat, nbr, weights)
        return mixed

    @staticmethod
    def backward(ctx: Any, grad_mixed: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, None]:
        q, lat, nbr, weights = ctx.saved_tensors
        g = grad_mixed.detach().to(q.dtype).contiguous()
        n = q.shape[0]
        grad_q = torch.empty_like(q)
        halves = _halves(n)
        grad_lat = [torch.zeros_like(lat) for _ in halves]
        qa, la, na, wa, ga, gq = q.numpy(), lat.numpy(), nbr.numpy(), weights.numpy(), g.numpy(), grad_q.numpy()
        _run(_backward, [(lo, hi, qa, la, na, wa, ga, gq, buf.numpy()) for (lo, hi), buf in zip(halves, grad_lat)])
        total = grad_lat[0]
        for buf in grad_lat[1:]:
            total += buf
        return grad_q, total, None
