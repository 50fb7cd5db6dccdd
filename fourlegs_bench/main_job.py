"""``fourlegs bench main-job``: the README's first command from scratch, as a stage table.

Runs ``fourlegs highlight --demo QUERY --preset PRESET`` (the headless job, in a child process) with
``FOURLEGS_CACHE`` pointing at a new empty directory, so every stage runs: scene generation, feature
extraction, autoencoder training, the lift, localization and planning, and the Blender render. The
stage timings are the ones the job itself records in its ``report.json`` (wall and CPU seconds per
stage); this command adds the child's total wall time, CPU time and peak RSS, the answer (segment and
peak) and, from the scene's ``language/autoencoder.json``, what each autoencoder epoch bought
(held-out reconstruction cosine) and cost (seconds), as a table and a plot.

Writes into ``-o DIR``: ``main_job.json``, ``main_job.md``, ``ae_epochs.png`` and the job's own
outputs under ``job/``.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Optional, Sequence

#: the job's stages in the order they run (``encode mp4`` is timed inside ``render``)
STAGES = ("scene", "extract features", "train autoencoder", "distil (lift)", "open query engine",
          "localize + plan", "blender import", "generate highlight", "render", "encode mp4", "save .blend")
NESTED = {"encode mp4": "render"}
DEFAULT_QUERY = "a ball flying in the air"


def register_bench(bench_sub: Any) -> None:
    p = bench_sub.add_parser(
        "main-job", help="the main job (fourlegs highlight --demo) from an empty cache: stage table",
        description="Run `fourlegs highlight --demo QUERY --preset PRESET` from scratch (a new empty "
                    "FOURLEGS_CACHE) and write the stage table (wall and CPU seconds per stage, from the "
                    "job's report.json), the answer, and the autoencoder's accuracy per epoch.")
    p.add_argument("--query", default=DEFAULT_QUERY, help="the query (default: %(default)r)")
    p.add_argument("--preset", default="broadcast", help="highlight preset (default: %(default)s)")
    p.add_argument("--demo-size", default="demo", choices=("tiny", "demo", "bench", "full"),
                   help="synthetic scene size (default: %(default)s, the README's command)")
    p.add_argument("--resolution", default=None, help="output WIDTHxHEIGHT (default: the job's, 640x360)")
    p.add_argument("--fps", type=float, default=None, help="output frame rate (default: the preset's)")
    p.add_argument("-o", "--output", required=True, metavar="DIR", help="where the tables and the job's outputs go")
    p.add_argument("--cache", default=None, metavar="DIR",
                   help="the job's FOURLEGS_CACHE; must be absent or empty (default: a temporary directory, "
                        "deleted afterwards)")
    p.add_argument("--ae-epochs", default="", metavar="LIST",
                   help="also retrain the autoencoder with these epoch counts (comma-separated) from the job's "
                        "features, lift, and localize the query again: the answer and its time per count "
                        "(default: off)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing result in DIR")
    p.set_defaults(func=bench_main_job)


def job_command(args: argparse.Namespace, job_dir: Path) -> list[str]:
    """The headless job's command line (what ``fourlegs highlight`` runs in its child process)."""
    cmd = [sys.executable, "-m", "fourlegs_addon.headless", args.query, "--demo", "--demo-size", args.demo_size,
           "--preset", args.preset, "-o", str(job_dir)]
    if args.resolution:
        cmd += ["--resolution", args.resolution]
    if args.fps is not None:
        cmd += ["--fps", str(args.fps)]
    return cmd


def readme_command(args: argparse.Namespace) -> str:
    parts = ["fourlegs", "highlight", "--demo", json.dumps(args.query), "--preset", args.preset]
    if args.demo_size != "demo":
        parts += ["--demo-size", args.demo_size]
    if args.resolution:
        parts += ["--resolution", args.resolution]
    if args.fps is not None:
        parts += ["--fps", f"{args.fps:g}"]
    return " ".join(parts + ["-o", "out/"])


def bench_command(args: argparse.Namespace) -> str:
    parts = ["fourlegs", "bench", "main-job"]
    if args.query != DEFAULT_QUERY:
        parts += ["--query", json.dumps(args.query)]
    if args.preset != "broadcast":
        parts += ["--preset", args.preset]
    if args.demo_size != "demo":
        parts += ["--demo-size", args.demo_size]
    if args.resolution:
        parts += ["--resolution", args.resolution]
    if args.fps is not None:
        parts += ["--fps", f"{args.fps:g}"]
    return " ".join(parts + ["-o", str(args.output)])


