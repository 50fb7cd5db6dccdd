"""Neighbourhood smoothing of per-Gaussian latents (paper §3.1 and the supplementary ablations).

``knn_indices`` finds each Gaussian's k nearest Gaussians at one timestep (itself included) with
scipy's cKDTree, once per timestep. ``NeighbourhoodAttention`` is the paper's single-head
self-attention: Gaussian i attends over its neighbours j with softmax(q_i·k_j/√d) and outputs
W_o Σ_j a_ij v_j. ``neighbour_blur`` (Local_Blur) and ``smoothness_loss`` (Local_Reg) are the ablations.
"""
from __future__ import annotations

import math
import warnings

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import nn
from torch.utils.checkpoint import checkpoint

from ..errors import InputError

DEFAULT_NEIGHBOURS = 20


def knn_indices(points: np.ndarray | torch.Tensor, k: int = DEFAULT_NEIGHBOURS) -> torch.Tensor:
    """Indices of each point's ``k`` nearest points, the point itself always in column 0.

    Args:
        points: (N,3) positions.
        k: neighbourhood size including the point itself (clamped to N).
    Returns:
        (N, min(k,N)) int64. Coincident points are handled: column 0 is forced to be the point itself
        and the rest are its nearest *other* points (ties broken by cKDTree).
    """
    pts = np.asarray(points.detach().cpu().numpy() if isinstance(points, torch.Tensor) else points,
                     dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points have shape {pts.shape}, expected (N,3)", field="means")
    n = pts.shape[0]
    if k < 1:
        raise InputError(f"neighbourhood size must be >= 1, got {k}", field="k")
    k = min(k, n)
    if n == 0:
        return torch.zeros((0, 0), dtype=torch.long)
    if not np.all(np.isfinite(pts)):
        raise InputError("Gaussian positions contain NaN or Inf", field="means")
    tree = cKDTree(pts)
    # ask for one extra so that removing the point itself still leaves k-1 others
    kq = min(k + 1, n)
    _, idx = tree.query(pts, k=kq)
    idx = np.asarray(idx, dtype=np.int64).reshape(n, kq)
    self_idx = np.arange(n)[:, None]
    others = idx[idx != self_idx]
    # rows where the point itself was not returned (many duplicates) lose their last column instead
    has_self = (idx == self_idx).any(axis=1)
    rows = []
    if has_self.all():
        others = others.reshape(n, kq - 1)[:, :k - 1]
        rows = np.concatenate([self_idx, others], axis=1)
    else:
        rows = np.empty((n, k), dtype=np.int64)
        rows[:, 0] = np.arange(n)
        for i in range(n):
            row = idx[i][idx[i] != i][:k - 1]
            rows[i, 1:] = row
    return torch.from_numpy(np.ascontiguousarray(rows))


def brute_force_knn(points: np.ndarray, k: int) -> np.ndarray:
    """O(N²) float64 reference: (N, k) nearest indices with the point itself first (for tests)."""
    pts = np.asarray(points, dtype=np.float64)
    d = ((pts[:, None, :] - pts[None, :, :]) ** 2).sum(-1)
    np.fill_diagonal(d, -1.0)
    return np.argsort(d, axis=1, kind="stable")[:, :min(k, len(pts))]


class NeighbourhoodAttention(nn.Module):
    """Single-head self-attention of each Gaussian over its kNN neighbourhood.

    Q, K, V and the output projection are Linear(d, d). Memory: the (N,k,d) gathered keys/values are
    computed in chunks of ``chunk`` Gaussians with activation checkpointing, so 100k Gaussians x 20
    neighbours x 128 channels never sit in memory at once.
    """

    def __init__(self, dim: int = 128, chunk: int = 16384):
        super().__init__()
        self.dim = dim
        self.chunk = chunk
        self.q = nn.Linear(dim, dim)
        self.k = nn.Linear(dim, dim)
        self.v = nn.Linear(dim, dim)
        self.out = nn.Linear(dim, dim)

    def init_near_identity(self) -> "NeighbourhoodAttention":
        """V = O = identity, Q/K scaled down: starts as a near-uniform neighbourhood average."""
        with torch.no_grad():
            for lin in (self.v, self.out):
                lin.weight.copy_(torch.eye(self.dim))
                lin.bias.zero_()
            for lin in (self.q, self.k):
                lin.weight.mul_(0.1)
                lin.bias.zero_()
        return self

    def init_zero_output(self) -> "NeighbourhoodAttention":
        """Output projection zeroed: as a residual branch (L + attention(L)) it starts as the identity.

        Used when refining a lifted field, so the first render is exactly the lift's.
        """
        with torch.no_grad():
            self.out.weight.zero_()
            self.out.bias.zero_()
        return self

    def forward(self, latents: torch.Tensor, neighbours: torch.Tensor,
                rows: torch.Tensor | None = None) -> torch.Tensor:
        """latents (N,d), neighbours (N,k) int64 -> smoothed latents (N,d), or (R,d) for the Gaussians
        ``rows`` (R,) only (an optimizer step that renders one view needs just the Gaussians it sees).

        Computed in an equivalent form that gathers each neighbourhood once instead of twice:
        q_i·k_j = (W_kᵀq_i)·l_j + q_i·b_k, and the second term is constant over j, so the softmax
        only needs q̃_i = W_kᵀq_i against the raw latents; Σ_j a_ij v_j = W_v(Σ_j a_ij l_j) + b_v
        because the weights sum to 1.
        """
        if latents.dim() != 2 or latents.shape[1] != self.dim:
            raise InputError(f"latents have shape {tuple(latents.shape)}, expected (N,{self.dim})",
                             field="latents")
        if neighbours.shape[0] != latents.shape[0]:
            raise InputError(f"{neighbours.shape[0]} neighbour rows for {latents.shape[0]} latents",
                             field="neighbours")
        if latents.shape[0] == 0:
            return latents.clone()
        source, nbr = latents, neighbours
        if rows is not None:
            source, nbr = latents.index_select(0, rows), neighbours.index_select(0, rows)
        q_tilde = (self.q(source) @ self.k.weight) / math.sqrt(self.dim)         # (R,d)
        return self.out(self.v(neighbour_attend(q_tilde, latents, nbr, chunk=self.chunk)))


def neighbour_attend(q_tilde: torch.Tensor, latents: torch.Tensor, neighbours: torch.Tensor,
                     chunk: int = 16384) -> torch.Tensor:
    """Σ_j softmax_j(q̃_i·l_j) l_j over each row's neighbours: (N,d), (N,d), (N,k) -> (N,d).

    On the CPU with numba the fused kernels of :mod:`.attention_kernels` do it without materializing
    the (N,k,d) neighbourhood tensors (forward and backward); otherwise (and as their test reference)
    the gathered form runs in chunks of ``chunk`` rows with activation checkpointing.
    """
    from . import attention_kernels

    if attention_kernels.usable(q_tilde, latents):
        return attention_kernels.NeighbourAttend.apply(q_tilde, latents, neighbours)
    n = q_tilde.shape[0]
    if n <= chunk:
        return _attend(q_tilde, latents, neighbours)
    parts = []
    for s in range(0, n, chunk):
        sl = slice(s, min(n, s + chunk))
        if torch.is_grad_enabled():
            parts.append(checkpoint(_attend, q_tilde[sl], latents, neighbours[sl], use_reentrant=False))
        else:
            parts.append(_attend(q_tilde[sl], latents, neighbours[sl]))
    return torch.cat(parts, 0)


def _attend(q_tilde: torch.Tensor, latents: torch.Tensor, nbr: torch.Tensor) -> torch.Tensor:
    """q̃ (n,d) of the chunk; latents (N,d) of all; nbr (n,k) -> (n,d)."""
    n, k = nbr.shape
    l_n = latents.index_select(0, nbr.reshape(-1)).view(n, k, -1)        # (n,k,d); backward is an index_add
    weights = torch.softmax(torch.bmm(l_n, q_tilde.unsqueeze(2)).squeeze(2), dim=-1)  # max-subtracted softmax
    return torch.bmm(weights.unsqueeze(1), l_n).squeeze(1)


def neighbour_blur(latents: torch.Tensor, neighbours: torch.Tensor) -> torch.Tensor:
    """Local_Blur: mean of the neighbourhood's latents (N,d), (N,k) -> (N,d)."""
    if latents.shape[0] == 0:
        return latents.clone()
    return latents[neighbours].mean(dim=1)


def neighbour_mean(latents: torch.Tensor, neighbours: torch.Tensor) -> torch.Tensor:
    """:func:`neighbour_blur` without the (N,k,d) gather: one sparse (N×N, k entries a row) product.

    Same result up to float32 summation order; no autograd (the learning-free lift smoothing).
    """
    n, k = neighbours.shape[0], neighbours.shape[1] if neighbours.ndim == 2 else 0
    if n == 0 or k == 0:
        return latents.clone()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # torch's beta warning for sparse CSR
        mean = torch.sparse_csr_tensor(torch.arange(0, n * k + 1, k, dtype=torch.long),
                                       neighbours.reshape(-1).long(),
                                       torch.full((n * k,), 1.0 / k, dtype=latents.dtype), (n, latents.shape[0]))
        return mean @ latents


def smoothness_loss(latents: torch.Tensor, neighbours: torch.Tensor, chunk: int = 32768) -> torch.Tensor:
    """Local_Reg: mean over Gaussians of Σ_j∈kNN(i) ||L_i - L_j||₂ (the point itself contributes 0).

    The norm uses sqrt(|x|² + eps²) so its gradient stays finite where neighbours coincide.
    """
    n = latents.shape[0]
    if n == 0:
        return latents.sum() * 0.0
    total = latents.new_zeros(())
    for s in range(0, n, chunk):
        sl = slice(s, min(n, s + chunk))
        diff = latents[sl, None, :] - latents[neighbours[sl, 1:]]
        total = total + torch.sqrt((diff * diff).sum(-1) + 1e-12).sum()
    return total / n
