"""Per-pixel label coverage: what a "labels" teacher sees of a scene whose Gaussians carry labels.

Channel c of a coverage frame is the share of each pixel's colour contributed by the Gaussians of label
c (rendered with the rasterizer, occlusion included); 8 frames around a timestep make a crop tube.
"""
from __future__ import annotations

from typing import Any, Iterable, Sequence

import numpy as np
import torch

from ..errors import InputError


def label_one_hot(labels: np.ndarray | torch.Tensor, num_labels: int, dtype: torch.dtype = torch.float32
                  ) -> torch.Tensor:
    """(N,) int labels -> (N, num_labels) one-hot features (label -1 or out of range -> all zero)."""
    lab = torch.from_numpy(np.array(labels, dtype=np.int64).reshape(-1))
    valid = (lab >= 0) & (lab < num_labels)
    out = torch.zeros(lab.shape[0], num_labels, dtype=dtype)
    idx = torch.nonzero(valid, as_tuple=True)[0]
    out[idx, lab[idx]] = 1.0
    return out


def render_label_coverage(scene: Any, camera: Any, t: int, *, num_labels: int | None = None,
                          options: Any = None, backend: str = "auto") -> torch.Tensor:
    """Per-pixel label coverage of ``scene`` at timestep ``t`` seen by ``camera``.

    Renders one-hot label features with the rasterizer: channel c at a pixel is sum over Gaussians of
    label c of alpha_i * T_i, the share of the pixel's colour those Gaussians contribute, with
    occlusion by every other Gaussian of the scene accounted for.

    Returns:
        (C, H, W) float32 in [0, 1] with C = ``num_labels`` (default: the scene's vocabulary size).
    """
    from ..render import render_frame

    g = scene.gaussians
    if g.labels is None:
        raise InputError("the scene has no ground-truth labels (not a synthetic scene)", field="labels")
    if num_labels is None:
        num_labels = len((scene.metadata or {}).get("labels") or []) or int(np.max(g.labels)) + 1
    t = g.check_timestep(t)
    frame = g.at(t)
    features = label_one_hot(np.asarray(g.labels[t]), num_labels)
    kwargs: dict[str, Any] = {"outputs": ("features",), "features": features, "backend": backend}
    if options is not None:
        kwargs["options"] = options
    out = render_frame(frame, camera, **kwargs)
    cov = torch.nan_to_num(out["features"].float(), nan=0.0).clamp_(0.0, 1.0)  # (H, W, C)
    return cov.permute(2, 0, 1).contiguous()


def label_coverage_tube(frames: Sequence[torch.Tensor] | torch.Tensor, t: int,
                        offsets: Iterable[int] = tuple(range(-4, 4))) -> torch.Tensor:
    """Stack coverage frames (T of (C,H,W)) into the 8-frame tube around ``t``: (8, C, H, W).

    Edge tubes repeat the first/last frame, as the ViCLIP pipeline does.
    """
    T = len(frames)
    idx = [min(max(t + o, 0), T - 1) for o in offsets]
    return torch.stack([frames[i] for i in idx])
