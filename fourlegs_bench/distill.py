"""``fourlegs bench distill``: seconds per timestep and fidelity of every distillation mode, in one run."""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from fourlegs_engine.errors import InputError

SYNTHETIC_SIZES = ("tiny", "demo", "bench", "full")


def run_bench_distill(args: argparse.Namespace) -> int:
    import torch
    from fourlegs_engine.scene.bundle import load_bundle
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.scene in SYNTHETIC_SIZES:
        from fourlegs_engine.demo.synthetic import ensure_demo_bundle
        path = ensure_demo_bundle(args.scene)
    else:
        path = Path(args.scene)
    scene = load_bundle(path)
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    iters = [int(v) for v in args.iterations.split(",") if v.strip()]
    strides = [int(v) for v in args.teacher_strides.split(",") if v.strip()]
    report = bench_distill(scene, modes=modes, optimize_iterations=iters, refine_iterations=args.refine_iterations,
                           timesteps=args.timesteps, teacher_strides=strides, progress=True)
    prefix = Path(args.out) if args.out else Path(scene.root) / "bench" / "distill"
    json_path, md_path = write_bench_report(report, prefix)
    print(md_path.read_text())
    print(f"written: {json_path} and {md_path}", file=sys.stderr)
    return 0


def bench_distill(scene: Any, *, modes: list[str], optimize_iterations: list[int], refine_iterations: int,
                  timesteps: str, teacher_strides: list[int], progress: bool = False) -> dict[str, Any]:
    """Seconds per timestep of every mode/knob and its distillation fidelity, in one run.

    Prepares the scene first (extract with the simulated encoder, train-ae; both cached in the bundle).
    Fidelity of a result = mean over the training views of the L1 distance and the cosine between the
    rendered latent map and the encoded teacher (stride 1) on covered pixels (alpha > 0.5).
    """
    import shutil
    import torch
    from fourlegs_engine.language.autoencoder import ENCODER_FILE, load_encoder, train_autoencoder
    from fourlegs_engine.language.distill import DistillOptions, distill_scene, fidelity_reference, render_fidelity
    import fourlegs_engine.demo  # noqa: F401 (registers the "simulated" encoder)
    from fourlegs_engine.language.encoders import get_encoder
    from fourlegs_engine.language.extract import extract_features, feature_store
    from fourlegs_engine.language.store import select_timesteps

    root = Path(scene.root)
    prep = time.perf_counter()
    steps = select_timesteps(scene.num_timesteps, timesteps)
    # every timestep (cached): the autoencoder trained here is then the scene's own, the one the query
    # pipeline would train, instead of one fitted to the timed subset that later runs refuse to mix with
    extract_features(scene, get_encoder("simulated", scene=scene), progress=progress)
    ae = train_autoencoder(scene, progress=progress)
    prep = time.perf_counter() - prep
    runs: list[tuple[str, DistillOptions]] = []
    for mode in modes:
        if mode == "lift":
            runs += [(f"lift (teacher stride {s})", DistillOptions(mode="lift", teacher_stride=s))
                     for s in teacher_strides]
            runs.append(("lift (views at 0.5x, teacher stride 1)",
                         DistillOptions(mode="lift", teacher_stride=1, view_scale=0.5)))
        elif mode == "lift+refine":
            runs.append((f"lift+refine {refine_iterations}",
                         DistillOptions(mode="lift+refine", iterations=refine_iterations)))
        elif mode == "optimize":
            runs += [(f"optimize {n}", DistillOptions(mode="optimize", iterations=n)) for n in optimize_iterations]
        else:
            raise InputError(f"unknown mode {mode!r}", field="--modes")
    encoder = load_encoder(root / ENCODER_FILE)
    features = feature_store(scene)
    rows, outs = [], []
    for label, cfg in runs:
        out = root / "bench" / ("distill-" + "".join(ch if ch.isalnum() or ch in "+." else "-" for ch in label))
        shutil.rmtree(out, ignore_errors=True)
        result = distill_scene(scene, config=cfg, timesteps=steps, out_dir=out, merge=False, progress=progress)
        outs.append((out, result.config))
        tim = result.timings
        rows.append({
            "run": label, "mode": cfg.mode, "iterations": cfg.num_iterations, "teacher_stride": cfg.teacher_stride,
            "view_scale": cfg.view_scale,
            "seconds_per_timestep": sum(t.seconds for t in tim) / len(tim),
            "weights_seconds": sum(t.weights_seconds for t in tim) / len(tim),
            "teacher_seconds": sum(t.teacher_seconds for t in tim) / len(tim),
            "lift_seconds": sum(t.lift_seconds for t in tim) / len(tim),
            "optimize_seconds": sum(t.optimize_seconds for t in tim) / len(tim),
            "seconds_per_iteration": (sum(t.optimize_seconds for t in tim) / sum(t.iterations for t in tim)
                                      if any(t.iterations for t in tim) else None),
        })
    # fidelity: one full-resolution reference (weights + stride-1 teacher) per timestep, shared by all runs
    from fourlegs_engine.language.store import StepStore
    fid: list[list[dict[str, float]]] = [[] for _ in runs]
    for t in steps:
        reference = fidelity_reference(scene, t, encoder, features)
        for i, (out, cfg_dict) in enumerate(outs):
            store = StepStore(out / "steps", "latents", cfg_dict, scene.num_timesteps)
            lat = torch.from_numpy(store.load(t, mmap=False).astype("float32"))
            fid[i].append(render_fidelity(reference, lat))
        del reference
    for row, f, (out, _) in zip(rows, fid, outs):
        row["render_l1"] = sum(x["l1"] for x in f) / len(f)
        row["render_cosine"] = sum(x["cosine"] for x in f) / len(f)
        shutil.rmtree(out, ignore_errors=True)
    import torch as _torch
    return {"benchmark": "distill", "scene": scene.name, "num_gaussians": scene.num_gaussians,
            "num_cameras": scene.cameras.num_cameras("train"),
            "image_size": [scene.cameras.cameras(0)[0].width, scene.cameras.cameras(0)[0].height],
            "timesteps": steps, "threads": _torch.get_num_threads(), "prepare_seconds": prep,
            "autoencoder_heldout_cosine": ae.get("heldout_cosine"), "rows": rows}


