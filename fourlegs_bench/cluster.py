"""``fourlegs bench cluster``: a local Ray cluster against the single-process run, and a simulation
of scale for one Panoptic sequence.

Measured part: the synthetic scene's extraction (simulated encoder) and lift, once in this process
and once as Ray tasks on a local cluster of ``--workers`` one-CPU workers, each in its own copy of
the bundle (inputs hard-linked). Reports whether every per-timestep file is byte-identical, the
wall-clock and summed worker-side seconds, and the overhead per task: the round trip of an empty
task (one at a time, and pipelined over all workers) and, for the real tasks,
(wall × slots − Σ task seconds) / tasks, i.e. what the cluster adds per task including idle slots.

Simulated part: list scheduling (each task, in submission order, goes to the earliest free GPU, as
Ray's scheduler does for equal tasks) of one sequence's extraction (one task per timestep, as
``--ray`` does with ViCLIP; and one run of timesteps per GPU for comparison), the autoencoder training (one task) and the distillation (one task
per timestep) on 1, 8 and 64 GPUs. Every per-task cost is an explicit, printed assumption (or the
overhead measured above); durations get a seeded ±``jitter`` spread.
"""
from __future__ import annotations

import argparse
import contextlib
import heapq
import math
import os
import shutil
import statistics
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Sequence

SYNTHETIC_SIZES = ("tiny", "demo", "bench", "full")


def register_bench(bench_subparsers: Any) -> None:
    p = bench_subparsers.add_parser(
        "cluster", help="Ray: local cluster vs single process (same bytes, overhead per task) + simulation of scale",
        description="Extraction and lift of a synthetic scene in one process and on a local Ray cluster "
                    "(identical bytes? overhead per task in ms), then a list-scheduling simulation of the "
                    "Panoptic basketball sequence on 1, 8 and 64 GPUs. Needs Ray (pip install \"fourlegs[cluster]\").")
    p.add_argument("--scene", default="bench", help="synthetic size (tiny, demo, bench, full) or a bundle path "
                   "(default bench)")
    p.add_argument("--timesteps", default="0:16", help="timesteps extracted and lifted (default 0:16)")
    p.add_argument("--workers", type=int, default=2, help="CPUs of the local Ray cluster = workers (default 2)")
    p.add_argument("--chunk", type=int, default=None, help="timesteps per extraction task (default auto)")
    p.add_argument("--single-threads", type=int, default=1,
                   help="torch threads of the single-process run (default 1, as each one-CPU Ray worker has)")
    p.add_argument("--no-shared-fs", action="store_true", help="measure the object-store mode instead")
    p.add_argument("--skip-measure", action="store_true", help="only the simulation (with --overhead-ms)")
    p.add_argument("--overhead-ms", type=float, default=None,
                   help="per-task overhead for the simulation (default: the measured pipelined empty-task ms)")
    p.add_argument("--gpus", default="1,8,64", help="GPU counts to simulate (default 1,8,64)")
    p.add_argument("--out", default=None, help="output prefix for .json/.md (default: <bundle>/bench/cluster)")
    p.set_defaults(func=run_bench_cluster)


# ------------------------------------------------------------------------------------ simulation
@dataclass
class SequenceAssumptions:
    """One Panoptic sequence and the per-task costs the simulation assumes (seconds unless noted).

    ``clip_seconds``: ViCLIP-L/14 video tower, one 8×224² clip on one A100/H100-class GPU in fp16 —
    a FLOP estimate (ViT-L/14 ≈ 81 GMAC per 224² frame, 8 frames ≈ 1.3 TFLOP per clip, at ~100 TFLOP/s
    sustained), not a measurement: no GPU was available. ``render_seconds``: one 640×360 RGB frame of
    300k Gaussians with gsplat. ``encoder_load_seconds``: first task on a GPU loads the checkpoint.
    ``distill_seconds``: one timestep of the paper's optimize (≈5 min per timestep on a GPU, paper).
    ``autoencoder_seconds``: the per-scene 768→128 autoencoder (one task, all timesteps' features).
    ``feature_mb``: one timestep's features (27 × 572 crops × 768 float16) moved per distill task.
    """

    cameras: int = 27
    timesteps: int = 150
    clips_per_camera: int = 572
    clip_seconds: float = 0.013
    render_seconds: float = 0.01
    encoder_load_seconds: float = 20.0
    distill_seconds: float = 300.0
    autoencoder_seconds: float = 600.0
    feature_mb: float = 27 * 572 * 768 * 2 / 1e6
    transfer_mb_per_s: float = 1000.0
    jitter: float = 0.1
    seed: int = 0


