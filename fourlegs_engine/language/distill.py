"""Distil the teacher features into per-Gaussian 128-d latents, timestep by timestep (paper §3.1).

Modes (geometry frozen in all of them):

``lift`` (learning-free; LUDVIG-style, beyond the paper)
    Rendering is linear in the latents: pixel p of view v renders l(p) = Σ_i w_i(p) L_i with
    w_i(p) = α_i T_i. The lift is the rendering-weighted average of the encoded teacher latents
    L_i ∝ Σ_v Σ_p w_i(p) e_v(p) / Σ_v Σ_p w_i(p), L2-normalized — one rasterizer pass per view. Where
    every pixel sees a single Gaussian this is exactly the direction of the least-squares solution.
    Gaussians no training pixel sees keep a zero latent. Computed by one splat pass per view
    (:func:`~fourlegs_engine.render.splat`, the transpose of rendering: Σ_p w·[e, 1] per Gaussian
    without materializing the weights; equal to the weights-based sum up to float32 summation order).
    ``lift_smoothing="blur"`` then replaces each lifted latent by the mean over its ``neighbours``
    nearest Gaussians (itself included; the paper's Local_Blur with fixed weights, no learning) and
    re-normalizes: the learning-free counterpart of optimize's neighbourhood smoothing. It also gives
    unseen Gaussians their neighbours' latent. It helps on small scenes and not on larger ones (see
    docs/benchmarks.md), so it is off by default. Cost: one kNN and one sparse product per timestep.
``optimize`` (the paper)
    Latents start at 0 and are smoothed by single-head self-attention over each Gaussian's 20 nearest
    neighbours (kNN once per timestep); the smoothed latents are rendered and compared with L1 to the
    encoded teacher of ``views_per_iteration`` randomly drawn training views per iteration (the
    official code draws one view per iteration); Adam (eps 1e-15), lr 0.0025 for the latents and
    1.6e-4 for the attention, 2000 iterations by default. Ablations: ``smoothing="none"`` (w/o Attn),
    ``"blur"`` (Local_Blur: kNN mean) and ``smoothness`` λ (Local_Reg).
``lift+refine``
    The lift, then ``iterations`` optimize steps from there. The attention is a residual branch with
    a zero-initialized output projection (L + SelfAttention(L)), so the first render is the lift's.

Rendering during optimization uses the blending weights of each view, computed once per timestep
by the rasterizer (``outputs=("weights",)``): with frozen geometry, rendering features is the sparse
linear map (P×N) @ (N×d), identical to the rasterizer's feature output and much cheaper to repeat.

Teacher: the encoder of the trained autoencoder applied to the per-pixel teacher features. Its first
Linear layer is applied to the crop features before the pixel interpolation (exact: the
interpolation is a convex combination), the rest per sample pixel. With ``teacher_stride`` s > 1 the
encoded latents are computed at the centres of s×s pixel blocks and bilinearly upsampled (then
re-normalized) — a speed knob measured by ``fourlegs bench distill``.

Results: one float16 (N, 128) file per timestep under ``language/steps/`` (atomic; a killed run
resumes and ends with exactly the uninterrupted result since every timestep is seeded from its index
and written only when finished), merged into ``language/latents.npy`` (T, N, 128) when complete.
"""
from __future__ import annotations

import math
import os
import shutil
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from ..errors import ConfigMismatchError, InputError
from ..fileio import atomic_path, load_npy, read_json
from ..render.options import RasterOptions
from ..scene.scene import Scene
from ..threads import torch_threads
from .attention import NeighbourhoodAttention, knn_indices, neighbour_blur, smoothness_loss
from .autoencoder import (AE_REPORT, DECODER_FILE, ENCODER_FILE, FeatureEncoder, l2_normalize, load_decoder,
                          load_encoder, weights_fingerprint)
from .encoders import CANONICAL_PHRASES
from .extract import feature_store, load_step_features, view_has_evidence
from .pyramid import PyramidLayout, interpolate_grid, sample_positions, upsample_to_pixels
from .store import StepStore, config_hash, format_ranges, select_timesteps

