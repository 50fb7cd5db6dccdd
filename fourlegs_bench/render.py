"""``fourlegs bench render``: speed, memory and accuracy of the rasterizer, as JSON, Markdown and a plot.

Three parts, all on the documented benchmark scene (:mod:`.render_scene`):

1. **speed** — per N and output, the median ms/frame and peak memory of the forward pass and of
   forward+backward (rgb: gradients for colours and geometry; features: for the features, geometry
   frozen, as in distillation; depth: for the means) at 640×360 with 128 feature channels.
2. **baselines** — at a small N (and a smaller image so the brute force stays quick), the float64
   brute-force oracle, the straightforward dense-tile implementation (:mod:`.reference`) and the
   fast rasterizer side by side: time and speed ratio.
3. **knobs** — the fast rasterizer's accuracy knobs (tile size, 3σ vs opacity-aware extent, float32
   vs float16 features) at that small N: time next to max/mean error against the oracle.
4. **floor** — per N, the frame's pixel–Gaussian pairs (in boxes / footprints / evaluated / blended),
   the measured peak of one core and the floors they imply (:mod:`.render_floor`), next to each
   kernel's forward CPU ms: the gap to the floor as a number.
5. **busy** (``--busy``) — a fit-like step alone and beside a competing busy process, under this
   project's OpenMP policy and OpenMP's default (:mod:`.render_busy`).

On the CPU every speed case runs once per fused-kernel generation (``--kernels``, default v2 and v1:
``RasterOptions(kernel=...)``), so the previous kernel's row sits next to the current one.

Every record carries at least ``n, output, mode, device, backend, ms_median, peak_mb``.
"""
from __future__ import annotations

import argparse
import ctypes
import os
import shlex
import sys
import statistics
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import torch

from .render_scene import BenchScene, make_bench_scene

OUTPUT_CHOICES = ("rgb", "features", "depth")


@dataclass
class RenderBenchOptions:
    sizes: tuple[int, ...] = (10_000, 100_000, 300_000)
    outputs: tuple[str, ...] = OUTPUT_CHOICES
    device: str = "cpu"
    backends: tuple[str, ...] = ("torch",)
    repeats: int = 3
    channels: int = 128
    width: int = 640
    height: int = 360
    small_n: int = 2000
    small_width: int = 320
    small_height: int = 180
    baselines: bool = True
    knobs: bool = True
    kernels: tuple[str, ...] = ("v2", "v1")
    floor: bool = True
    busy: bool = False
    busy_n: int = 100_000
    busy_threads: int = 2
    seed: int = 0
    extra: dict = field(default_factory=dict)


# ----------------------------------------------------------------------------------------- memory
class PeakMemory:
    """Peak memory of a block in MB: CUDA allocator peak on CUDA; on CPU the peak resident set size
    above the level at entry, sampled every 2 ms (``total_mb``: the whole process's peak RSS)."""

    def __init__(self, device: str):
        self.device = device
        self.peak_mb = 0.0
        self.total_mb = 0.0

    def __enter__(self):
        _release_memory()
        if self.device == "cuda":
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
            self._base = torch.cuda.memory_allocated()
        else:
            self._base = _rss_bytes()
            self._peak = self._base
            self._stop = threading.Event()
            self._thread = threading.Thread(target=self._sample, daemon=True)
            self._thread.start()
        return self

    def _sample(self) -> None:
        while not self._stop.is_set():
            self._peak = max(self._peak, _rss_bytes())
            time.sleep(0.002)

    def __exit__(self, *exc):
        if self.device == "cuda":
            torch.cuda.synchronize()
            peak = torch.cuda.max_memory_allocated()
            self.peak_mb = (peak - self._base) / 2**20
            self.total_mb = peak / 2**20
        else:
            self._stop.set()
            self._thread.join()
            self._peak = max(self._peak, _rss_bytes())
            self.peak_mb = (self._peak - self._base) / 2**20
            self.total_mb = self._peak / 2**20
        return False