def list_schedule(durations: Sequence[float], workers: int) -> tuple[float, list[float]]:
    """Makespan of running ``durations`` in order, each on the earliest free of ``workers``;
    returns (makespan, busy seconds per worker).

    >>> list_schedule([3, 1, 1, 1], 2)
    (3.0, [3.0, 3.0])
    """
    free = [(0.0, w) for w in range(workers)]
    heapq.heapify(free)
    busy = [0.0] * workers
    end = 0.0
    for d in durations:
        t, w = heapq.heappop(free)
        busy[w] += float(d)
        heapq.heappush(free, (t + float(d), w))
        end = max(end, t + float(d))
    return end, busy


def _jittered(base: float, n: int, jitter: float, rng: Any) -> list[float]:
    return [base * (1.0 + jitter * (2.0 * rng.random() - 1.0)) for _ in range(n)]


def simulate_sequence(a: SequenceAssumptions, gpus: int, overhead_s: float, grain: str = "timestep",
                      chunk: int | None = None) -> dict[str, Any]:
    """Extraction → autoencoder → distillation of one sequence on ``gpus`` GPUs (stages in order).

    ``grain="timestep"`` is what ``--ray`` schedules (chunks of ``chunk`` consecutive timesteps; None:
    the auto size of ``--ray-chunk`` for ViCLIP, 1);
    ``"camera-timestep"`` is a what-if with one task per camera and timestep (not implemented: the
    result files hold whole timesteps).
    """
    import random
    from fourlegs_engine.cluster import auto_chunk
    rng = random.Random(a.seed * 1000 + gpus)
    clip_per_cam = a.clips_per_camera * a.clip_seconds
    if grain == "timestep":
        chunk = chunk or auto_chunk(a.timesteps, gpus, "rgb")
        n_tasks = math.ceil(a.timesteps / chunk)
        sizes = [min(chunk, a.timesteps - i * chunk) for i in range(n_tasks)]
        # a task renders the 8-frame tubes of its timesteps: (c + 7) frames per camera
        base = [c * a.cameras * clip_per_cam + (c + 7) * a.cameras * a.render_seconds for c in sizes]
    else:
        chunk = 1
        base = [clip_per_cam + 8 * a.render_seconds] * (a.cameras * a.timesteps)
    extract = [d * (1.0 + a.jitter * (2.0 * rng.random() - 1.0)) + overhead_s for d in base]
    first_loads = [a.encoder_load_seconds] * min(gpus, len(extract))   # once per GPU worker
    for i, load in enumerate(first_loads):
        extract[i] += load
    ext_span, ext_busy = list_schedule(extract, gpus)
    transfer = a.feature_mb / a.transfer_mb_per_s
    distill = [d + overhead_s + transfer for d in _jittered(a.distill_seconds, a.timesteps, a.jitter, rng)]
    dis_span, dis_busy = list_schedule(distill, gpus)
    total = ext_span + a.autoencoder_seconds + dis_span
    work = sum(extract) + a.autoencoder_seconds + sum(distill)
    return {"gpus": gpus, "grain": grain, "extract_chunk": chunk, "extract_tasks": len(extract),
            "extract_hours": ext_span / 3600, "autoencoder_hours": a.autoencoder_seconds / 3600,
            "distill_hours": dis_span / 3600, "total_hours": total / 3600, "gpu_hours": work / 3600,
            "efficiency": work / (gpus * total)}


def simulation_table(a: SequenceAssumptions, gpu_counts: Sequence[int], overhead_s: float) -> list[dict[str, Any]]:
    rows = [simulate_sequence(a, g, overhead_s) for g in gpu_counts]
    rows += [simulate_sequence(a, g, overhead_s, chunk=math.ceil(a.timesteps / g)) for g in gpu_counts if g > 1]
    rows += [simulate_sequence(a, g, overhead_s, "camera-timestep") for g in gpu_counts if g > 1]
    return sorted(rows, key=lambda r: (r["gpus"], r["grain"] != "timestep", -r["extract_chunk"]))


# --------------------------------------------------------------------------------- measurement
def _noop(job: Any, chunk: tuple[int, ...], payload: Any) -> None:
    return None