MODES = ("optimize", "lift", "lift+refine")
SMOOTHING = ("attention", "none", "blur")
LIFT_SMOOTHING = ("none", "blur")
LANGUAGE_DIR = "language"
STEPS_DIR = "language/steps"
LATENTS_FILE = "language/latents.npy"
NEXT_LATENTS_NAME = "latents.next.npy"  # a merged field on its way in (see _swap_in_latents)
DEFAULT_ITERATIONS = {"optimize": 2000, "lift": 0, "lift+refine": 200}
#: lift's splat pass: 64-entry chunks are faster for the wide (d+1)-channel splat; same result up to
#: float32 summation order
LIFT_RASTER_OPTIONS = RasterOptions(chunk=64)
#: lift's view accumulators (see :func:`_lift_timestep`)
LIFT_STREAMS = 2


@dataclass
class DistillConfig:
    """Distillation settings; :meth:`to_dict` (the hashed part) keeps only what affects the result.

    Attributes:
        mode: "optimize" | "lift" | "lift+refine".
        iterations: optimizer steps per timestep (None: 2000 optimize, 200 lift+refine).
        smoothing: "attention" (paper) | "none" (w/o Attn) | "blur" (Local_Blur).
        smoothness: weight λ of the Local_Reg loss (0 = off).
        neighbours: k of the kNN (the Gaussian itself included).
        lr_latents, lr_attention: Adam learning rates.
        views_per_iteration: training views rendered per optimizer step (sampled without replacement).
        teacher_stride: the teacher latents are encoded every ``teacher_stride`` pixels and upsampled.
        view_scale: the training views are rendered (blending weights) and compared at this fraction
            of their resolution (speed knob; 1 = full resolution).
        seed: base seed; timestep t uses a seed derived from (seed, t).
        split: the camera split distilled from.
        lift_smoothing: "none" | "blur": the lift (also lift+refine's starting point) averaged over each
            Gaussian's ``neighbours`` nearest Gaussians and re-normalized (learning-free).
    """

    mode: str = "lift"
    iterations: int | None = None
    smoothing: str = "attention"
    smoothness: float = 0.0
    neighbours: int = 20
    lr_latents: float = 0.0025
    lr_attention: float = 1.6e-4
    views_per_iteration: int = 1
    teacher_stride: int = 4
    view_scale: float = 1.0
    seed: int = 0
    split: str = "train"
    lift_smoothing: str = "none"

    def check(self) -> "DistillConfig":
        if self.mode not in MODES:
            raise InputError(f"unknown mode {self.mode!r} (choose from {', '.join(MODES)})", field="--mode")
        if self.smoothing not in SMOOTHING:
            raise InputError(f"unknown smoothing {self.smoothing!r} (choose from {', '.join(SMOOTHING)})",
                             field="smoothing")
        if self.lift_smoothing not in LIFT_SMOOTHING:
            raise InputError(f"unknown lift smoothing {self.lift_smoothing!r} (choose from "
                             f"{', '.join(LIFT_SMOOTHING)})", field="--lift-smoothing")
        if self.mode == "optimize" and self.lift_smoothing != "none":
            raise InputError("lift smoothing applies to lift and lift+refine only", field="--lift-smoothing")
        if self.iterations is not None and self.iterations < 0:
            raise InputError(f"must be >= 0, got {self.iterations}", field="--iterations")
        if self.mode == "optimize" and self.num_iterations < 1:
            raise InputError("optimize needs at least one iteration", field="--iterations")
        if not 0 < self.view_scale <= 1:
            raise InputError(f"must be in (0, 1], got {self.view_scale}", field="--view-scale")
        if self.neighbours < 1 or self.views_per_iteration < 1 or self.teacher_stride < 1:
            raise InputError("neighbours, views per iteration and teacher stride must be >= 1", field="distill")
        if not (self.smoothness >= 0 and math.isfinite(self.smoothness)):
            raise InputError(f"must be >= 0, got {self.smoothness}", field="--smoothness")
        return self

    @property
    def num_iterations(self) -> int:
        return DEFAULT_ITERATIONS[self.mode] if self.iterations is None else int(self.iterations)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["iterations"] = self.num_iterations
        if self.lift_smoothing == "none":  # absent when off: the hashes of existing fields stay valid
            d.pop("lift_smoothing")
        if self.mode == "lift":
            for key in ("smoothing", "smoothness", "lr_latents", "lr_attention",
                        "views_per_iteration", "seed", "iterations"):
                d.pop(key)
            if self.lift_smoothing == "none":
                d.pop("neighbours")
        elif self.smoothing != "attention":
            d.pop("lr_attention")
        return d


