"""Distil the teacher features into per-Gaussian 128-d latents, timestep by timestep (paper §3.1).

Modes (geometry frozen in all of them):

``lift`` (learning-free; LUDVIG-style, beyond the paper)
    Rendering is linear in the latents: pixel p of view v renders l(p) = Σ_i w_i(p) L_i with
    w_i(p) = α_i T_i. The lift is the rendering-weighted average of the encoded teacher latents
    L_i ∝ Σ_v Σ_p w_i(p) e_v(p) / Σ_v Σ_p w_i(p), L2-normalized — one rasterizer pass per view. Where
    every pixel sees a single Gaussian this is exactly the direction of the least-squares solution.
    Gaussians no training pixel sees keep a zero latent. The in-between timesteps of a ``fill="latents"``
    extraction are not lifted but filled from their lifted neighbours (:mod:`.latent_fill`).
    Computed by one splat pass per view
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
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from ..errors import ConfigMismatchError, InputError
from ..fileio import load_npy
from ..render.options import RasterOptions
from ..scene.scene import Scene
from ..threads import torch_threads
from .attention import knn_indices
from .autoencoder import AE_REPORT, ENCODER_FILE, FeatureEncoder, l2_normalize, load_encoder, read_ae_report
from .extract import feature_store, load_step_features, view_has_evidence
from .latent_fill import fill_latent_steps, latent_fill_of, lift_and_fill_work
from .latent_solvers import lift_latents, optimize_latents, smooth_lift, teacher_latents, timestep_seed
from .latents_file import LANGUAGE_DIR, finish_swap, forget_merged, merge_latents, merged_hash
from .pyramid import PyramidLayout
from .store import StepStore, config_hash, format_ranges
from .view_operator import ViewOperator, view_operator

MODES = ("optimize", "lift", "lift+refine")
#: the smallest fraction of a camera's resolution the training views are rendered at
MIN_SCALE = 0.01
SMOOTHING = ("attention", "none", "blur")
LIFT_SMOOTHING = ("none", "blur")
DEFAULT_ITERATIONS = {"optimize": 2000, "lift": 0, "lift+refine": 200}
#: lift's splat pass: 64-entry chunks are faster for the wide (d+1)-channel splat; same result up to
#: float32 summation order
LIFT_RASTER_OPTIONS = RasterOptions(chunk=64)
#: lift's view accumulators (see :func:`_lift_timestep`)
LIFT_STREAMS = 2


@dataclass
class DistillOptions:
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

    def check(self) -> "DistillOptions":
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
        if not MIN_SCALE <= self.view_scale <= 1:
            raise InputError(f"must be in [{MIN_SCALE}, 1], got {self.view_scale}", field="--view-scale")
        if self.neighbours < 1 or self.views_per_iteration < 1 or self.teacher_stride < 1:
            raise InputError("neighbours, views per iteration and teacher stride must be >= 1", field="distill")
        for name, value, high in (("--neighbours", self.neighbours, 1024), ("--teacher-stride", self.teacher_stride,
                                  64), ("--views-per-iteration", self.views_per_iteration, 4096),
                                  ("--iterations", self.iterations or 0, 10_000_000)):
            if value > high:
                raise InputError(f"must be at most {high}, got {value}", field=name)
        for name, value in (("--lr-latents", self.lr_latents), ("--lr-attention", self.lr_attention)):
            if not (0 < value <= 1 and math.isfinite(value)):
                raise InputError(f"must be in (0, 1], got {value}", field=name)
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
    #: in-between timesteps of a fill="latents" extraction filled from their lifted neighbours
    filled: list[int] = field(default_factory=list)

    @property
    def seconds_per_timestep(self) -> float | None:
        return float(np.mean([t.seconds for t in self.timings])) if self.timings else None

    def to_dict(self) -> dict[str, Any]:
        return {"mode": self.mode, "config": self.config, "config_hash": self.config_hash,
                "out_dir": self.out_dir, "latents": self.latents, "skipped": self.skipped, "filled": self.filled,
                "seconds_per_timestep": self.seconds_per_timestep,
                "timings": [dict(asdict(t), seconds_per_iteration=t.seconds_per_iteration) for t in self.timings]}


def distill_timestep(scene: Scene, t: int, encoder: FeatureEncoder, features: StepStore,
                     config: DistillOptions, progress: Any = None) -> tuple[np.ndarray, TimestepTiming]:
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
                   layouts: Sequence[PyramidLayout], offsets: Sequence[int], config: DistillOptions, t: int,
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
def distill_scene(scene: Scene, mode: str | None = None, iterations: int | None = None,
                  timesteps: str | Sequence[int] | None = None, shard: str | tuple[int, int] | None = None, *,
                  config: DistillOptions | None = None, out_dir: str | Path | None = None,
                  overwrite: bool = False, merge: bool = True, progress: bool = False,
                  **options: Any) -> DistillResult:
    """Distil the language field of a bundle scene (features extracted, autoencoder trained).

    Args:
        scene: a bundle scene (``scene.root`` set).
        mode, iterations: see :class:`DistillOptions` (default "lift"; ``options`` sets its other fields).
        config: the settings as one :class:`DistillOptions` instead (then without ``mode``, ``iterations``
            or ``options``: InputError when both are given).
        timesteps, shard: the timesteps this worker handles ("a:b", [..], "i/n").
        out_dir: where results go (default ``<bundle>/language``: merged latents + scene.json entry);
            another directory (benchmarks) gets ``steps/`` and, when complete, ``latents.npy``.
        overwrite: discard results of another configuration instead of refusing.
        merge: merge into the (T,N,d) latents file when every timestep is finished.
    Returns:
        :class:`DistillResult` with per-timestep timings.
    """
    if config is None:
        config = DistillOptions(mode=mode or "lift", iterations=iterations, **options)
    elif mode is not None or iterations is not None or options:
        given = sorted((["mode"] if mode is not None else []) + (["iterations"] if iterations is not None else [])
                       + list(options))
        raise InputError(f"give the settings either as config= or as keywords, not both (also given: "
                         f"{', '.join(given)})", field="config")
    config.check()
    if scene.root is None:
        raise InputError("the scene must be a bundle on disk", field="scene")
    root = Path(scene.root)
    features = feature_store(scene)
    ae_report_path = root / AE_REPORT
    if not ae_report_path.is_file():
        raise InputError("no trained autoencoder; run `fourlegs train-ae` first", file=ae_report_path)
    ae_report = read_ae_report(ae_report_path)
    cfg = {"features": features.hash, "autoencoder": ae_report.get("config_hash"), **config.to_dict()}
    chash = config_hash(cfg)
    default_out = out_dir is None
    out = root / LANGUAGE_DIR if default_out else Path(out_dir)
    latents_path = out / "latents.npy"
    store = StepStore(out / "steps", "latents", cfg, scene.num_timesteps)
    if default_out:
        finish_swap(root)
    existing_hash = merged_hash(scene, out, default_out)
    if existing_hash is not None and existing_hash != chash:
        if not overwrite:
            raise ConfigMismatchError(
                f"{latents_path}: latents of another configuration exist (hash {existing_hash}, now {chash}); "
                "pass --overwrite to replace them, or use the same settings")
        # the old field stays in place (and readable) until the new one is merged and swapped in
        if not default_out:
            forget_merged(out)
        existing_hash = None
    result = DistillResult(config.mode, cfg, chash, str(out), None)
    stride = latent_fill_of(features.config)  # a fill="latents" extraction: the lift fills the in-between steps
    steps, to_fill = lift_and_fill_work(scene.num_timesteps, stride, timesteps, shard)
    if existing_hash == chash:
        result.skipped = sorted(steps + to_fill)
        result.latents = str(latents_path)
        return result
    store.open(overwrite=overwrite)
    encoder = load_encoder(root / ENCODER_FILE)
    store.shape_of, store.dtype = (lambda t: (scene.num_gaussians, encoder.dims[-1])), "float16"
    todo = [t for t in steps if not store.is_done(t)]  # a damaged step file is distilled again
    result.skipped = sorted([t for t in steps if t not in todo] + [t for t in to_fill if store.is_done(t)])
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
    result.filled = fill_latent_steps(store, to_fill, stride) if stride is not None else []
    if merge and not store.missing():
        merge_latents(scene, store, out, chash, config, update_bundle=default_out)
        result.latents = str(latents_path)
    return result


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
