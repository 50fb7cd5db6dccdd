"""The spatio-temporal grounding benchmark runner (paper §4.1 metrics on synthetic scenes).

Every *method* answers every benchmark query in every evaluation view (the scene's test cameras) with
a :class:`~fourlegs_bench.baseline2d.ViewPrediction`; the runner scores it against the exact
ground truth (:mod:`.ground_truth`) with :mod:`.metrics` and reports, per method, the six metrics per
query and overall as mean ± standard deviation over the views (overall: per view, the mean over the
queries; then mean ± std over views).

Methods are registered by name with :func:`register_method` (a factory taking the
:class:`BenchmarkContext`). Built in: ``"2D features"`` (:mod:`.baseline2d`). Other packages add theirs
from one of ``METHOD_MODULES`` (imported on first use, silently skipped when absent), e.g. the 4D
method of the query package calls ``register_method("4D (4-LEGS)", factory)`` at import time.
"""
from __future__ import annotations

import importlib
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol, Sequence

import numpy as np

from fourlegs_engine.errors import InputError
from fourlegs_engine.scene.camera import Camera
from fourlegs_engine.scene.scene import Scene
from .baseline2d import Features2D, ViewPrediction
from .ground_truth import CoverageVideo, default_eval_cameras, ensure_ground_truth, scene_labels, \
    scene_queries
from .metrics import METRIC_NAMES, aggregate_views, format_percent, grounding_metrics

METHOD_MODULES = ("fourlegs_bench.method4d",)


@dataclass
class BenchmarkContext:
    """What a method may use. Ground truth is for scoring only; methods must not read it.

    Attributes:
        scene: the synthetic scene (bundle on disk when ``scene.root`` is set).
        queries: query texts in order.
        cameras: the evaluation views (test cameras).
        text_encoder, video_encoder: the (simulated) video-text model of this benchmark.
        videos: per evaluation camera, its lazily rendered label-coverage frames (shared by methods).
        progress: show progress bars.
        seed: the benchmark seed (scene and encoder corruptions).
        options: method settings from the command line (e.g. ``pixel_stride`` of the 2D baseline).
    """

    scene: Scene
    queries: list[str]
    cameras: list[Camera]
    text_encoder: Any
    video_encoder: Any
    videos: dict[str, CoverageVideo]
    progress: bool = False
    seed: int = 0
    options: dict[str, Any] = field(default_factory=dict)


class GroundingMethod(Protocol):
    name: str

    def predict_view(self, context: BenchmarkContext, camera: Camera) -> dict[str, ViewPrediction]:
        """Predictions of every query in ``camera``'s view."""
        ...


_METHODS: dict[str, Callable[[BenchmarkContext], GroundingMethod]] = {}
_modules_loaded = False


def register_method(name: str, factory: Callable[[BenchmarkContext], GroundingMethod], *,
                    replace: bool = False) -> None:
    """Register a grounding method under ``name`` (``replace=True`` to override)."""
    if name in _METHODS and not replace:
        raise ValueError(f"a grounding method named {name!r} is already registered")
    _METHODS[name] = factory


def method_names() -> list[str]:
    """Registered method names (built-in first, then in registration order)."""
    _load_method_modules()
    return list(_METHODS)


def _load_method_modules() -> None:
    global _modules_loaded
    if _modules_loaded:
        return
    _modules_loaded = True
    for name in METHOD_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name is not None and name.startswith(exc.name):
                continue
            raise
        if hasattr(module, "register"):
            module.register()


class _Features2DMethod:
    name = "2D features"

    def __init__(self, context: BenchmarkContext, pixel_stride: int | None = None):
        stride = pixel_stride if pixel_stride is not None else int(context.options.get("pixel_stride", 2))
        self.impl = Features2D(context.video_encoder, pixel_stride=stride)

    def predict_view(self, context: BenchmarkContext, camera: Camera) -> dict[str, ViewPrediction]:
        bar = None
        if context.progress:
            from tqdm import tqdm
            bar = tqdm(total=len(context.videos[camera.name]), desc=f"2D features {camera.name}",
                       unit="frame", leave=False)
        try:
            return self.impl.predict_view(context.videos[camera.name], camera, context.queries,
                                          context.text_encoder,
                                          progress=(lambda t: bar.update(1)) if bar is not None else None)
        finally:
            if bar is not None:
                bar.close()


register_method("2D features", _Features2DMethod)


# ------------------------------------------------------------------------------------- scoring
def score_view(pred: ViewPrediction, gt_frames: np.ndarray, gt_masks: Any, gt_boxes: np.ndarray
               ) -> dict[str, float]:
    """Six metrics of one query in one view; relevancy maps and boxes are read only on S_i frames."""
    frames = np.asarray(pred.frames, dtype=bool)
    T = gt_frames.shape[0]
    if frames.shape != (T,):
        raise InputError(f"method returned {frames.shape} frames, expected ({T},)", field="frames")
    inter = np.flatnonzero(frames & gt_frames)
    maps = {int(t): np.nan_to_num(np.asarray(pred.relevancy_map(int(t)), dtype=np.float64)) for t in inter}
    boxes = np.full((T, 4), np.nan)
    for t in inter:
        boxes[t] = pred.box(int(t))
    scores = np.nan_to_num(np.asarray(pred.scores, dtype=np.float64))
    return grounding_metrics(frames, gt_frames, scores=scores, relevancy_maps=maps, gt_masks=gt_masks,
                             pred_boxes=boxes, gt_boxes=gt_boxes)