@dataclass
class TimestepTiming:
    t: int
    seconds: float
    weights_seconds: float
    teacher_seconds: float
    lift_seconds: float
    optimize_seconds: float
    iterations: int
    final_loss: float | None

    @property
    def seconds_per_iteration(self) -> float | None:
        return self.optimize_seconds / self.iterations if self.iterations else None


@dataclass
class DistillResult:
    """What :func:`distill_scene` did: per-timestep timings, where the latents are, what was skipped."""

    mode: str
    config: dict[str, Any]
    config_hash: str
    out_dir: str
    latents: str | None
    timings: list[TimestepTiming] = field(default_factory=list)
    skipped: list[int] = field(default_factory=list)

    @property
    def seconds_per_timestep(self) -> float | None:
        return float(np.mean([t.seconds for t in self.timings])) if self.timings else None

    def to_dict(self) -> dict[str, Any]:
        return {"mode": self.mode, "config": self.config, "config_hash": self.config_hash,
                "out_dir": self.out_dir, "latents": self.latents, "skipped": self.skipped,
                "seconds_per_timestep": self.seconds_per_timestep,
                "timings": [dict(asdict(t), seconds_per_iteration=t.seconds_per_iteration) for t in self.timings]}


# ------------------------------------------------------------------------------ rendering map
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
    crow = torch.zeros(num_rows + 1, dtype=torch.long)
    crow[1:] = torch.cumsum(torch.bincount(sorted_rows, minlength=num_rows), 0)
    return crow


class _SparseRender(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, latents: torch.Tensor, op: ViewOperator) -> torch.Tensor:  # noqa: D401
        ctx.op = op
        return op.A @ latents

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor, None]:
        return ctx.op.At @ grad.contiguous(), None


def view_operator(frame: Any, camera: Any) -> ViewOperator:
    """Blending weights of one view from the rasterizer, as a :class:`ViewOperator`."""
    from ..render import rasterize
    with torch.no_grad():
        out = rasterize(frame.means, frame.rotations, frame.log_scales, frame.opacity_logits, camera,
                        outputs=("weights",))
    return ViewOperator.from_weights(out["weights"], frame.num_gaussians)


# ------------------------------------------------------------------------------------ teacher
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


# ---------------------------------------------------------------------------------- per step
def timestep_seed(seed: int, t: int) -> int:
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
                     config: DistillConfig, seed: int, init: torch.Tensor | None = None,
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