def run_job(cmd: Sequence[str], cache: Path) -> dict[str, float]:
    """Run the job with ``FOURLEGS_CACHE=cache``; returns its wall s, CPU s (user + sys) and peak RSS MB."""
    env = {**os.environ, "FOURLEGS_CACHE": str(cache)}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    proc = subprocess.run(list(cmd), env=env)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        from fourlegs_engine.errors import FourlegsError
        raise FourlegsError(f"the main job failed (exit status {proc.returncode}): {' '.join(cmd)}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"wall_seconds": round(wall, 3), "cpu_seconds": round(cpu, 3),
            "peak_rss_mb": round(after.ru_maxrss / 1024.0, 1)}


def stage_rows(report: dict[str, Any]) -> list[dict[str, Any]]:
    """One row per stage the job timed, in run order: name, wall s, CPU s (None if not recorded),
    share of the job's total wall time (None for stages nested in another)."""
    wall = report.get("timings_s") or {}
    cpu = report.get("cpu_timings_s") or {}
    total = float(report.get("total_seconds") or 0.0)
    names = [s for s in STAGES if s in wall] + [s for s in wall if s not in STAGES]
    rows = []
    for name in names:
        nested = NESTED.get(name)
        rows.append({"stage": name, "inside": nested if nested in wall else None, "wall_s": float(wall[name]),
                     "cpu_s": float(cpu[name]) if name in cpu else None,
                     "share": (float(wall[name]) / total if total > 0 and not (nested in wall) else None)})
    return rows


def epoch_rows(ae_report: dict[str, Any]) -> list[dict[str, Any]]:
    """Per autoencoder epoch: training loss, held-out reconstruction cosine, seconds and their running sum."""
    loss = ae_report.get("loss_history") or []
    cos = ae_report.get("cosine_history") or []
    secs = ae_report.get("epoch_seconds") or []
    rows, elapsed = [], 0.0
    for i in range(len(loss)):
        s = float(secs[i]) if i < len(secs) else None
        elapsed = elapsed + s if s is not None else elapsed
        rows.append({"epoch": i + 1, "loss": float(loss[i]), "heldout_cosine": float(cos[i]) if i < len(cos) else None,
                     "seconds": s, "cumulative_seconds": elapsed if s is not None else None})
    return rows


def epoch_sweep(bundle: Path, epochs: Sequence[int], query: str, work: Path) -> list[dict[str, Any]]:
    """For each epoch count: retrain the autoencoder on a copy of ``bundle`` (its extracted features
    shared), lift, and localize ``query`` as the job does; returns seconds and the answer per count."""
    import torch

    from fourlegs_engine.highlight_job import DEFAULT_QUERY_PATH, DEFAULT_SPATIAL
    from fourlegs_engine.fileio import read_json, write_json_atomic
    from fourlegs_engine.language.autoencoder import AETrainOptions, train_autoencoder
    from fourlegs_engine.language.distill import distill_scene
    from fourlegs_engine import pipeline
    from fourlegs_engine.scene.loaders import load_scene

    rows = []
    for count in epochs:
        root = work / f"epochs-{count}"
        shutil.rmtree(root, ignore_errors=True)
        shutil.copytree(bundle, root, ignore=shutil.ignore_patterns("features", "language", ".*"))
        (root / "features").symlink_to((bundle / "features").resolve(), target_is_directory=True)
        meta = read_json(root / "scene.json")
        meta.pop("language", None)
        meta.get("arrays", {}).pop("latents", None)
        write_json_atomic(root / "scene.json", meta)
        scene = load_scene(root)
        start = time.perf_counter()
        ae = train_autoencoder(scene, AETrainOptions(epochs=int(count)))
        trained = time.perf_counter()
        distill_scene(scene, mode="lift", view_scale=pipeline.FIELD_VIEW_SCALE)  # as the job lifts
        lifted = time.perf_counter()
        scene = load_scene(root)
        engine = pipeline.open_query_engine(
            scene, options=pipeline.QueryOptions(path=DEFAULT_QUERY_PATH, spatial=DEFAULT_SPATIAL))
        with torch.no_grad():
            loc = engine.localize(query, ("temporal", "best_view", "action_centre"))
        done = time.perf_counter()
        tr = loc.temporal
        rows.append({"epochs": int(count), "heldout_cosine": ae.get("heldout_cosine"),
                     "train_ae_s": round(trained - start, 3), "lift_s": round(lifted - trained, 3),
                     "localize_s": round(done - lifted, 3),
                     "segment": list(tr.segment) if tr is not None and tr.segment is not None else None,
                     "peak": tr.peak if tr is not None else None, "found": bool(tr is not None and tr.found),
                     "messages": ([tr.message] if tr is not None and tr.message else []) + list(loc.messages),
                     "best_view": loc.best_view,
                     "action_centre": None if loc.action_centre is None else [float(v) for v in loc.action_centre],
                     "scores": None if tr is None else [float(v) for v in tr.scores]})
        shutil.rmtree(root, ignore_errors=True)
    return rows


