"""Rendering per-Gaussian features with frozen geometry as sparse matrices: one view's blending weights
from the rasterizer, so the distillation renders and splats latents without rasterizing again."""
from __future__ import annotations

import warnings
from typing import Any

import torch

from ..render import rasterize


class ViewOperator:
    """Rendering of per-Gaussian features for one view with frozen geometry, as sparse matrices.

    ``render(L)`` = A @ L with A (P×N), A[p,i] = α_i T_i at pixel p — what the rasterizer's
    ``features`` output computes (background 0) — and ``splat(E)`` = Aᵀ @ E. Only the Gaussians the
    view sees (``columns``, sorted ids) are stored; :meth:`render_columns` takes their values directly.
    """

    def __init__(self, pixel: torch.Tensor, gaussian: torch.Tensor, weight: torch.Tensor, num_pixels: int,
                 num_gaussians: int):
        pixel, gaussian = pixel.long(), gaussian.long()
        weight = weight.detach().to(torch.float32)
        self.num_pixels, self.num_gaussians = int(num_pixels), int(num_gaussians)
        if pixel.numel() > 1 and not bool((pixel[1:] >= pixel[:-1]).all()):  # the rasterizer's rows are sorted
            order = torch.argsort(pixel, stable=True)
            pixel, gaussian, weight = pixel[order], gaussian[order], weight[order]
        self.columns = torch.unique(gaussian)                              # (C,) sorted ids seen by the view
        column = torch.searchsorted(self.columns, gaussian)
        C = int(self.columns.numel())
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            self.A = torch.sparse_csr_tensor(_crow(pixel, num_pixels), column, weight, (num_pixels, C))
            by_c = torch.argsort(column, stable=True)
            self.At = torch.sparse_csr_tensor(_crow(column[by_c], C), pixel[by_c], weight[by_c], (C, num_pixels))
        self.weight_sum = torch.bincount(gaussian, weights=weight.double(), minlength=num_gaussians).float()
        self.nnz = int(weight.numel())

    @staticmethod
    def from_weights(weights: Any, num_gaussians: int) -> "ViewOperator":
        return ViewOperator(weights.pixel, weights.gaussian, weights.weight, weights.width * weights.height,
                            num_gaussians)

    def render(self, latents: torch.Tensor) -> torch.Tensor:
        """(N,d) -> (P,d), differentiable w.r.t. the latents."""
        return _SparseRender.apply(latents.index_select(0, self.columns), self)

    def render_columns(self, values: torch.Tensor) -> torch.Tensor:
        """(C,d) values of the ``columns`` Gaussians -> (P,d), differentiable."""
        return _SparseRender.apply(values, self)

    def splat(self, values: torch.Tensor) -> torch.Tensor:
        """(P,d) -> (N,d): Σ_p w_i(p) values(p)."""
        out = values.new_zeros(self.num_gaussians, values.shape[1])
        out[self.columns] = self.At @ values
        return out


def _crow(sorted_rows: torch.Tensor, num_rows: int) -> torch.Tensor:
    """CSR row pointers (num_rows+1,) of sorted row indices."""
    crow = torch.zeros(num_rows + 1, dtype=torch.long)
    crow[1:] = torch.cumsum(torch.bincount(sorted_rows, minlength=num_rows), 0)
    return crow


class _SparseRender(torch.autograd.Function):
    """A @ latents, with Aᵀ @ grad as the gradient (A stays constant)."""

    @staticmethod
    def forward(ctx: Any, latents: torch.Tensor, op: ViewOperator) -> torch.Tensor:  # noqa: D401
        ctx.op = op
        return op.A @ latents

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor, None]:
        return ctx.op.At @ grad.contiguous(), None


def view_operator(frame: Any, camera: Any) -> ViewOperator:
    """Blending weights of one view from the rasterizer, as a :class:`ViewOperator`."""
    with torch.no_grad():
        out = rasterize(frame.means, frame.rotations, frame.log_scales, frame.opacity_logits, camera,
                        outputs=("weights",))
    return ViewOperator.from_weights(out["weights"], frame.num_gaussians)