def write_bench_report(report: dict[str, Any], prefix: Path) -> tuple[Path, Path]:
    """Write ``prefix.json`` and ``prefix.md`` (a table) atomically."""
    from fourlegs_engine.fileio import write_bytes_atomic, write_json_atomic
    json_path, md_path = prefix.with_suffix(".json"), prefix.with_suffix(".md")
    write_json_atomic(json_path, report)
    lines = [f"# Distillation benchmark: {report['scene']}",
             "",
             f"{report['num_gaussians']:,} Gaussians, {report['num_cameras']} training cameras, "
             f"{report['image_size'][0]}x{report['image_size'][1]}, timesteps {report['timesteps']}, "
             f"{report['threads']} torch threads. Fidelity: rendered latents vs. encoded teacher on covered "
             "pixels of all training views (L1 lower is better, cosine higher is better).",
             "",
             "| run | s / timestep | weights s | teacher s | lift s | optimize s | s / iteration | L1 | cosine |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in report["rows"]:
        spi = "-" if r["seconds_per_iteration"] is None else f"{r['seconds_per_iteration']:.3f}"
        lines.append(f"| {r['run']} | {r['seconds_per_timestep']:.2f} | {r['weights_seconds']:.2f} | "
                     f"{r['teacher_seconds']:.2f} | {r['lift_seconds']:.2f} | {r['optimize_seconds']:.2f} | {spi} | "
                     f"{r['render_l1']:.4f} | {r['render_cosine']:.4f} |")
    write_bytes_atomic(md_path, ("\n".join(lines) + "\n").encode())
    return json_path, md_path