def segment_iou(a: Optional[Sequence[int]], b: Optional[Sequence[int]]) -> Optional[float]:
    """Temporal IoU of two inclusive [start, end] timestep segments (None if either is missing)."""
    if a is None or b is None:
        return None
    inter = max(0, min(a[1], b[1]) - max(a[0], b[0]) + 1)
    union = (a[1] - a[0] + 1) + (b[1] - b[0] + 1) - inter
    return inter / union if union > 0 else None


def answer_of(report: dict[str, Any]) -> dict[str, Any]:
    loc = report.get("localization") or {}
    return {"found": loc.get("found"), "segment": loc.get("segment"), "peak": loc.get("peak"),
            "best_view": loc.get("best_view"), "action_centre": loc.get("action_centre")}


def _fmt(value: Optional[float], digits: int = 1) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def markdown(result: dict[str, Any]) -> str:
    job, ans = result["job"], result["answer"]
    lines = [f"`{result['command']}` from an empty cache (measured by `{result['bench_command']}`)", "",
             "| stage | wall s | CPU s | share of wall |", "|---|---:|---:|---:|"]
    for r in result["stages"]:
        name = r["stage"] if r["inside"] is None else f"{r['stage']} (inside {r['inside']})"
        share = "" if r["share"] is None else f"{100 * r['share']:.0f}%"
        lines.append(f"| {name} | {_fmt(r['wall_s'])} | {_fmt(r['cpu_s'])} | {share} |")
    lines.append(f"| **job (report total_seconds)** | **{_fmt(result['report_total_seconds'])}** | | |")
    lines.append(f"| **process (with start-up)** | **{_fmt(job['wall_seconds'])}** | **{_fmt(job['cpu_seconds'])}** | |")
    lines += ["", f"Answer: segment {ans['segment']}, peak {ans['peak']}, best view {ans['best_view']}; "
                  f"{result['frames']} frames at {result['resolution'][0]}x{result['resolution'][1]}; "
                  f"peak RSS {job['peak_rss_mb']:.0f} MB; render: {result['render_threads']}."]
    if result["ae_epochs"]:
        lines += ["", "Autoencoder: what each epoch buys (held-out reconstruction cosine) and costs:", "",
                  "| epoch | train loss | held-out cosine | s | cumulative s |", "|---:|---:|---:|---:|---:|"]
        for r in result["ae_epochs"]:
            lines.append(f"| {r['epoch']} | {r['loss']:.5f} | {_fmt(r['heldout_cosine'], 4)} | {_fmt(r['seconds'])} | "
                         f"{_fmt(r['cumulative_seconds'])} |")
    if result.get("ae_sweep"):
        ref = result["answer"]
        lines += ["", "Autoencoder epochs against the answer (same features; retrained, lifted and localized again; "
                      "tIoU and centre shift against the job's answer):", "",
                  "| epochs | held-out cosine | train-ae s | lift s | localize s | found | segment | peak | tIoU | "
                  "best view | action centre shift (m) |", "|---:|---:|---:|---:|---:|---|---|---:|---:|---|---:|"]
        for r in result["ae_sweep"]:
            shift = None
            if r["action_centre"] is not None and ref.get("action_centre") is not None:
                shift = sum((x - y) ** 2 for x, y in zip(r["action_centre"], ref["action_centre"])) ** 0.5
            iou = segment_iou(r["segment"], ref.get("segment"))
            lines.append(f"| {r['epochs']} | {_fmt(r['heldout_cosine'], 4)} | {_fmt(r['train_ae_s'])} | "
                         f"{_fmt(r['lift_s'])} | {_fmt(r['localize_s'])} | {'yes' if r.get('found') else 'no'} | "
                         f"{r['segment']} | {r['peak']} | "
                         f"{_fmt(iou, 2)} | {r['best_view']} | {_fmt(shift, 3)} |")
    lines += ["", f"Machine: {result['machine']}"]
    return "\n".join(lines) + "\n"


