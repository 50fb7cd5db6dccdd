"""Per-Gaussian latents of one timestep from the encoded teacher (paper §3.1): the teacher's per-pixel
latents, the learning-free lift and its optional blur, and the paper's optimization (see :mod:`.distill`)."""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Sequence

import numpy as np
import torch

from .attention import NeighbourhoodAttention, knn_indices, neighbour_blur, smoothness_loss
from .autoencoder import FeatureEncoder, l2_normalize
from .pyramid import PyramidLayout, interpolate_grid, sample_positions, upsample_to_pixels
from .view_operator import ViewOperator

if TYPE_CHECKING:
    from .distill import DistillOptions


@torch.no_grad()
def teacher_latents(encoder: FeatureEncoder, layout: PyramidLayout, crop_features: np.ndarray | torch.Tensor,
                    stride: int = 1, width: int | None = None, height: int | None = None) -> torch.Tensor:
    """Encoded per-pixel teacher of one view: (num_crops, D) crop features -> (h*w, d) unit latents.

    ``width``/``height`` (default the layout's) give the resolution of the rendered view; pixel
    centres of a smaller view map to (x + 0.5) * W / width - 0.5 in the full-resolution pyramid.
    """
    width = layout.width if width is None else int(width)
    height = layout.height if height is None else int(height)
    crops = torch.from_numpy(np.array(crop_features, dtype=np.float32))
    h = encoder.first_layer()(crops)                                  # (n, hidden) exact before interp.
    xs = (sample_positions(width, stride) + 0.5) * (layout.width / width) - 0.5
    ys = (sample_positions(height, stride) + 0.5) * (layout.height / height) - 0.5
    grid = interpolate_grid(layout, h, xs, ys)                        # (h', w', hidden)
    z = encoder.after_first_layer(grid.reshape(-1, grid.shape[-1])).view(grid.shape[0], grid.shape[1], -1)
    if stride > 1:
        z = l2_normalize(upsample_to_pixels(z, width, height, stride))
    return z.reshape(width * height, -1).contiguous()


def timestep_seed(seed: int, t: int) -> int:
    """The seed of timestep ``t``'s optimization: a killed run resumes with the same result."""
    return int(np.random.SeedSequence([int(seed), int(t), 0x4C45]).generate_state(1)[0])


def lift_latents(ops: Sequence[ViewOperator], teachers: Sequence[torch.Tensor]) -> torch.Tensor:
    """Rendering-weighted average of the teacher latents per Gaussian, L2-normalized: -> (N,d)."""
    num = None
    den = None
    for op, e in zip(ops, teachers):
        part = op.splat(e)
        num = part if num is None else num + part
        den = op.weight_sum if den is None else den + op.weight_sum
    seen = den > 1e-12
    out = torch.zeros_like(num)
    out[seen] = num[seen] / den[seen, None]
    return l2_normalize(out)


def smooth_lift(latents: torch.Tensor, means: torch.Tensor, neighbours: int,
                knn: torch.Tensor | None = None) -> torch.Tensor:
    """``lift_smoothing="blur"``: each latent (N,d) replaced by the mean over its ``neighbours`` nearest
    Gaussians (itself included; ``knn`` (N,k) if already computed), L2-normalized."""
    from .attention import neighbour_mean
    if latents.shape[0] == 0:
        return latents
    nb = knn_indices(means, neighbours) if knn is None else knn
    return l2_normalize(neighbour_mean(latents.float(), nb))


def optimize_latents(ops: Sequence[ViewOperator], teachers: Sequence[torch.Tensor], neighbours: torch.Tensor | None,
                     config: DistillOptions, seed: int, init: torch.Tensor | None = None,
                     progress: Any = None) -> tuple[torch.Tensor, float | None]:
    """The paper's optimization for one timestep; returns (smoothed latents (N,d), last loss)."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    n, d = ops[0].num_gaussians, teachers[0].shape[1]
    latents = torch.zeros(n, d) if init is None else init.detach().clone().float()
    latents.requires_grad_(True)
    groups: list[dict[str, Any]] = [{"params": [latents], "lr": config.lr_latents}]
    attention = None
    if config.smoothing == "attention":
        attention = NeighbourhoodAttention(d)
        if init is not None:
            attention.init_zero_output()
        groups.append({"params": list(attention.parameters()), "lr": config.lr_attention})
    opt = torch.optim.Adam(groups, eps=1e-15)

    def smooth(x: torch.Tensor, rows: torch.Tensor | None = None) -> torch.Tensor:
        """Smoothed latents of all Gaussians (N,d), or of ``rows`` only (R,d)."""
        if config.smoothing == "attention":
            # refining a lift: residual attention that starts as the identity
            mixed = attention(x, neighbours, rows)
            return (x if rows is None else x.index_select(0, rows)) + mixed if init is not None else mixed
        if config.smoothing == "blur":
            return neighbour_blur(x, neighbours if rows is None else neighbours.index_select(0, rows))
        return x if rows is None else x.index_select(0, rows)

    k = min(config.views_per_iteration, len(ops))
    loss_value = None
    for _ in range(config.num_iterations):
        views = rng.choice(len(ops), size=k, replace=False)
        # a view's loss depends only on the Gaussians it sees: smooth just those (same gradient)
        loss = sum((ops[v].render_columns(smooth(latents, ops[v].columns)) - teachers[v]).abs().mean()
                   for v in views) / k
        if config.smoothness > 0:
            loss = loss + config.smoothness * smoothness_loss(latents, neighbours)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        loss_value = float(loss.detach())
        if progress is not None:
            progress.update(1)
    with torch.no_grad():
        final = smooth(latents).detach()
    if not torch.all(torch.isfinite(final)):
        raise FloatingPointError("distillation diverged (NaN/Inf latents); lower the learning rates")
    return final, loss_value