def _rss_bytes() -> int:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except OSError:  # not Linux: fall back to the lifetime peak
        import resource
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _release_memory() -> None:
    """Hand freed heap pages back to the OS so the next case's RSS baseline is low (tensors are freed
    by reference counting; no gc pass needed)."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except OSError:
        pass


# ------------------------------------------------------------------------------------------ timing
def _sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


#: process CPU time of the last :func:`time_case` (median ms): on a shared, oversubscribed machine this
#: tracks the work done far better than wall time (with one thread it approximates a quiet machine)
LAST_CPU_MS: list[float] = [0.0]


def time_case(fn: Callable[[], object], device: str, repeats: int) -> tuple[float, float, float]:
    """Median wall ms over ``repeats`` runs after one warm-up; peak MB (above entry) and total peak MB.
    The median process CPU ms is left in ``LAST_CPU_MS[0]``."""
    fn()
    _sync(device)
    times, cpu = [], []
    with PeakMemory(device) as mem:
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            _sync(device)
            times.append((time.perf_counter() - t0) * 1000)
            cpu.append((time.process_time() - c0) * 1000)
    LAST_CPU_MS[0] = statistics.median(cpu)
    return statistics.median(times), mem.peak_mb, mem.total_mb


def _render_fn(scene: BenchScene, output: str, mode: str, backend: str, options=None,
               features: torch.Tensor | None = None) -> Callable[[], object]:
    from fourlegs_engine.render import rasterize

    feats = scene.features if features is None else features

    def run():
        geom = [scene.means, scene.rotations, scene.log_scales, scene.opacity_logits]
        colors, f = scene.colors, feats
        if mode == "backward":
            if output == "rgb":
                geom = [g.detach().requires_grad_() for g in geom]
                colors = colors.detach().requires_grad_()
                leaves = geom + [colors]
            elif output == "features":
                f = f.detach().requires_grad_()
                leaves = [f]
            else:
                geom[0] = geom[0].detach().requires_grad_()
                leaves = [geom[0]]
        out = rasterize(*geom, scene.camera, colors=colors, features=f, outputs=(output,), options=options,
                        backend=backend)
        if mode == "backward":
            torch.autograd.grad(out[output].sum(), leaves)
        return out
    return run


# ------------------------------------------------------------------------------------------- parts
def _kernels(cfg: RenderBenchOptions, backend: str) -> tuple[str | None, ...]:
    """The fused-kernel generations a backend's cases run with (only the torch backend on the CPU has them)."""
    return cfg.kernels if backend == "torch" and cfg.device == "cpu" else (None,)


def speed_records(cfg: RenderBenchOptions, progress=None) -> list[dict]:
    from fourlegs_engine.render import RasterOptions

    records = []
    for n in cfg.sizes:
        scene = make_bench_scene(n, feature_dim=cfg.channels, seed=cfg.seed, device=cfg.device,
                                 width=cfg.width, height=cfg.height)
        for backend in cfg.backends:
            for output in cfg.outputs:
                for mode in ("forward", "backward"):
                    for kernel in _kernels(cfg, backend):
                        options = RasterOptions(kernel=kernel) if kernel else None
                        ms, peak, total = time_case(_render_fn(scene, output, mode, backend, options=options),
                                                    cfg.device, cfg.repeats)
                        records.append({"part": "speed", "n": n, "output": output, "mode": mode, "device": cfg.device,
                                        "backend": backend, "kernel": kernel, "ms_median": round(ms, 2),
                                        "cpu_ms_median": round(LAST_CPU_MS[0], 2), "peak_mb": round(peak, 1),
                                        "process_peak_mb": round(total, 1), "width": cfg.width, "height": cfg.height,
                                        "channels": cfg.channels if output == "features" else None})
                        if progress:
                            progress(records[-1])
        del scene
        _release_memory()
    return records


def floor_records(cfg: RenderBenchOptions, speed: list[dict], progress=None) -> list[dict]:
    """Per N: the frame's pair counts, the measured peak and the floors of its rgb and features forward
    passes, next to each kernel's forward CPU ms (one record per N × output × kernel)."""
    from .render_floor import floor_ms, frame_work, measure_peak

    peak = measure_peak()
    records = []
    for n in cfg.sizes:
        scene = make_bench_scene(n, feature_dim=cfg.channels, seed=cfg.seed, device="cpu", width=cfg.width,
                                 height=cfg.height)
        work = frame_work(scene)
        for output in ("rgb", "features"):
            channels = 3 if output == "rgb" else cfg.channels
            flop_floor, exp_floor = floor_ms(work, peak, channels)
            for r in speed:
                if r["n"] == n and r["output"] == output and r["mode"] == "forward" and r["device"] == "cpu":
                    records.append({
                        "part": "floor", "n": n, "output": output, "mode": "forward", "device": "cpu",
                        "backend": r["backend"], "kernel": r.get("kernel"), "ms_median": r["ms_median"],
                        "cpu_ms_median": r["cpu_ms_median"], "peak_mb": r["peak_mb"], "channels": channels,
                        **work, "peak_gflops": round(peak["gflops"], 1), "peak_gexp_per_s": round(peak["gexp_per_s"], 3),
                        "floor_flop_ms": flop_floor, "floor_exp_ms": exp_floor,
                        "x_flop_floor": round(r["cpu_ms_median"] / max(flop_floor, 1e-9), 1),
                        "x_exp_floor": round(r["cpu_ms_median"] / max(exp_floor, 1e-9), 1)})
                    if progress:
                        progress(records[-1])
        del scene
    return records