def distill_timestep(scene: Scene, t: int, encoder: FeatureEncoder, features: StepStore,
                     config: DistillConfig, progress: Any = None) -> tuple[np.ndarray, TimestepTiming]:
    """Latents (N, d) float32 of timestep t and its timing breakdown."""
    start = time.perf_counter()
    frame = scene.gaussians.at(t)
    cameras = scene.cameras.cameras(t, config.split)
    feats, layouts, offsets = load_step_features(scene, features, t)
    if not cameras:
        raise InputError(f"timestep {t} has no {config.split} cameras to lift from", field="cameras")
    # views without evidence (annotation masks that do not cover them) do not vote
    voting = [i for i, off in enumerate(offsets) if view_has_evidence(feats, off)]
    cameras, layouts, offsets = ([seq[i] for i in voting] for seq in (cameras, layouts, offsets))
    if not cameras:
        latents = np.zeros((frame.num_gaussians, encoder.dims[-1]), dtype=np.float32)
        return latents, TimestepTiming(t, time.perf_counter() - start, 0.0, 0.0, 0.0, 0.0, 0, None)
    if config.mode == "lift":
        return _lift_timestep(frame, cameras, encoder, feats, layouts, offsets, config, t, start)
    ops, teachers = [], []
    w_s = te_s = 0.0
    for cam, layout, off in zip(cameras, layouts, offsets):
        view = cam if config.view_scale == 1.0 else cam.scaled(config.view_scale)
        s = time.perf_counter()
        ops.append(view_operator(frame, view))
        w_s += time.perf_counter() - s
        s = time.perf_counter()
        teachers.append(teacher_latents(encoder, layout, feats[off:off + layout.num_crops], config.teacher_stride,
                                        view.width, view.height))
        te_s += time.perf_counter() - s
    lift_s = opt_s = 0.0
    init = None
    loss = None
    neighbours = None
    if config.mode in ("lift", "lift+refine"):
        s = time.perf_counter()
        init = lift_latents(ops, teachers)
        if config.lift_smoothing == "blur":
            neighbours = knn_indices(frame.means, config.neighbours)
            init = smooth_lift(init, frame.means, config.neighbours, neighbours)
        lift_s = time.perf_counter() - s
    result = init
    iterations = 0
    if config.mode in ("optimize", "lift+refine") and config.num_iterations > 0:
        s = time.perf_counter()
        if neighbours is None and (config.smoothing != "none" or config.smoothness > 0):
            neighbours = knn_indices(frame.means, config.neighbours)
        result, loss = optimize_latents(ops, teachers, neighbours, config, timestep_seed(config.seed, t),
                                        init=init, progress=progress)
        opt_s = time.perf_counter() - s
        iterations = config.num_iterations
    timing = TimestepTiming(t, time.perf_counter() - start, w_s, te_s, lift_s, opt_s, iterations, loss)
    return result.numpy(), timing