def _link_copy(src: Path, dst: Path) -> Path:
    """The bundle's inputs (no stage outputs), hard-linked where the filesystem allows."""
    from fourlegs_engine.cluster import OUTPUT_DIRS

    def ignore(directory: str, names: list[str]) -> list[str]:
        return [n for n in names if Path(directory) == src and n in OUTPUT_DIRS]

    def link(s: str, d: str) -> None:
        try:
            os.link(s, d)
        except OSError:
            shutil.copy2(s, d)

    shutil.copytree(src, dst, ignore=ignore, copy_function=link)
    return dst


def _compare(a: Path, b: Path) -> dict[str, Any]:
    import numpy as np
    names = sorted(p.name for p in a.glob("t*.npy"))
    other = sorted(p.name for p in b.glob("t*.npy"))
    identical = names == other and all((a / n).read_bytes() == (b / n).read_bytes() for n in names)
    max_diff = 0.0
    for n in set(names) & set(other):
        x = np.load(a / n).astype(np.float64)
        y = np.load(b / n).astype(np.float64)
        max_diff = max(max_diff, float(np.abs(x - y).max()) if x.shape == y.shape else float("inf"))
    return {"files": len(names), "same_names": names == other, "bitwise_identical": identical,
            "max_abs_diff": max_diff}


def measure(source: Path, timesteps: str, workers: int, chunk: int | None, shared_fs: bool,
            progress: bool = True, single_threads: int | None = 1) -> dict[str, Any]:
    """Single process vs local Ray cluster on copies of ``source`` (see the module docstring)."""
    import torch
    from fourlegs_engine import cluster
    from fourlegs_engine.language.autoencoder import (AE_CHECKPOINT, AE_REPORT, DECODER_FILE, ENCODER_FILE,
                                                      AETrainOptions, train_autoencoder)
    from fourlegs_engine.language.distill import DistillOptions, distill_scene
    import fourlegs_engine.demo  # noqa: F401 (registers the "simulated" encoder)
    from fourlegs_engine.language.encoders import get_encoder
    from fourlegs_engine.language.extract import ExtractOptions, extract_features
    from fourlegs_engine.language.store import select_timesteps
    from fourlegs_engine.scene.bundle import load_bundle

    ray = cluster.require_ray()
    work = Path(tempfile.mkdtemp(prefix="fourlegs-bench-cluster-"))
    try:
        single, multi = _link_copy(source, work / "single"), _link_copy(source, work / "cluster")
        scene = load_bundle(single)
        steps = select_timesteps(scene.num_timesteps, timesteps)
        out: dict[str, Any] = {"scene": scene.name, "num_gaussians": scene.num_gaussians,
                               "cameras": scene.cameras.num_cameras("train"), "timesteps": steps,
                               "workers": workers,
                               "shared_fs": shared_fs}
        # ---- single process
        from fourlegs_engine.threads import torch_threads
        with torch_threads(single_threads) if single_threads else contextlib.nullcontext():
            out["single_threads"] = torch.get_num_threads()
            c0, w0 = time.process_time(), time.perf_counter()
            extract_features(scene, get_encoder("simulated", scene=scene), ExtractOptions(), timesteps=steps,
                             progress=progress)
            out["single_extract_s"] = time.perf_counter() - w0
            out["single_extract_cpu_s"] = time.process_time() - c0
            # the same autoencoder serves both runs; its quality does not matter here
            train_autoencoder(scene, AETrainOptions(epochs=1, samples=8192), timesteps=steps, progress=progress)
            for rel in (AE_REPORT, ENCODER_FILE, DECODER_FILE, AE_CHECKPOINT):
                if (single / rel).is_file():
                    (multi / rel).parent.mkdir(parents=True, exist_ok=True)
                    shutil.copy2(single / rel, multi / rel)
            c0, w0 = time.process_time(), time.perf_counter()
            distill_scene(scene, config=DistillOptions(mode="lift"), timesteps=steps, merge=False, progress=progress)
            out["single_lift_s"] = time.perf_counter() - w0
            out["single_lift_cpu_s"] = time.process_time() - c0
        # ---- local Ray cluster
        w0 = time.perf_counter()
        ray.init(num_cpus=workers, include_dashboard=False, logging_level="WARNING")
        out["ray_init_s"] = time.perf_counter() - w0
        try:
            options = cluster.RayOptions(chunk=chunk, shared_fs=shared_fs)
            warm = cluster.run_chunks(_noop, None, [(i,) for i in range(4 * workers)], options=options,
                                      stage="warm-up", progress=False)
            warm.raise_failures()
            lat = []
            remote = ray.remote(cluster.run_task).options(num_cpus=1)
            for _ in range(20):
                s = time.perf_counter()
                ray.get(remote.remote(_noop, None, (), None))
                lat.append(time.perf_counter() - s)
            out["empty_task_roundtrip_ms"] = 1000 * statistics.median(lat)
            n = 200
            noop = cluster.run_chunks(_noop, None, [(i,) for i in range(n)], options=options, stage="noop",
                                      progress=False)
            out["empty_task_pipelined_ms"] = 1000 * noop.wall_seconds / n
            mscene = load_bundle(multi)
            w0 = time.perf_counter()
            rep, ext = cluster.extract_on_ray(mscene, _simulated_encoder, timesteps=steps, options=options,
                                              progress=progress)
            ext_wall = time.perf_counter() - w0
            w0 = time.perf_counter()
            res, dis = cluster.distill_on_ray(mscene, DistillOptions(mode="lift"), timesteps=steps,
                                              options=options, progress=progress)
            walls = {"extract": ext_wall, "lift": time.perf_counter() - w0}
            gaps = noop.dispatch_gaps()
            out["empty_task_dispatch_gap_ms"] = 1000 * statistics.median(gaps) if gaps else None
            for name, r in (("extract", ext), ("lift", dis)):
                setup = r.setup or cluster.ClusterReport(name)
                out[f"ray_{name}_s"] = walls[name]            # the whole call: set-up task, tasks, merge
                out[f"ray_{name}_tasks"] = len(r.done)
                out[f"ray_{name}_task_s"] = sum(r.task_seconds) + sum(setup.task_seconds)
                out[f"ray_{name}_task_cpu_s"] = sum(r.task_cpu_seconds) + sum(setup.task_cpu_seconds)
                out[f"ray_{name}_overhead_ms_per_task"] = (
                    1000 * (r.wall_seconds * r.slots - sum(r.task_seconds)) / max(1, len(r.done)))
                gaps = r.dispatch_gaps()
                out[f"ray_{name}_dispatch_gap_ms"] = 1000 * statistics.median(gaps) if gaps else None
                out[f"ray_{name}_result_latency_ms"] = 1000 * statistics.median(
                    arrived - end for _, _, end, arrived in r.timeline)
                out[f"ray_{name}_slots"] = r.slots
        finally:
            ray.shutdown()
        out["features"] = _compare(single / "features", multi / "features")
        out["latents"] = _compare(single / "language" / "steps", multi / "language" / "steps")
        return out
    finally:
        shutil.rmtree(work, ignore_errors=True)