def _errors(out: torch.Tensor, ref: torch.Tensor) -> tuple[float, float]:
    d = (out.detach().double() - ref.detach().double()).abs()
    return float(d.max()), float(d.mean())


def small_scene(cfg: RenderBenchOptions) -> BenchScene:
    return make_bench_scene(cfg.small_n, feature_dim=cfg.channels, seed=cfg.seed, device=cfg.device,
                            width=cfg.small_width, height=cfg.small_height)


def oracle_outputs(scene: BenchScene) -> dict[str, torch.Tensor]:
    """float64 brute force (every pixel × every Gaussian) for rgb and features."""
    from fourlegs_engine.render.reference import rasterize_reference
    s64 = [t.double() for t in (scene.means, scene.rotations, scene.log_scales, scene.opacity_logits)]
    with torch.no_grad():
        return rasterize_reference(*s64, scene.camera, colors=scene.colors.double(),
                                   features=scene.features.double(), outputs=("rgb", "features"), tile_size=None)


def baseline_records(cfg: RenderBenchOptions, scene: BenchScene, progress=None) -> list[dict]:
    """Oracle vs dense-tile vs fast, forward and forward+backward, at the small N."""
    from fourlegs_engine.render.reference import rasterize_reference

    def ref_fn(dtype, tile_size, output, mode):
        def run():
            geom = [t.to(dtype) for t in (scene.means, scene.rotations, scene.log_scales, scene.opacity_logits)]
            colors, feats = scene.colors.to(dtype), scene.features.to(dtype)
            leaf = None
            if mode == "backward":
                leaf = (colors if output == "rgb" else feats).requires_grad_()
            out = rasterize_reference(*geom, scene.camera, colors=colors, features=feats, outputs=(output,),
                                      tile_size=tile_size)
            if leaf is not None:
                torch.autograd.grad(out[output].sum(), [leaf])
        return run

    records = []
    for output in ("rgb", "features"):
        for mode in ("forward", "backward"):
            row = {}
            for impl, fn in (("oracle_float64", ref_fn(torch.float64, None, output, mode)),
                             ("dense_tile", ref_fn(torch.float32, 16, output, mode)),
                             ("fast", _render_fn(scene, output, "backward" if mode == "backward" and output == "rgb"
                                                 else mode, "torch"))):
                if impl == "fast" and mode == "backward" and output == "rgb":
                    fn = _colors_only_backward(scene)
                ms, peak, total = time_case(fn, cfg.device, max(1, min(cfg.repeats, 3)))
                row[impl] = ms
                records.append({"part": "baseline", "impl": impl, "n": scene.n, "output": output, "mode": mode,
                                "device": cfg.device, "backend": "torch", "ms_median": round(ms, 2),
                                "cpu_ms_median": round(LAST_CPU_MS[0], 2), "peak_mb": round(peak, 1),
                                "width": cfg.small_width, "height": cfg.small_height})
                if progress:
                    progress(records[-1])
            for r in records[-3:]:
                r["speedup_of_fast"] = round(r["ms_median"] / max(row["fast"], 1e-9), 2)
    return records


def _colors_only_backward(scene: BenchScene):
    """Fast path with the same gradient request as the baselines (colours only)."""
    from fourlegs_engine.render import rasterize

    def run():
        c = scene.colors.detach().requires_grad_()
        out = rasterize(scene.means, scene.rotations, scene.log_scales, scene.opacity_logits, scene.camera,
                        colors=c, outputs=("rgb",))
        torch.autograd.grad(out["rgb"].sum(), [c])
    return run