def _lift_timestep(frame: Any, cameras: Sequence[Any], encoder: FeatureEncoder, feats: np.ndarray,
                   layouts: Sequence[PyramidLayout], offsets: Sequence[int], config: DistillConfig, t: int,
                   start: float) -> tuple[np.ndarray, TimestepTiming]:
    """``lift`` without materializing the blending weights: one splat pass per view (the transpose
    of rendering, :func:`~fourlegs_engine.render.splat`) accumulates Σ_p w·[teacher, 1] per Gaussian.
    Equal to :func:`lift_latents` over :func:`view_operator` maps up to float32 summation order.

    Views alternate between :data:`LIFT_STREAMS` accumulators that are summed at the end; with two or
    more torch threads the streams run concurrently (the per-view work is a long series of small
    tensor ops that one thread cannot keep two cores busy with). The stream count is fixed, so the
    summation order, and the result, do not depend on the number of threads.
    """
    from ..render import splat
    if not cameras:
        raise InputError(f"timestep {t} has no {config.split} cameras to lift from", field="cameras")
    views = [(cam if config.view_scale == 1.0 else cam.scaled(config.view_scale), layout, off)
             for cam, layout, off in zip(cameras, layouts, offsets)]
    dtype = frame.means.dtype if frame.means.dtype in (torch.float32, torch.float64) else torch.float32
    width = encoder.dims[-1] + 1
    sums = [torch.zeros(frame.num_gaussians, width, dtype=dtype, device=frame.means.device)
            for _ in range(min(LIFT_STREAMS, len(views)))]
    seconds = [[0.0, 0.0] for _ in sums]  # per stream: splat (weights) s, teacher s

    def stream(k: int) -> None:
        for view, layout, off in views[k::len(sums)]:
            s = time.perf_counter()
            teacher = teacher_latents(encoder, layout, feats[off:off + layout.num_crops], config.teacher_stride,
                                      view.width, view.height)
            seconds[k][1] += time.perf_counter() - s
            s = time.perf_counter()
            values = torch.cat([teacher, torch.ones(teacher.shape[0], 1)], dim=1).view(view.height, view.width, -1)
            splat(frame.means, frame.rotations, frame.log_scales, frame.opacity_logits, view, values,
                  options=LIFT_RASTER_OPTIONS, out=sums[k])
            seconds[k][0] += time.perf_counter() - s

    threads = torch.get_num_threads()
    if threads >= 2 and len(sums) > 1:
        with torch_threads(max(1, threads // len(sums))), ThreadPoolExecutor(len(sums)) as pool:
            list(pool.map(stream, range(len(sums))))
    else:
        for k in range(len(sums)):
            stream(k)
    s = time.perf_counter()
    total = sums[0]
    for part in sums[1:]:
        total += part
    total = total.float()
    num, den = total[:, :-1], total[:, -1]
    seen = den > 1e-12
    out = torch.zeros_like(num)
    out[seen] = num[seen] / den[seen, None]
    out = l2_normalize(out)
    if config.lift_smoothing == "blur":
        out = smooth_lift(out, frame.means, config.neighbours)
    lift_s = time.perf_counter() - s
    w_s, te_s = sum(x[0] for x in seconds), sum(x[1] for x in seconds)
    timing = TimestepTiming(t, time.perf_counter() - start, w_s, te_s, lift_s, 0.0, 0, None)
    return out.numpy(), timing


# ------------------------------------------------------------------------------------- scene
def distill_scene(scene: Scene, mode: str = "lift", iterations: int | None = None,
                  timesteps: str | Sequence[int] | None = None, shard: str | tuple[int, int] | None = None, *,
                  config: DistillConfig | None = None, out_dir: str | Path | None = None,
                  overwrite: bool = False, merge: bool = True, progress: bool = False,
                  **options: Any) -> DistillResult:
    """Distil the language field of a bundle scene (features extracted, autoencoder trained).

    Args:
        scene: a bundle scene (``scene.root`` set).
        mode, iterations: see :class:`DistillConfig` (``options`` sets its other fields).
        timesteps, shard: the timesteps this worker handles ("a:b", [..], "i/n").
        out_dir: where results go (default ``<bundle>/language``: merged latents + scene.json entry);
            another directory (benchmarks) gets ``steps/`` and, when complete, ``latents.npy``.
        overwrite: discard results of another configuration instead of refusing.
        merge: merge into the (T,N,d) latents file when every timestep is finished.
    Returns:
        :class:`DistillResult` with per-timestep timings.
    """
    if config is None:
        config = DistillConfig(mode=mode, iterations=iterations, **options)
    config.check()
    if scene.root is None:
        raise InputError("the scene must be a bundle on disk", field="scene")
    root = Path(scene.root)
    features = feature_store(scene)
    ae_report_path = root / AE_REPORT
    if not ae_report_path.is_file():
        raise InputError("no trained autoencoder; run `fourlegs train-ae` first", file=ae_report_path)
    ae_report = read_json(ae_report_path)
    cfg = {"features": features.hash, "autoencoder": ae_report.get("config_hash"), **config.to_dict()}
    chash = config_hash(cfg)
    default_out = out_dir is None
    out = root / LANGUAGE_DIR if default_out else Path(out_dir)
    latents_path = out / "latents.npy"
    store = StepStore(out / "steps", "latents", cfg, scene.num_timesteps)
    if default_out:
        _finish_swap(root)
    merged_hash = _merged_hash(scene, out, default_out)
    if merged_hash is not None and merged_hash != chash:
        if not overwrite:
            raise ConfigMismatchError(
                f"{latents_path}: latents of another configuration exist (hash {merged_hash}, now {chash}); "
                "pass --overwrite to replace them, or use the same settings")
        # the old field stays in place (and readable) until the new one is merged and swapped in
        if not default_out:
            _forget_merged(out)
        merged_hash = None
    result = DistillResult(config.mode, cfg, chash, str(out), None)
    steps = select_timesteps(scene.num_timesteps, timesteps, shard)
    if merged_hash == chash:
        result.skipped = list(steps)
        result.latents = str(latents_path)
        return result
    store.open(overwrite=overwrite)
    todo = [t for t in steps if not store.is_done(t)]
    result.skipped = [t for t in steps if store.is_done(t)]
    encoder = load_encoder(root / ENCODER_FILE)
    bar = None
    if progress and todo:
        from tqdm import tqdm
        per = max(config.num_iterations, 1)
        bar = tqdm(total=len(todo) * per, desc=f"distill ({config.mode})",
                   unit="it" if config.num_iterations else "timestep")
    try:
        for t in todo:
            latents, timing = distill_timestep(scene, t, encoder, features, config,
                                               progress=bar if config.num_iterations else None)
            store.save(t, latents.astype(np.float16))
            result.timings.append(timing)
            if bar is not None and not config.num_iterations:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    if merge and not store.missing():
        merge_latents(scene, store, out, chash, config, update_bundle=default_out)
        result.latents = str(latents_path)
    return result


def _merged_hash(scene: Scene, out: Path, default_out: bool) -> str | None:
    if not (out / "latents.npy").is_file():
        return None
    if default_out:
        lang = read_json(Path(scene.root) / "scene.json").get("language") or {}
        return lang.get("config_hash")
    marker = out / "latents.json"
    return read_json(marker).get("config_hash") if marker.is_file() else None


def _forget_merged(out: Path) -> None:
    (out / "latents.json").unlink(missing_ok=True)


def merge_latents(scene: Scene, store: StepStore, out: Path, chash: str, config: DistillConfig, *,
                  update_bundle: bool) -> Path:
    """Assemble the per-timestep files into (T,N,d) float16 ``latents.npy`` atomically; then record it
    (scene.json ``language`` for the bundle's own field, ``latents.json`` elsewhere) and drop the parts."""
    from ..fileio import write_json_atomic
    first = store.load(0)
    root = Path(scene.root)
    T = scene.num_timesteps
    path = out / "latents.npy"
    info = {"encoder": _encoder_name(store, scene),
            "encoder_config": feature_store(scene).config.get("encoder_config"), "latent_dim": int(first.shape[1]),
            "canonical_phrases": list(CANONICAL_PHRASES), "decoder": DECODER_FILE, "latents": LATENTS_FILE,
            "decoder_fingerprint": weights_fingerprint(load_decoder(root / DECODER_FILE)),
            "mode": config.mode, "config_hash": chash, "config": store.config}
    next_path = out / NEXT_LATENTS_NAME
    with atomic_path(next_path) as tmp:
        arr = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.float16, shape=(T,) + tuple(first.shape))
        for t in range(T):
            arr[t] = store.load(t)
        arr.flush()
        del arr
    if update_bundle:
        _swap_in_latents(root, next_path, path, info)
    else:
        next_path.replace(path)
        write_json_atomic(out / "latents.json", {**info, "latents": str(path)})
    shutil.rmtree(store.root, ignore_errors=True)
    return path


def _finish_swap(root: Path) -> None:
    """Complete a swap that a kill interrupted after scene.json named the new field's file."""
    lang = read_json(root / "scene.json").get("language") or {}
    next_path = root / LANGUAGE_DIR / NEXT_LATENTS_NAME
    if isinstance(lang, dict) and lang.get("latents") == next_path.relative_to(root).as_posix() \
            and next_path.is_file():
        _swap_in_latents(root, next_path, root / LATENTS_FILE, dict(lang))


def _swap_in_latents(root: Path, next_path: Path, path: Path, info: dict[str, Any]) -> None:
    """Make the complete ``next_path`` the bundle's field; ``scene.json`` always names a complete file
    whose description it holds, so a reader (or a kill) at any point sees the old or the new field.

    1. scene.json -> next_path (new description), 2. ``path`` replaced by a hard link to the new file,
    3. scene.json -> ``path``, 4. ``next_path`` removed.
    """
    from ..scene.bundle import read_bundle_meta, update_bundle_meta

    arrays = dict(read_bundle_meta(root)["arrays"])
    arrays["latents"] = info["latents"] = next_path.relative_to(root).as_posix()
    update_bundle_meta(root, language=dict(info), arrays=arrays)
    with atomic_path(path) as tmp:
        tmp.unlink()
        try:
            os.link(next_path, tmp)
        except OSError:  # no hard links on this file system: a copy
            shutil.copyfile(next_path, tmp)
    arrays["latents"] = info["latents"] = LATENTS_FILE
    update_bundle_meta(root, language=info, arrays=arrays)
    next_path.unlink(missing_ok=True)


def _encoder_name(store: StepStore, scene: Scene) -> str:
    return str(feature_store(scene).config.get("encoder", "unknown"))


def check_distill(scene: Scene, out_dir: str | Path | None = None) -> dict[str, Any]:
    """Merge/check report of the distillation results (missing timesteps, merged or not)."""
    root = Path(scene.root)
    out = root / LANGUAGE_DIR if out_dir is None else Path(out_dir)
    merged = (out / "latents.npy").is_file()
    store = StepStore(out / "steps", "latents", {}, scene.num_timesteps)
    meta = store.read_manifest()
    if merged and (meta is None or not store.done()):
        lat = load_npy(out / "latents.npy", field="latents")
        return {"stage": "latents", "merged": True, "shape": list(lat.shape), "missing": [], "complete": True}
    if meta is None:
        return {"stage": "latents", "merged": False, "missing": list(range(scene.num_timesteps)),
                "missing_ranges": format_ranges(range(scene.num_timesteps)), "complete": False}
    store.config = meta["config"]
    report = store.check((scene.num_gaussians, 128))
    report["merged"] = merged
    report["missing_ranges"] = format_ranges(report["missing"])
    return report


@torch.no_grad()
def fidelity_reference(scene: Scene, t: int, encoder: FeatureEncoder, features: StepStore,
                       split: str = "train") -> list[tuple[ViewOperator, torch.Tensor]]:
    """Full-resolution rendering maps and stride-1 teacher latents of every view of timestep t that carries
    evidence."""
    frame = scene.gaussians.at(t)
    feats, layouts, offsets = load_step_features(scene, features, t)
    return [(view_operator(frame, cam), teacher_latents(encoder, layout, feats[off:off + layout.num_crops], 1))
            for cam, layout, off in zip(scene.cameras.cameras(t, split), layouts, offsets)
            if view_has_evidence(feats, off)]


@torch.no_grad()
def render_fidelity(reference: list[tuple[ViewOperator, torch.Tensor]], latents: torch.Tensor,
                    min_alpha: float = 0.5) -> dict[str, float]:
    """How well latents (N,d) reproduce the encoded teacher over the views of :func:`fidelity_reference`.

    Returns mean L1 (per channel) and mean cosine between rendered and teacher latents on pixels
    with alpha > ``min_alpha`` (0 and 0 when no pixel is covered).
    """
    l1s, coss = [], []
    for op, teacher in reference:
        rendered = op.render(latents)
        alpha = op.render(torch.ones(op.num_gaussians, 1))
        covered = alpha[:, 0] > min_alpha
        if not covered.any():
            continue
        r, e = rendered[covered], teacher[covered]
        l1s.append(float((r - e).abs().mean()))
        coss.append(float(torch.nn.functional.cosine_similarity(r, e, dim=-1, eps=1e-8).mean()))
    return {"l1": float(np.mean(l1s)) if l1s else 0.0, "cosine": float(np.mean(coss)) if coss else 0.0}