def _summary(per_view: dict[str, dict[str, dict[str, float]]], queries: Sequence[str]) -> dict[str, Any]:
    """{"overall": {metric: {mean, std}}, "per_query": {q: {metric: {mean, std}}}} from per-view scores."""
    def pack(agg: dict[str, tuple[float, float]]) -> dict[str, dict[str, float]]:
        return {k: {"mean": float(m), "std": float(s)} for k, (m, s) in agg.items()}

    per_query = {q: pack(aggregate_views([per_view[v][q] for v in per_view])) for q in queries}
    overall_views = [{k: float(np.mean([per_view[v][q][k] for q in queries])) for k in METRIC_NAMES}
                     for v in per_view]
    return {"overall": pack(aggregate_views(overall_views)), "per_query": per_query}


def build_context(scene: Scene, *, seed: int = 0, progress: bool = False,
                  views: Sequence[str] | None = None, options: dict[str, Any] | None = None) -> BenchmarkContext:
    from fourlegs_engine.demo.simulated import SimulatedTextEncoder, create_encoder

    labels = scene_labels(scene)
    queries = list(scene_queries(scene))
    cams = default_eval_cameras(scene)
    if views:
        by_name = {c.name: c for c in scene.cameras.cameras(0, "all")}
        missing = [v for v in views if v not in by_name]
        if missing:
            raise InputError(f"no camera named {missing} (cameras: {', '.join(by_name)})", field="views")
        cams = [by_name[v] for v in views]
    frame_bytes = len(labels) * cams[0].width * cams[0].height * 4 if cams else 0
    window = scene.num_timesteps if frame_bytes * scene.num_timesteps <= 400 * 2 ** 20 else 12
    videos = {c.name: CoverageVideo(scene, c, window=window) for c in cams}
    return BenchmarkContext(scene=scene, queries=queries, cameras=cams, text_encoder=SimulatedTextEncoder(),
                            video_encoder=create_encoder(scene=scene, seed=seed), videos=videos,
                            progress=progress, seed=seed, options=dict(options or {}))


def run_grounding_benchmark(scene: Scene, methods: Sequence[str] | None = None, *, seed: int = 0,
                            progress: bool = False, views: Sequence[str] | None = None,
                            options: dict[str, Any] | None = None) -> dict[str, Any]:
    """Score every (or the named) registered method on ``scene``; returns the JSON-ready results.

    ``views``: camera names to evaluate (default: the test cameras); ``options``: method settings.
    """
    available = method_names()
    names = list(methods) if methods else available
    unknown = [m for m in names if m not in _METHODS]
    if unknown:
        raise InputError(f"unknown method(s) {unknown} (registered: {', '.join(available)})", field="methods")
    ctx = build_context(scene, seed=seed, progress=progress, views=views, options=options)
    start = time.perf_counter()
    gt = ensure_ground_truth(scene, ctx.cameras, progress=progress, videos=ctx.videos)
    gt_seconds = time.perf_counter() - start
    results: dict[str, Any] = {}
    for name in names:
        start = time.perf_counter()
        method = _METHODS[name](ctx)
        per_view: dict[str, dict[str, dict[str, float]]] = {}
        for cam in ctx.cameras:
            preds = method.predict_view(ctx, cam)
            per_view[cam.name] = {}
            for qi, q in enumerate(ctx.queries):
                if q not in preds:
                    raise InputError(f"method {name!r} gave no prediction for query {q!r}", field="methods")
                per_view[cam.name][q] = score_view(preds[q], gt.frames[q], gt.masks[cam.name][:, qi],
                                                   gt.boxes[cam.name][:, qi])
        summary = _summary(per_view, ctx.queries)
        results[name] = {**summary["overall"], "per_query": summary["per_query"], "per_view": per_view,
                         "seconds": time.perf_counter() - start}
    meta = scene.metadata.get("generator", {}) if scene.metadata else {}
    return {
        "benchmark": "grounding",
        "scene": {"name": scene.name, "size": meta.get("size"), "seed": meta.get("seed"),
                  "num_gaussians": scene.num_gaussians, "num_timesteps": scene.num_timesteps,
                  "views": [c.name for c in ctx.cameras],
                  "image_size": [ctx.cameras[0].width, ctx.cameras[0].height] if ctx.cameras else None},
        "queries": {q: gt.labels[q] for q in ctx.queries},
        "ground_truth": {"visibility_threshold": gt.threshold, "seconds": gt_seconds,
                         "segments": {q: [list(s) for s in gt.segments(q)] for q in ctx.queries}},
        "encoder": ctx.video_encoder.config(),
        "options": ctx.options,
        "metrics": list(METRIC_NAMES),
        "methods": results,
    }