def knob_records(cfg: RenderBenchOptions, scene: BenchScene, oracle: dict, progress=None) -> list[dict]:
    """Accuracy knobs: time next to max/mean error against the float64 oracle."""
    from fourlegs_engine.render import RasterOptions, rasterize

    cases = [("tile_size", str(ts), RasterOptions(tile_size=ts), "float32") for ts in (2, 4, 8, 16)]
    cases += [("extent", ext, RasterOptions(extent=ext), "float32") for ext in ("opacity", "3sigma")]
    cases += [("feature_dtype", dt, RasterOptions(), dt) for dt in ("float32", "float16")]
    records = []
    for knob, value, opts, fdtype in cases:
        for output in (("features",) if knob == "feature_dtype" else ("rgb", "features")):
            feats = scene.features.to(getattr(torch, fdtype))
            fn = _render_fn(scene, output, "forward", "torch", options=opts, features=feats)
            ms, peak, _ = time_case(fn, cfg.device, cfg.repeats)
            out = rasterize(scene.means, scene.rotations, scene.log_scales, scene.opacity_logits, scene.camera,
                            colors=scene.colors, features=feats, outputs=(output,), options=opts)[output]
            err_max, err_mean = _errors(out, oracle[output])
            records.append({"part": "knob", "knob": knob, "value": value, "n": scene.n, "output": output,
                            "mode": "forward", "device": cfg.device, "backend": "torch", "ms_median": round(ms, 2),
                            "cpu_ms_median": round(LAST_CPU_MS[0], 2),
                            "peak_mb": round(peak, 1), "max_abs_error": err_max, "mean_abs_error": err_mean,
                            "width": cfg.small_width, "height": cfg.small_height})
            if progress:
                progress(records[-1])
    return records


def run_bench(cfg: RenderBenchOptions, progress=None) -> list[dict]:
    records = speed_records(cfg, progress)
    if cfg.floor and cfg.device == "cpu":
        records += floor_records(cfg, records, progress)
    if cfg.busy and cfg.device == "cpu":
        from .render_busy import busy_records
        records += busy_records(cfg.busy_n, cfg.kernels, cfg.busy_threads, max(1, cfg.repeats), progress)
    if cfg.baselines or cfg.knobs:
        scene = small_scene(cfg)
        if cfg.baselines:
            records += baseline_records(cfg, scene, progress)
        if cfg.knobs:
            records += knob_records(cfg, scene, oracle_outputs(scene), progress)
    return records