def epoch_plot(path: Path, rows: list[dict[str, Any]]) -> None:
    """Held-out reconstruction cosine against cumulative training seconds, one point per epoch."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fourlegs_engine.fileio import atomic_path

    pts = [(r["cumulative_seconds"], r["heldout_cosine"], r["epoch"]) for r in rows
           if r["cumulative_seconds"] is not None and r["heldout_cosine"] is not None]
    fig, ax = plt.subplots(figsize=(5, 3.2), dpi=100)
    ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", color="tab:blue")
    for x, y, e in pts:
        ax.annotate(f"epoch {e}", (x, y), textcoords="offset points", xytext=(5, 4), fontsize=8)
    ax.set_xlabel("autoencoder training time (s, cumulative)")
    ax.set_ylabel("held-out reconstruction cosine")
    ax.set_title("what autoencoder epochs buy")
    ax.grid(alpha=0.3)
    ax.margins(x=0.15, y=0.15)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def machine() -> str:
    import platform

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return f"{platform.processor() or platform.machine()}, {cores} cores, load average {load:.1f} at the end"


def bench_main_job(args: argparse.Namespace) -> int:
    from fourlegs_engine.errors import InputError, OutputExistsError
    from fourlegs_engine.fileio import atomic_path, read_json, write_json_atomic

    out = Path(args.output)
    targets = [out / "main_job.json", out / "main_job.md", out / "job"]
    existing = [p for p in targets if p.exists()]
    if existing and not args.overwrite:
        raise OutputExistsError(", ".join(map(str, existing)))
    try:
        sweep_ok = all(int(v) >= 1 for v in args.ae_epochs.split(",") if v.strip())
    except ValueError:
        sweep_ok = False
    if not sweep_ok:
        raise InputError(f"expected positive integers, got {args.ae_epochs!r}", field="--ae-epochs")
    if args.cache is not None and Path(args.cache).exists() and any(Path(args.cache).iterdir()):
        raise InputError("must be absent or empty: the job runs from scratch", file=args.cache, field="--cache")
    out.mkdir(parents=True, exist_ok=True)
    shutil.rmtree(out / "job", ignore_errors=True)
    cache = Path(args.cache) if args.cache else Path(tempfile.mkdtemp(prefix="fourlegs-main-job-cache-"))
    try:
        cache.mkdir(parents=True, exist_ok=True)
        job = run_job(job_command(args, out / "job"), cache)
        report = read_json(out / "job" / "report.json")
        ae_path = Path(report["scene"]["path"]) / "language" / "autoencoder.json"
        ae_report = read_json(ae_path) if ae_path.is_file() else {}
        sweep = [int(v) for v in args.ae_epochs.split(",") if v.strip()]
        ae_sweep = epoch_sweep(Path(report["scene"]["path"]), sweep, args.query, cache / "ae-sweep") if sweep else []
    finally:
        if args.cache is None:
            shutil.rmtree(cache, ignore_errors=True)
    render = report.get("render") or {}
    result = {
        "format": "fourlegs-bench-main-job", "version": 1,
        "command": readme_command(args), "bench_command": bench_command(args),
        "job": job, "report_total_seconds": report.get("total_seconds"), "stages": stage_rows(report),
        "answer": answer_of(report), "resolution": report.get("resolution"),
        "frames": (report["frames"][1] - report["frames"][0] + 1) if report.get("frames") else None,
        "render_threads": f"{render.get('render_threads')} torch thread(s), "
                          f"{render.get('render_kernel_threads', render.get('render_threads'))} kernel worker(s)",
        "ae_epochs": epoch_rows(ae_report), "ae_sweep": ae_sweep, "machine": machine(),
    }
    write_json_atomic(out / "main_job.json", result, overwrite=True)
    with atomic_path(out / "main_job.md") as tmp:
        tmp.write_text(markdown(result))
    if result["ae_epochs"]:
        epoch_plot(out / "ae_epochs.png", result["ae_epochs"])
    print(markdown(result))
    return 0