def _simulated_encoder(scene: Any) -> Any:
    import fourlegs_engine.demo  # noqa: F401 (registers the "simulated" encoder)
    from fourlegs_engine.language.encoders import get_encoder
    return get_encoder("simulated", scene=scene)


# ----------------------------------------------------------------------------------------- report
def run_bench_cluster(args: argparse.Namespace) -> int:
    from fourlegs_engine.errors import InputError
    from fourlegs_engine.fileio import write_bytes_atomic, write_json_atomic
    if args.scene in SYNTHETIC_SIZES:
        from fourlegs_engine.demo.synthetic import ensure_demo_bundle
        source = ensure_demo_bundle(args.scene)
    else:
        source = Path(args.scene)
    try:
        gpu_counts = [int(g) for g in args.gpus.split(",") if g.strip()]
    except ValueError:
        raise InputError(f"cannot parse {args.gpus!r}; use e.g. 1,8,64", field="--gpus") from None
    if not gpu_counts or min(gpu_counts) < 1:
        raise InputError("GPU counts must be >= 1", field="--gpus")
    report: dict[str, Any] = {"benchmark": "cluster", "command": "fourlegs bench cluster " + " ".join(sys.argv[3:])}
    if not args.skip_measure:
        report["measured"] = measure(source, args.timesteps, args.workers, args.chunk, not args.no_shared_fs,
                                     single_threads=args.single_threads)
    overhead_ms = args.overhead_ms
    if overhead_ms is None:
        overhead_ms = report.get("measured", {}).get("empty_task_pipelined_ms", 5.0)
    assumptions = SequenceAssumptions()
    report["simulation"] = {"assumptions": asdict(assumptions), "overhead_ms_per_task": overhead_ms,
                            "rows": simulation_table(assumptions, gpu_counts, overhead_ms / 1000)}
    prefix = Path(args.out) if args.out else Path(source) / "bench" / "cluster"
    write_json_atomic(prefix.with_suffix(".json"), report)
    md = markdown(report)
    write_bytes_atomic(prefix.with_suffix(".md"), md.encode())
    print(md)
    print(f"written: {prefix.with_suffix('.json')} and {prefix.with_suffix('.md')}", file=sys.stderr)
    return 0