# ------------------------------------------------------------------------------------------ report
def markdown_report(records: list[dict], command: str, env: dict) -> str:
    lines = [f"Command: `{command}`", "", f"Machine: {env.get('machine', '')}; torch {env.get('torch', '')}, "
             f"{env.get('threads', '?')} threads, OpenMP wait policy {env.get('omp_wait_policy', '?')}, freed memory "
             f"{'kept (glibc thresholds raised)' if env.get('freed_memory_kept') else 'returned to the system'}", ""]
    speed = [r for r in records if r["part"] == "speed"]
    if speed:
        res = f"{speed[0]['width']}×{speed[0]['height']}"
        channels = next((r["channels"] for r in speed if r.get("channels")), 128)
        lines += [f"**Speed** ({res}, features = {channels} channels; backward = forward+backward)",
                  "", "| N | output | mode | backend | kernel | device | ms/frame (median) | CPU ms/frame "
                  "| × this kernel's time | peak MB (above baseline) | process peak MB |",
                  "|---:|---|---|---|---|---|---:|---:|---:|---:|---:|"]
        for r in speed:
            first = next(q for q in speed if all(q[k] == r[k] for k in ("n", "output", "mode", "backend", "device")))
            ratio = r["cpu_ms_median"] / max(first["cpu_ms_median"], 1e-9)
            lines.append(f"| {r['n']:,} | {r['output']} | {r['mode']} | {r['backend']} | {r.get('kernel') or '-'} | "
                         f"{r['device']} | {r['ms_median']:.1f} | {r['cpu_ms_median']:.1f} | {ratio:.2f} | "
                         f"{r['peak_mb']:.0f} | {r['process_peak_mb']:.0f} |")
        lines += ["", "× this kernel's time: CPU ms over the first row's of the same case (the current kernel)", ""]
    floor = [r for r in records if r["part"] == "floor"]
    if floor:
        f0 = floor[0]
        lines += [f"**Work and floor** (forward; peak of one core measured now: {f0['peak_gflops']:.1f} GFLOP/s fp32 "
                  f"matmul, {f0['peak_gexp_per_s']:.3f} G exp/s; floors from the pair counts, see "
                  "fourlegs_bench/render_floor.py)", "",
                  "| N | output | kernel | visible | pairs in boxes | in footprints | evaluated (v2) | blended "
                  "| tile pairs (v2 / boxes) | flop floor ms | exp floor ms | CPU ms | × flop floor | × exp floor |",
                  "|---:|---|---|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|"]
        for r in floor:
            lines.append(f"| {r['n']:,} | {r['output']} | {r.get('kernel') or '-'} | {r['visible']:,} | "
                         f"{r['in_boxes']:,} | {r['in_footprints']:,} | {r['evaluated']:,} | {r['blended']:,} | "
                         f"{r['tile_pairs']:,} / {r['tile_pairs_in_boxes']:,} | {r['floor_flop_ms']:.2f} | "
                         f"{r['floor_exp_ms']:.2f} | {r['cpu_ms_median']:.1f} | {r['x_flop_floor']:.0f} | "
                         f"{r['x_exp_floor']:.0f} |")
        lines.append("")
    busy = [r for r in records if r["part"] == "busy"]
    if busy:
        lines += [f"**Beside a busy process** (rgb forward+backward with every gradient, N = {busy[0]['n']:,}, "
                  f"{busy[0]['step_threads']} torch threads and kernel workers, each case a fresh process)", "",
                  "| kernel | OpenMP policy | competing busy process | wall ms (median) | CPU ms | × alone |",
                  "|---|---|---|---:|---:|---:|"]
        for r in busy:
            lines.append(f"| {r['kernel']} | {r['policy']} ({r['omp_wait_policy']}) | "
                         f"{'yes' if r['competitor'] else 'no'} | {r['ms_median']:.1f} | {r['cpu_ms_median']:.1f} | "
                         f"{r['x_alone']:.2f} |")
        lines.append("")
    base = [r for r in records if r["part"] == "baseline"]
    if base:
        lines += [f"**Baselines** (N = {base[0]['n']:,}, {base[0]['width']}×{base[0]['height']}; backward = "
                  "forward+backward for the colours/features)", "",
                  "| output | mode | implementation | ms (median) | × the fast path's time | peak MB |",
                  "|---|---|---|---:|---:|---:|"]
        for r in base:
            lines.append(f"| {r['output']} | {r['mode']} | {r['impl']} | {r['ms_median']:.1f} | "
                         f"{r['speedup_of_fast']:.1f} | {r['peak_mb']:.0f} |")
        lines.append("")
    knobs = [r for r in records if r["part"] == "knob"]
    if knobs:
        lines += [f"**Accuracy knobs** (N = {knobs[0]['n']:,}, {knobs[0]['width']}×{knobs[0]['height']}, forward, "
                  "error against the float64 oracle)", "",
                  "| knob | value | output | ms (median) | max abs error | mean abs error |",
                  "|---|---|---|---:|---:|---:|"]
        for r in knobs:
            lines.append(f"| {r['knob']} | {r['value']} | {r['output']} | {r['ms_median']:.1f} | "
                         f"{r['max_abs_error']:.2e} | {r['mean_abs_error']:.2e} |")
        lines.append("")
    return "\n".join(lines)


