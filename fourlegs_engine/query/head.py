"""Relevancy straight from latents, without forming the (M, 768) decoded features.

The decoder is an MLP whose last layer is affine, ``y = W h + b`` with ``h`` the (M,H) last hidden
activations (H = 512 < D = 768), followed by ``φ = y / max(|y|, eps)``. Relevancy only needs the
dot products ``φ · (q − c)`` and the norm ``|y|``. With the thin QR factorization ``W = Q R``
(Q (D,H) orthonormal columns, R (H,H)) and ``b = Q β + b⊥`` (b⊥ orthogonal to Q's columns):

    u = R h + β                       (M,H)
    y · v = u · (Qᵀ v) + b⊥ · v       for any direction v (D,)
    |y|²  = |u|² + |b⊥|²              (a sum of squares: no cancellation)

so the last layer costs H·H/2 instead of H·D multiply-adds per row (R is triangular: on the CPU the
product is BLAS ``strmm``), the D-wide normalization and the (D, P) reference product disappear, and
the result is the same relevancy up to float32 rounding
(tests compare it with the float64 decode-then-score reference). The BatchNorm layers (eval mode) are
folded into the preceding Linear layers. Decoders of another shape (or in reduced precision) get no
head and are scored the plain way.

Where a caller only needs to know on which side of a window [low, high] a relevancy lies,
:meth:`RelevancyHead.relevancy_windowed` skips even the triangular product for most rows: with the
eigendecomposition RᵀR = Σ λ_i v_i v_iᵀ (λ descending), the top ``BOUND_RANK`` terms give

    S + λ_min·ρ  ≤  |R h|²  ≤  S + λ_{r+1}·ρ
    with  S = Σ_{i≤r} λ_i (v_i·h)²  and  ρ = |h|² − Σ_{i≤r} (v_i·h)²

at r·H multiply-adds, while the dot products u·(Qᵀv) = h·(Rᵀ Qᵀ v) + β·Qᵀv stay exact. Each margin is
monotone in |y|, so the relevancy lies between its values at the two norm bounds; a row whose interval
is clear of the window needs nothing more. A trained decoder concentrates |Rh|² in a few directions,
so most of the codebook path's re-scored and sampled rows are decided this way.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional

import numpy as np
import torch
import torch.nn.functional as F
from scipy.linalg import blas
from torch import nn

from ..language.autoencoder import NORM_EPS, FeatureDecoder

#: below this many rows a product goes through torch: switching between torch's and BLAS's thread pools
#: costs more than scipy's faster kernels save on small batches
BLAS_MIN_ROWS = 8192
#: eigen-directions of RᵀR used to bound |y| in :meth:`RelevancyHead.relevancy_windowed`
BOUND_RANK = 32
#: relevancy bounds are widened by this much before a row counts as decided (float32 rounding of the
#: exact path is ~1e-6)
BOUND_PAD = 1e-4
#: rows per block of :meth:`RelevancyHead.relevancy_windowed` (its (M,H) activations stay in cache,
#: which is faster per row than one product over all rows)
WINDOW_BLOCK_ROWS = 4096
F32_SAFE = 1e36  # |y|² below this: the float32 exact path computes |u|² without overflow


@dataclass(frozen=True)
class NormBounds:
    """What :meth:`RelevancyHead.relevancy_windowed` bounds |Rh|² with (see the module docstring).

    vectors (H,r) float32 top eigen-directions of RᵀR (None when H = 1), lambdas (r,) float64 their
    eigenvalues, lambda_next / lambda_min the (r+1)-th and the smallest eigenvalue, r_beta (H,) float64
    Rᵀβ (the cross term 2 (Rᵀβ)·h of |u|²), beta_sq |β|².
    """

    vectors: Optional[torch.Tensor]
    lambdas: Optional[torch.Tensor]
    lambda_next: float
    lambda_min: float
    r_beta: torch.Tensor
    beta_sq: float

    @classmethod
    def of(cls, r: torch.Tensor, beta: torch.Tensor) -> "NormBounds":
        lam, vec = torch.linalg.eigh(r.T @ r)          # ascending
        rank = min(BOUND_RANK, lam.shape[0] - 1)
        if rank <= 0:
            return cls(None, None, 0.0, float(lam[0].clamp_min(0)), r.T @ beta, float((beta * beta).sum()))
        return cls(vec[:, -rank:].flip(1).float().contiguous(), lam[-rank:].flip(0),
                   float(lam[-rank - 1].clamp_min(0)), float(lam[0].clamp_min(0)), r.T @ beta,
                   float((beta * beta).sum()))


def _fold(linear: nn.Linear, bn: Optional[nn.BatchNorm1d]) -> tuple[torch.Tensor, torch.Tensor]:
    """(W, b) of ``bn(linear(x))`` in eval mode, computed in float64."""
    w = linear.weight.detach().double()
    b = linear.bias.detach().double() if linear.bias is not None else torch.zeros(w.shape[0], dtype=torch.float64,
                                                                                 device=w.device)
    if bn is None:
        return w, b
    scale = bn.weight.detach().double() / torch.sqrt(bn.running_var.detach().double() + bn.eps)
    return w * scale[:, None], (b - bn.running_mean.detach().double()) * scale + bn.bias.detach().double()


class RelevancyHead:
    """Relevancy margins of latents for one :class:`FeatureDecoder`.

    Build with :meth:`from_decoder` (None when the decoder does not qualify).
    """

    def __init__(self, hidden: list[tuple[torch.Tensor, torch.Tensor]], r: torch.Tensor, beta: torch.Tensor,
                 q: torch.Tensor, b_perp: torch.Tensor):
        self.hidden = [(w.float().contiguous(), b.float().contiguous()) for w, b in hidden]
        # the same weights as Fortran-ordered arrays for scipy's BLAS (no copy per call)
        self.hidden_fortran = [np.asfortranarray(w.float().cpu().numpy()) for w, _ in hidden]
        self.r_t = r.T.float().contiguous()             # (H,H): u = h @ Rᵀ + β
        self.r_fortran = np.asfortranarray(r.float().cpu().numpy())  # upper-triangular R for strmm
        self.beta = beta.float()                        # (H,)
        self.q64 = q                                    # (D,H) float64, to project directions
        self.b_perp64 = b_perp                          # (D,) float64
        self.perp_sq = float((b_perp * b_perp).sum())
        self.device = self.r_t.device
        self.r64 = r.double()                           # (H,H) float64
        self.beta64 = beta.double()                     # (H,) float64
        self._bounds: Optional[NormBounds] = None       # built on the first windowed call

    @classmethod
    def from_decoder(cls, decoder: Any) -> Optional["RelevancyHead"]:
        """The head of a float32 eval-mode :class:`FeatureDecoder` whose last hidden width is below its
        output width; None otherwise (the caller then decodes and scores)."""
        if not isinstance(decoder, FeatureDecoder) or decoder.training:
            return None
        layers = list(decoder.net)
        if any(p.dtype != torch.float32 for p in decoder.parameters()):
            return None
        hidden, i = [], 0
        while i < len(layers) - 1:
            lin, bn, act = layers[i:i + 3] if i + 3 <= len(layers) else (None, None, None)
            if not (isinstance(lin, nn.Linear) and isinstance(bn, nn.BatchNorm1d) and isinstance(act, nn.ReLU)
                    and bn.track_running_stats and bn.running_mean is not None):
                return None
            hidden.append(_fold(lin, bn))
            i += 3
        last = layers[-1]
        if not isinstance(last, nn.Linear) or last.in_features >= last.out_features:
            return None
        w, b = _fold(last, None)                       # (D,H), (D,)
        q, r = torch.linalg.qr(w)                      # thin: (D,H), (H,H)
        beta = q.T @ b
        return cls(hidden, r, beta, q, b - q @ beta)

    def _last_hidden(self, z: torch.Tensor) -> torch.Tensor:
        """(M,d) -> (M,H) last hidden activations (folded BatchNorm, ReLU)."""
        if z.device.type != "cpu" or z.shape[0] < BLAS_MIN_ROWS:
            h = z
            for w, b in self.hidden:
                h = torch.addmm(b, h, w.T).clamp_min_(0.0)
            return h
        # CPU: hᵀ = W zᵀ with zᵀ the Fortran view of C-ordered z; scipy's BLAS beats torch's on these
        # tall-skinny products
        h = z.contiguous()
        for (_, b), w in zip(self.hidden, self.hidden_fortran):
            h = torch.from_numpy(blas.sgemm(1.0, w, h.numpy().T).T).add_(b).clamp_min_(0.0)
        return h

    def _project(self, h: torch.Tensor) -> torch.Tensor:
        """(M,H) -> u = h Rᵀ + β. On the CPU uᵀ = R hᵀ is one in-place triangular BLAS product on h's
        memory (h is C-contiguous, so hᵀ is the Fortran-ordered (H,M) array strmm wants); ``h`` must be
        a temporary of the caller's (``margins`` always passes one)."""
        if h.device.type != "cpu" or h.shape[0] < BLAS_MIN_ROWS:
            return torch.addmm(self.beta, h, self.r_t)
        h = h.contiguous()
        blas.strmm(1.0, self.r_fortran, h.numpy().T, side=0, lower=0, trans_a=0, overwrite_b=1)
        return h.add_(self.beta)

    def _hidden(self, latents: torch.Tensor) -> torch.Tensor:
        """(M,d) latents (non-finite values count as 0) -> (M,H) float32 last hidden activations."""
        z = torch.nan_to_num(torch.as_tensor(latents).to(self.device, torch.float32), nan=0.0, posinf=0.0,
                             neginf=0.0)
        return self._last_hidden(z)

    def _margins_of_hidden(self, h: torch.Tensor, directions: torch.Tensor, scale: float) -> torch.Tensor:
        """(M,H) last hidden activations (consumed), (P,D) directions -> (M,P) finite float32 margins."""
        v = directions.to(self.device, torch.float64)
        proj = (self.q64.T @ v.T).float()              # (H,P)
        offset = (v @ self.b_perp64).float()           # (P,)
        u = self._project(h)
        norm = torch.sqrt(torch.linalg.vector_norm(u, dim=1).square_() + self.perp_sq).clamp_min(NORM_EPS)
        margin = (torch.addmm(offset, u, proj) / norm[:, None]) * scale
        # rows whose activations overflow float32 (|z| near 1e38) score as a zero feature would: margin 0
        return torch.where(torch.isfinite(margin), margin, torch.zeros((), dtype=margin.dtype))

    def margins(self, latents: torch.Tensor, directions: torch.Tensor, scale: float) -> torch.Tensor:
        """``scale · φ(z) · v`` for every latent and direction.

        Args:
            latents: (M,d) latents (non-finite values count as 0, as in the field's decode).
            directions: (P,D) directions v (e.g. query − reference), any float dtype.
        Returns:
            (M,P) float32 margins, always finite.
        """
        return self._margins_of_hidden(self._hidden(latents), directions, scale)

    @property
    def norm_bounds(self) -> NormBounds:
        """The |Rh|² bounds of :meth:`relevancy_windowed`, computed on first use (an eigendecomposition
        of the H x H RᵀR: engines that never bound pay nothing for it)."""
        if self._bounds is None:
            self._bounds = NormBounds.of(self.r64, self.beta64)
        return self._bounds

    def relevancy_windowed(self, latents: torch.Tensor, query: torch.Tensor, refs: torch.Tensor, *, scale: float,
                           window: tuple[float, float]) -> tuple[torch.Tensor, torch.Tensor]:
        """Relevancy of each latent to one query where it may lie inside ``window``; elsewhere a bound.

        Args:
            latents: (M,d); query: (D,) unit; refs: (K,D) unit references.
            window: (low, high) with low <= high.
        Returns:
            (M,) float32 values and (M,) bool ``exact``. Where ``exact`` the value is
            ``relevancy_many(latents, query[None], refs)[:, 0]`` (up to float32 rounding). Elsewhere the
            relevancy is certainly <= low (the value is an upper bound of it, also <= low) or certainly
            > high (a lower bound, also > high): compared with any threshold in [low, high] the value
            decides as the relevancy would.
        """
        bounds = self.norm_bounds
        if bounds.vectors is None or latents.shape[0] == 0:
            return (self.relevancy_many(latents, query[None], refs, scale=scale)[:, 0],
                    torch.ones(latents.shape[0], dtype=torch.bool))
        diffs = query.to(self.device, torch.float64)[None, :] - refs.to(self.device, torch.float64)  # (K,D)
        proj = self.q64.T @ diffs.T                                        # (H,K)
        # one product per row for the exact numerators u·(Qᵀv) = h·(RᵀQᵀv) + β·Qᵀv, the top-r coordinates
        # and h·Rᵀβ
        cols = torch.cat([(self.r64.T @ proj).float(), bounds.vectors, bounds.r_beta.float()[:, None]], 1)
        numer_offset = self.beta64 @ proj + diffs @ self.b_perp64  # (K,)
        parts = [self._windowed_block(latents[s:s + WINDOW_BLOCK_ROWS], diffs, cols, numer_offset, bounds, scale,
                                      window)
                 for s in range(0, latents.shape[0], WINDOW_BLOCK_ROWS)]
        return torch.cat([v for v, _ in parts]), torch.cat([e for _, e in parts])

    def _windowed_block(self, latents: torch.Tensor, diffs: torch.Tensor, cols: torch.Tensor,
                        numer_offset: torch.Tensor, bounds: NormBounds, scale: float,
                        window: tuple[float, float]) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`relevancy_windowed` of at most ``WINDOW_BLOCK_ROWS`` rows; ``cols`` (H, K+r+1)."""
        low, high = float(window[0]), float(window[1])
        K, r = diffs.shape[0], bounds.vectors.shape[1]
        h = self._hidden(latents)                                          # (M,H)
        prod = (h @ cols).double()                                         # (M, K+r+1)
        numer = prod[:, :K] + numer_offset
        coords = prod[:, K:K + r]
        h_sq = torch.linalg.vector_norm(h, dim=1).double().square()
        rest = (h_sq - (coords * coords).sum(1)).clamp_min(0.0)
        top = (coords * coords) @ bounds.lambdas
        fixed = 2.0 * prod[:, -1] + bounds.beta_sq + self.perp_sq           # |y|² = |Rh|² + fixed
        norm_sq_high = top + bounds.lambda_next * rest + fixed
        norm_low = torch.sqrt((top + bounds.lambda_min * rest + fixed).clamp_min(0.0)).clamp_min(NORM_EPS)
        norm_high = torch.sqrt(norm_sq_high.clamp_min(0.0)).clamp_min(NORM_EPS)
        m_a, m_b = scale * numer / norm_low[:, None], scale * numer / norm_high[:, None]
        rel_low = torch.exp(F.logsigmoid(torch.minimum(m_a, m_b)).min(dim=1).values)
        rel_high = torch.exp(F.logsigmoid(torch.maximum(m_a, m_b)).min(dim=1).values)
        below = rel_high <= low - BOUND_PAD
        above = rel_low > high + BOUND_PAD
        # rows whose exact (float32) evaluation would overflow score as zero features there: not bounded
        finite = torch.isfinite(rel_low) & torch.isfinite(rel_high) & (norm_sq_high < F32_SAFE)
        below, above = below & finite, above & finite
        exact = ~(below | above)
        out = torch.where(below, rel_high, rel_low).float()
        rows = torch.nonzero(exact).flatten()
        if rows.numel():
            margin = self._margins_of_hidden(h[rows].contiguous(), diffs, scale)
            out[rows] = torch.exp(F.logsigmoid(margin.min(dim=1).values))
        return out, exact

    def relevancy_gradient(self, latents: torch.Tensor, query: torch.Tensor, refs: torch.Tensor, *,
                           scale: float) -> torch.Tensor:
        """(M,d) gradient of each latent's relevancy ``min_c sigmoid(scale φ(z)·(q − c))`` with respect to
        the latent, in float64 (the first-order term of the relevancy around a code; at a kink of a ReLU
        or of the min, the gradient of the side taken). Non-finite latents count as 0 (as in
        :meth:`margins`) and get the gradient there; the result is always finite.

        Args:
            latents: (M,d); query: (D,) unit; refs: (K,D) unit references.
        """
        with torch.inference_mode(False), torch.enable_grad():
            z = torch.nan_to_num(torch.as_tensor(latents).detach().to(self.device, torch.float64).clone(),
                                 nan=0.0, posinf=0.0, neginf=0.0).requires_grad_(True)
            diffs = query.to(self.device, torch.float64).clone()[None, :] - refs.to(self.device, torch.float64).clone()
            h = z
            for w, b in self.hidden:
                h = torch.relu(h @ w.double().clone().T + b.double().clone())
            u = h @ self.r64.clone().T + self.beta64.clone()
            norm = torch.sqrt((u * u).sum(1) + self.perp_sq).clamp_min(NORM_EPS)
            numer = u @ (self.q64.clone().T @ diffs.T) + diffs @ self.b_perp64.clone()
            margin = (scale * numer / norm[:, None]).min(dim=1).values
            (grad,) = torch.autograd.grad(torch.sigmoid(margin).sum(), z)
        return torch.nan_to_num(grad.detach(), nan=0.0, posinf=0.0, neginf=0.0)

    def relevancy_many(self, latents: torch.Tensor, queries: torch.Tensor, refs: torch.Tensor, *,
                       scale: float) -> torch.Tensor:
        """(M,d) latents, (Q,D) unit queries, (K,D) unit references -> (M,Q) relevancy
        ``min_c sigmoid(scale φ·(q − c))`` (see :func:`query.lerf.relevancy_many`)."""
        Q, K = queries.shape[0], refs.shape[0]
        diffs = (queries[:, None, :].double() - refs[None, :, :].double()).reshape(Q * K, -1)
        margin = self.margins(latents, diffs, scale).reshape(-1, Q, K).min(dim=2).values
        return torch.exp(F.logsigmoid(margin))