def markdown(report: dict[str, Any]) -> str:
    lines = ["# Cluster benchmark (Ray)", ""]
    m = report.get("measured")
    if m:
        lines += [f"Scene `{m['scene']}`: {m['num_gaussians']:,} Gaussians, {m['cameras']} training cameras, "
                  f"{len(m['timesteps'])} timesteps ({m['timesteps'][0]}..{m['timesteps'][-1]}); single process "
                  f"with {m['single_threads']} torch threads vs a local Ray cluster of {m['workers']} one-CPU "
                  f"workers ({'shared filesystem' if m['shared_fs'] else 'object store'}).", "",
                  "| stage | single process s (CPU s) | Ray s | Ray tasks | Σ task s (CPU s) | (wall × slots − Σ task s) / task, ms "
                  "| dispatch gap ms | result latency ms | bitwise identical |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|---|"]

        def ms(v: Any) -> str:
            return "-" if v is None else f"{v:.1f}"
        for name, key, files in (("extract", "extract", "features"), ("lift", "lift", "latents")):
            lines.append(f"| {name} | {m[f'single_{key}_s']:.1f} ({m[f'single_{key}_cpu_s']:.1f}) | "
                         f"{m[f'ray_{key}_s']:.1f} | {m[f'ray_{key}_tasks']} | {m[f'ray_{key}_task_s']:.1f} "
                         f"({m[f'ray_{key}_task_cpu_s']:.1f}) | {m[f'ray_{key}_overhead_ms_per_task']:.0f} | "
                         f"{ms(m[f'ray_{key}_dispatch_gap_ms'])} | {ms(m[f'ray_{key}_result_latency_ms'])} | "
                         f"{m[files]['bitwise_identical']} ({m[files]['files']} files, max diff "
                         f"{m[files]['max_abs_diff']:.3g}) |")
        lines += ["", f"Ray start {m['ray_init_s']:.1f} s; empty task: {m['empty_task_roundtrip_ms']:.1f} ms round trip "
                  f"(one at a time), {m['empty_task_pipelined_ms']:.2f} ms per task pipelined over the workers, "
                  f"dispatch gap {ms(m['empty_task_dispatch_gap_ms'])} ms. Dispatch gap: median time between one "
                  "task's end and the next task's start on the same worker; result latency: median time from a "
                  "task's end to its result in the driver (files written there without a shared filesystem).", ""]
    s = report["simulation"]
    a = s["assumptions"]
    lines += [f"## Simulation: one sequence, {a['cameras']} cameras × {a['timesteps']} timesteps, "
              f"{a['clips_per_camera']} ViCLIP clips per camera-timestep", "",
              f"Assumed: {a['clip_seconds'] * 1000:.0f} ms per clip (FLOP estimate, fp16 A100/H100 class), "
              f"{a['render_seconds'] * 1000:.0f} ms per rendered frame, {a['encoder_load_seconds']:.0f} s encoder load "
              f"per GPU, {a['distill_seconds']:.0f} s distillation per timestep (paper: optimize), "
              f"{a['autoencoder_seconds']:.0f} s autoencoder (one task), {a['feature_mb']:.1f} MB features per "
              f"timestep at {a['transfer_mb_per_s']:.0f} MB/s, ±{100 * a['jitter']:.0f}% task spread, "
              f"{s['overhead_ms_per_task']:.2f} ms overhead per task. Stages run one after the other.", "",
              "| GPUs | grain | extract tasks (chunk) | extract h | autoencoder h | distill h | total h | GPU-hours | efficiency |",
              "|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in s["rows"]:
        lines.append(f"| {r['gpus']} | {r['grain']}{'' if r['grain'] == 'timestep' else ' (what-if)'} | "
                     f"{r['extract_tasks']} ({r['extract_chunk']}) | {r['extract_hours']:.2f} | "
                     f"{r['autoencoder_hours']:.2f} | {r['distill_hours']:.2f} | {r['total_hours']:.2f} | "
                     f"{r['gpu_hours']:.1f} | {100 * r['efficiency']:.0f}% |")
    return "\n".join(lines) + "\n"