def plot_knobs(records: list[dict], path) -> None:
    """Time vs max error of every knob setting (log-log), one marker per output."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fourlegs_engine.fileio import atomic_path

    knobs = [r for r in records if r["part"] == "knob"]
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for output, marker in (("rgb", "o"), ("features", "s")):
        rs = [r for r in knobs if r["output"] == output]
        ax.scatter([max(r["max_abs_error"], 1e-12) for r in rs], [r["ms_median"] for r in rs], marker=marker,
                   label=output)
        for r in rs:
            ax.annotate(f"{r['knob']}={r['value']}", (max(r["max_abs_error"], 1e-12), r["ms_median"]),
                        fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_xlabel("max abs error vs float64 oracle")
    ax.set_ylabel("ms per frame (median)")
    ax.set_title("Rasterizer accuracy knobs")
    ax.legend()
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=120)
    plt.close(fig)


def environment() -> dict:
    import platform
    from fourlegs_engine.memory import freed_memory_kept
    from fourlegs_engine.threads import openmp_wait_policy
    return {"machine": f"{platform.machine()} {os.cpu_count()} CPUs", "torch": torch.__version__,
            "threads": torch.get_num_threads(), "python": platform.python_version(),
            "omp_wait_policy": openmp_wait_policy(), "freed_memory_kept": freed_memory_kept()}


def _ints(text: str, name: str) -> tuple[int, ...]:
    from fourlegs_engine.errors import InputError
    try:
        values = tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise InputError(f"expected comma-separated integers, got {text!r}", field=name) from None
    if not values or any(v < 0 for v in values):
        raise InputError(f"expected non-negative integers, got {text!r}", field=name)
    return values


def _resolution(text: str, name: str) -> tuple[int, int]:
    from fourlegs_engine.errors import InputError
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"expected WxH, got {text!r}", field=name) from None
    if w <= 0 or h <= 0:
        raise InputError(f"expected a positive size, got {text!r}", field=name)
    return w, h


def run_render_cli(args: argparse.Namespace) -> int:
    """``fourlegs bench render``."""
    from pathlib import Path

    import torch
    from tqdm import tqdm

    from fourlegs_engine.errors import InputError, OutputExistsError
    from fourlegs_engine.fileio import atomic_path, write_json_atomic
    from fourlegs_engine.render.backends import gsplat_available
    from fourlegs_engine.render.options import KERNELS

    outputs = tuple(o.strip() for o in args.outputs.split(",") if o.strip())
    bad = [o for o in outputs if o not in OUTPUT_CHOICES]
    if bad or not outputs:
        raise InputError(f"unknown output(s) {bad}; choose from {OUTPUT_CHOICES}", field="--outputs")
    if args.device == "cuda" and not torch.cuda.is_available():
        raise InputError("CUDA is not available on this machine", field="--device")
    backend = args.backend or ("all" if args.device == "cuda" and gsplat_available() else "torch")
    backends = ("torch", "gsplat") if backend == "all" else (backend,)
    if "gsplat" in backends and (args.device != "cuda" or not gsplat_available()):
        raise InputError("the gsplat backend needs --device cuda and gsplat installed", field="--backend")
    for path in (args.json, args.markdown, args.plot):
        if path and Path(path).exists() and not args.overwrite:
            raise OutputExistsError(path)
    if args.repeats < 1:
        raise InputError("must be >= 1", field="--repeats")
    w, h = _resolution(args.resolution, "--resolution")
    sw, sh = _resolution(args.small_resolution, "--small-resolution")
    kernels = tuple(k.strip() for k in args.kernels.split(",") if k.strip())
    if not kernels or any(k not in KERNELS for k in kernels):
        raise InputError(f"expected kernels from {KERNELS}, got {args.kernels!r}", field="--kernels")
    cfg = RenderBenchOptions(sizes=_ints(args.sizes, "--sizes"), outputs=outputs, device=args.device, backends=backends,
                      repeats=args.repeats, channels=args.channels, width=w, height=h, small_n=args.small_n,
                      small_width=sw, small_height=sh, baselines=not args.skip_baselines, knobs=not args.skip_knobs,
                      kernels=kernels, floor=not args.skip_floor, busy=args.busy, busy_n=args.busy_n,
                      busy_threads=args.busy_threads)
    n_speed = len(cfg.sizes) * len(outputs) * len(backends) * 2 * (len(kernels) if args.device == "cpu" else 1)
    n_cases = (n_speed + (12 if cfg.baselines else 0) + (14 if cfg.knobs else 0)
               + (len(cfg.sizes) * 2 * len(kernels) if cfg.floor and args.device == "cpu" else 0)
               + (8 * len(kernels) if cfg.busy else 0))
    bar = tqdm(total=n_cases, desc="bench render", unit="case", file=sys.stderr)

    def progress(rec: dict) -> None:
        bar.update(1)
        bar.set_postfix_str(f"{rec.get('impl') or rec.get('knob') or rec.get('kernel') or ''} n={rec['n']} {rec['output']} "
                            f"{rec['mode']} {rec['ms_median']:.0f} ms")

    threads_before = torch.get_num_threads()
    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        records = run_bench(cfg, progress)
    finally:
        torch.set_num_threads(threads_before)
        bar.close()
    command = "fourlegs " + " ".join(shlex.quote(a) for a in sys.argv[1:]) if sys.argv[1:] else "fourlegs bench render"
    env = dict(environment(), threads=args.threads or threads_before)
    report = markdown_report(records, command, env)
    print(report)
    if args.json:
        write_json_atomic(args.json, [dict(r, command=command, threads=env["threads"], torch=env["torch"])
                                      for r in records], overwrite=args.overwrite)
    if args.markdown:
        with atomic_path(args.markdown, overwrite=args.overwrite) as tmp:
            Path(tmp).write_text(report + "\n", encoding="utf-8")
    if args.plot and cfg.knobs:
        plot_knobs(records, args.plot)
    return 0