def markdown_tables(results: dict[str, Any]) -> str:
    """Paper-style Markdown: one summary table of all methods, then one per method and query."""
    cols = list(METRIC_NAMES)
    lines = [f"Grounding benchmark on {results['scene']['name']} "
             f"({len(results['scene']['views'])} views, {results['scene']['num_timesteps']} timesteps); "
             "values in %, ± = std over views", "",
             "| method | " + " | ".join(cols) + " | seconds |",
             "|---" * (len(cols) + 2) + "|"]
    for name, r in results["methods"].items():
        lines.append(f"| {name} | " + " | ".join(format_percent(r[c]["mean"], r[c]["std"]) for c in cols)
                     + f" | {r['seconds']:.1f} |")
    for name, r in results["methods"].items():
        lines += ["", f"**{name}** per query", "", "| query | " + " | ".join(cols) + " |",
                  "|---" * (len(cols) + 1) + "|"]
        for q, m in r["per_query"].items():
            lines.append(f"| {q} | " + " | ".join(format_percent(m[c]["mean"], m[c]["std"]) for c in cols) + " |")
        lines.append("| **overall** | " + " | ".join(format_percent(r[c]["mean"], r[c]["std"]) for c in cols)
                     + " |")
    return "\n".join(lines)


def run_grounding_benchmark_cli(args: Any) -> int:
    """``fourlegs bench grounding``."""
    from fourlegs_engine.fileio import write_json_atomic
    from fourlegs_engine.errors import OutputExistsError
    from fourlegs_engine.scene.bundle import load_bundle
    from fourlegs_engine.demo.synthetic import ensure_demo_bundle

    for out in (args.json, getattr(args, "plot", None)):
        if out and Path(out).exists() and not args.overwrite:
            raise OutputExistsError(out)
    threads = getattr(args, "threads", None)
    if threads is not None:
        if threads < 1:
            raise InputError(f"--threads must be >= 1, got {threads}", field="--threads")
        import torch
        torch.set_num_threads(threads)
    start = time.perf_counter()
    path = Path(args.bundle) if args.bundle else ensure_demo_bundle(args.scene, args.seed)
    scene = load_bundle(path)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()] if args.methods else None
    views = [v.strip() for v in args.views.split(",") if v.strip()] if args.views else None
    strides = parse_strides(args.pixel_stride)
    if len(strides) > 1:  # the speed/accuracy knob of the 2D baseline: one variant per stride
        variants = []
        for stride in strides:
            name = f"2D features (pixel stride {stride})"
            register_method(name, lambda ctx, s=stride: _Features2DMethod(ctx, s), replace=True)
            variants.append(name)
        methods = [m for m in (methods or method_names()) if m != "2D features" and not
                   m.startswith("2D features (")] + variants
    results = run_grounding_benchmark(scene, methods, seed=args.seed, progress=True, views=views,
                                      options={"pixel_stride": strides[0]})
    results["scene"]["path"] = str(path)
    results["total_seconds"] = time.perf_counter() - start
    results["cpu_seconds"] = time.process_time()
    import torch
    results["torch_threads"] = torch.get_num_threads()
    print(markdown_tables(results))
    print(f"\ntotal {results['total_seconds']:.1f} s (ground truth {results['ground_truth']['seconds']:.1f} s)")
    if args.json:
        write_json_atomic(args.json, results)
        print(f"wrote {args.json}")
    if args.plot:
        plot_speed_accuracy(results, args.plot)
        print(f"wrote {args.plot}")
    return 0


def parse_strides(text: str | int) -> list[int]:
    """``"1,2,4"`` -> [1, 2, 4]; every stride must be a positive integer."""
    try:
        strides = [int(x) for x in str(text).split(",") if x.strip()]
    except ValueError:
        raise InputError(f"expected comma-separated integers, got {text!r}", field="--pixel-stride") from None
    if not strides or min(strides) < 1:
        raise InputError(f"strides must be >= 1, got {text!r}", field="--pixel-stride")
    return strides


def plot_speed_accuracy(results: dict[str, Any], path: str | Path) -> None:
    """Seconds against vAP and tIoU (± std over views) of every method of a benchmark run."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fourlegs_engine.fileio import atomic_path

    names = list(results["methods"])
    secs = [results["methods"][n]["seconds"] for n in names]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, metric in zip(axes, ("vAP", "tIoU")):
        for n, sec in zip(names, secs):
            m = results["methods"][n][metric]
            ax.errorbar([sec], [100 * m["mean"]], yerr=[100 * m["std"]], fmt="o", capsize=3, label=n)
        ax.set_xlabel("seconds (all views, all queries)")
        ax.set_ylabel(f"{metric} (%)")
        ax.set_title(f"{metric} vs time on {results['scene']['name']}")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)
