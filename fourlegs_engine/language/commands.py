"""CLI: ``fourlegs extract | train-ae | distill | language`` and ``fourlegs bench distill``.

Each stage works on a scene bundle, writes per-timestep results atomically into it, resumes where it
stopped, refuses results of another configuration unless ``--overwrite``, and splits across
independent workers with ``--timesteps a:b`` and ``--shard i/n``.
"""
from __future__ import annotations

import argparse
import functools
import json
import sys
import time
from pathlib import Path
from typing import Any

from ..cluster import add_ray_arguments
from ..errors import InputError

SYNTHETIC_SIZES = ("tiny", "demo", "bench", "full")


# ------------------------------------------------------------------------------------ parsers
def register(subparsers: Any) -> None:
    from .encoders import add_encoder_arguments

    p = subparsers.add_parser(
        "extract", help="teacher features: crop-pyramid video-text encodings per timestep",
        description="Encode the 8-frame crop pyramid (5 scales, stride half a crop) of every training view "
                    "and timestep into SCENE/features/ (float16 crop features, one file per timestep).")
    _scene_argument(p)
    add_encoder_arguments(p, default="simulated")
    p.add_argument("--ratios", default="0.15:0.6", help="crop ratio range low:high of the image height "
                   "(default 0.15:0.6 as for Panoptic Sports; 0.4:0.95 for animal scenes)")
    p.add_argument("--steps", type=int, default=5, help="number of pyramid scales (default 5)")
    p.add_argument("--crop-size", default=None,
                   help="crop side fed to the encoder (default 224 for RGB encoders; 'means' for label "
                        "encoders that only read per-frame coverage means)")
    p.add_argument("--batch-size", type=int, default=None,
                   help="crop tubes per encoder call (default 32 for RGB encoders, 256 otherwise)")
    p.add_argument("--frame-scale", type=float, default=1.0,
                   help="render frames at this fraction of the resolution, upsampled before cropping "
                        "(speed knob; default 1)")
    _split_arguments(p)
    p.add_argument("--check", action="store_true", help="only report finished, missing and unreadable timesteps")
    add_ray_arguments(p)
    p.set_defaults(func=run_extract)

    p = subparsers.add_parser(
        "train-ae", help="train the per-scene 768->128 feature autoencoder",
        description="Train the autoencoder on a seeded sample of per-pixel teacher features (all timesteps, "
                    "all training cameras but the held-out one); reports reconstruction cosine on the "
                    "held-out camera. Resumes from per-epoch checkpoints.")
    _scene_argument(p)
    _ae_arguments(p)
    p.add_argument("--overwrite", action="store_true", help="retrain even if a trained autoencoder exists")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=run_train_ae)

    p = subparsers.add_parser(
        "distill", help="distil the teacher into per-Gaussian latents (optimize | lift | lift+refine)",
        description="Per timestep, geometry frozen: 'lift' (learning-free weighted average, one rasterizer "
                    "pass per view), 'optimize' (the paper: attention-smoothed latents, L1 to the encoded "
                    "teacher), 'lift+refine' (lift, then --iterations optimize steps).")
    _scene_argument(p)
    _distill_arguments(p)
    _split_arguments(p)
    p.add_argument("--check", action="store_true",
                   help="report missing timesteps; merge the latents if every timestep is finished")
    add_ray_arguments(p)
    p.set_defaults(func=run_distill)

    p = subparsers.add_parser(
        "language", help="extract + train-ae + distill with defaults (the fast demo path: lift)",
        description="Run the three language stages in order; each resumes and skips finished work.")
    _scene_argument(p)
    add_encoder_arguments(p, default="simulated")
    _ae_arguments(p, epochs=LANGUAGE_AE_EPOCHS)
    _distill_arguments(p)
    p.add_argument("--overwrite", action="store_true", help="discard results of other configurations")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--frame-scale", type=float, default=1.0,
                   help="extract: render frames at this fraction of the resolution (default 1)")
    add_ray_arguments(p)
    p.set_defaults(func=run_language)


def register_bench(bench_subparsers: Any) -> None:
    p = bench_subparsers.add_parser(
        "distill", help="seconds per timestep of lift / optimize / lift+refine (JSON + Markdown)",
        description="Prepare the scene (extract, train-ae; cached in the bundle), then time each distillation "
                    "mode on a few timesteps. Deterministic; re-run with the same arguments to compare.")
    p.add_argument("--scene", default="bench",
                   help="a synthetic size (tiny, demo, bench, full) or a bundle path (default bench)")
    p.add_argument("--modes", default="lift,lift+refine,optimize",
                   help="comma-separated modes (default lift,lift+refine,optimize)")
    p.add_argument("--iterations", default="100,500,2000",
                   help="optimize iteration counts to time (default 100,500,2000)")
    p.add_argument("--refine-iterations", type=int, default=100, help="lift+refine iterations (default 100)")
    p.add_argument("--timesteps", default="0:60:20", help="timesteps to time (default 0:60:20 = 0,20,40)")
    p.add_argument("--teacher-strides", default="1,2,4", help="teacher strides to time for lift (default 1,2,4)")
    p.add_argument("--out", default=None, help="output prefix for .json/.md (default: <bundle>/bench/distill)")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")
    p.set_defaults(func=run_bench_distill)


def _scene_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", nargs="?", help="scene bundle directory")
    p.add_argument("--demo", action="store_true", help="use the built-in demo scene (generated on first use)")


def _split_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--timesteps", default=None, help="a:b (python slice, a:b:step) or a,b,c (default: all)")
    p.add_argument("--shard", default=None, help="i/n: this worker takes every n-th selected timestep from i")
    if not any(a.dest == "overwrite" for a in p._actions):
        p.add_argument("--overwrite", action="store_true", help="discard results of another configuration")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


#: the `language` (demo) path trains 2 epochs: measured on the demo scene (seed 0, 1 thread) 2 epochs
#: reach a held-out reconstruction cosine of 0.872 in 7.9 s CPU, 4 epochs 0.857 in 14.7 s
LANGUAGE_AE_EPOCHS = 2


def _ae_arguments(p: argparse.ArgumentParser, epochs: int = 4) -> None:
    g = p.add_argument_group("autoencoder")
    g.add_argument("--epochs", type=int, default=epochs, help=f"training epochs (default {epochs})")
    g.add_argument("--samples", type=int, default=32768, help="pixel features sampled for training (default 32768)")
    g.add_argument("--ae-batch-size", type=int, default=1024, help="training batch size (default 1024)")
    g.add_argument("--lr", type=float, default=7e-4, help="Adam learning rate (default 7e-4)")
    g.add_argument("--holdout-camera", type=int, default=-1, help="training camera held out (default the last)")
    g.add_argument("--seed", type=int, default=0)


def _distill_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("distillation")
    g.add_argument("--mode", default="lift", choices=("optimize", "lift", "lift+refine"), help="default lift")
    g.add_argument("--iterations", type=int, default=None,
                   help="optimizer steps per timestep (default 2000 optimize, 200 lift+refine)")
    g.add_argument("--no-attention", action="store_true", help="ablation: no smoothing (w/o Attn)")
    g.add_argument("--blur", action="store_true", help="ablation: kNN mean instead of attention (Local_Blur)")
    g.add_argument("--smoothness", type=float, default=0.0, help="ablation: kNN smoothness loss weight λ")
    g.add_argument("--neighbours", type=int, default=20, help="kNN size including the Gaussian (default 20)")
    g.add_argument("--lift-smoothing", default="none", choices=("none", "blur"),
                   help="lift / lift+refine: average each lifted latent over its --neighbours nearest "
                        "Gaussians (learning-free kNN blur; default none)")
    g.add_argument("--views-per-iteration", type=int, default=1, help="views rendered per step (default 1)")
    g.add_argument("--teacher-stride", type=int, default=4,
                   help="encode the teacher every n-th pixel and upsample (default 4; 1 = every pixel)")
    g.add_argument("--view-scale", type=float, default=1.0,
                   help="render the training views at this fraction of their resolution (default 1)")
    g.add_argument("--distill-seed", type=int, default=0)


# ------------------------------------------------------------------------------------ helpers
def resolve_bundle(args: argparse.Namespace):
    """The bundle scene named by ``args.scene`` / ``--demo`` (loaded, memory-mapped)."""
    from ..scene.bundle import is_bundle, load_bundle
    if bool(getattr(args, "demo", False)) == bool(args.scene):
        raise InputError("give either a scene bundle or --demo (exactly one)", field="scene")
    if args.demo:
        from ..eval.synthetic import ensure_demo_bundle
        return load_bundle(ensure_demo_bundle())
    path = Path(args.scene)
    if not is_bundle(path):
        raise InputError("is not a scene bundle; the language stages write into a bundle (convert the scene "
                         "first, e.g. with the scene loaders + write_bundle)", file=path)
    return load_bundle(path)


def _ratios(spec: str, steps: int) -> tuple[float, ...]:
    from .pyramid import pyramid_ratios
    try:
        low, high = (float(v) for v in spec.split(":"))
    except ValueError:
        raise InputError(f"cannot parse {spec!r}; use low:high, e.g. 0.15:0.6", field="--ratios") from None
    return pyramid_ratios(low, high, steps)


def _crop_size(value: str | None) -> int | str | None:
    if value is None or value == "means":
        return value
    try:
        size = int(value)
    except ValueError:
        raise InputError(f"must be an integer or 'means', got {value!r}", field="--crop-size") from None
    if size < 1:
        raise InputError(f"must be positive, got {size}", field="--crop-size")
    return size


def _encoder(args: argparse.Namespace, scene: Any):
    from .encoders import load_encoder_from_args
    extra = {"scene": scene} if (getattr(args, "encoder", "") or "").startswith("simulated") else {}
    return load_encoder_from_args(args, **extra)


def _ae_config(args: argparse.Namespace):
    from .autoencoder import AETrainConfig
    return AETrainConfig(epochs=args.epochs, samples=args.samples, batch_size=args.ae_batch_size, lr=args.lr,
                         holdout_camera=args.holdout_camera, seed=args.seed)


def _distill_config(args: argparse.Namespace):
    from .distill import DistillConfig
    if args.no_attention and args.blur:
        raise InputError("choose at most one of --no-attention and --blur", field="--blur")
    smoothing = "none" if args.no_attention else ("blur" if args.blur else "attention")
    return DistillConfig(mode=args.mode, iterations=args.iterations, smoothing=smoothing,
                         smoothness=args.smoothness, neighbours=args.neighbours,
                         views_per_iteration=args.views_per_iteration, teacher_stride=args.teacher_stride,
                         view_scale=args.view_scale, seed=args.distill_seed,
                         lift_smoothing=args.lift_smoothing).check()


def _print_check(report: dict[str, Any]) -> int:
    print(json.dumps(report, indent=2))
    return 0 if report.get("complete") else 1


# ----------------------------------------------------------------------------------- commands
def run_extract(args: argparse.Namespace) -> int:
    from .extract import ExtractConfig, check_features, extract_features
    scene = resolve_bundle(args)
    if args.check:
        return _print_check(check_features(scene))
    if args.batch_size is not None and args.batch_size < 1:
        raise InputError(f"must be >= 1, got {args.batch_size}", field="--batch-size")
    config = ExtractConfig(ratios=_ratios(args.ratios, args.steps), crop_size=_crop_size(args.crop_size),
                           batch_size=args.batch_size, frame_scale=args.frame_scale)
    if args.ray is not None:
        from ..cluster import cli_extract
        report = cli_extract(args, scene, functools.partial(_encoder, args), config, timesteps=args.timesteps,
                             shard=args.shard)
    else:
        report = extract_features(scene, _encoder(args, scene), config, timesteps=args.timesteps, shard=args.shard,
                                  overwrite=args.overwrite, progress=not args.no_progress)
    print(f"extract: {len(report.timesteps_done)} timestep(s) encoded, {len(report.timesteps_skipped)} already "
          f"done, {report.seconds:.1f} s (render {report.render_seconds:.1f} s, encoder "
          f"{report.encode_seconds:.1f} s), {report.crops_per_timestep} crops per timestep")
    return 0


def run_train_ae(args: argparse.Namespace) -> int:
    from .autoencoder import train_autoencoder
    scene = resolve_bundle(args)
    report = train_autoencoder(scene, _ae_config(args), overwrite=args.overwrite, progress=True)
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        held = report.get("heldout_cosine")
        print(f"train-ae: {'already trained' if report.get('skipped') else 'trained'}; reconstruction cosine "
              f"held-out view {held if held is None else round(held, 4)}, training views "
              f"{report.get('train_cosine', float('nan')):.4f}")
    return 0


def run_distill(args: argparse.Namespace) -> int:
    from .distill import check_distill, distill_scene
    scene = resolve_bundle(args)
    if args.check:
        report = check_distill(scene)
        if report.get("missing") == [] and not report.get("bad") and not report.get("merged"):
            # every timestep is finished (workers split the work): merge now
            result = distill_scene(scene, config=_distill_config(args), progress=False)
            report = check_distill(scene)
            report["merged_into"] = result.latents
        return _print_check(report)
    if args.ray is not None:
        from ..cluster import cli_distill
        result = cli_distill(args, scene, _distill_config(args), timesteps=args.timesteps, shard=args.shard)
    else:
        result = distill_scene(scene, config=_distill_config(args), timesteps=args.timesteps, shard=args.shard,
                               overwrite=args.overwrite, progress=not args.no_progress)
    done = len(result.timings)
    msg = f"distill ({result.mode}): {done} timestep(s) distilled, {len(result.skipped)} already done"
    if done:
        msg += f", {result.seconds_per_timestep:.2f} s per timestep"
        its = [t.seconds_per_iteration for t in result.timings if t.seconds_per_iteration]
        if its:
            msg += f", {sum(its) / len(its):.3f} s per iteration"
    msg += f"; latents: {result.latents}" if result.latents else "; latents are merged when every timestep is done"
    print(msg)
    return 0


def run_language(args: argparse.Namespace) -> int:
    from .autoencoder import train_autoencoder
    from .distill import distill_scene
    from .extract import ExtractConfig, extract_features
    scene = resolve_bundle(args)
    progress = not args.no_progress
    t0 = time.perf_counter()
    if args.ray is not None:
        from ..cluster import cli_extract
        rep = cli_extract(args, scene, functools.partial(_encoder, args), ExtractConfig(frame_scale=args.frame_scale))
    else:
        rep = extract_features(scene, _encoder(args, scene), ExtractConfig(frame_scale=args.frame_scale),
                               overwrite=args.overwrite, progress=progress)
    t1 = time.perf_counter()
    ae = train_autoencoder(scene, _ae_config(args), overwrite=args.overwrite, progress=progress)
    t2 = time.perf_counter()
    if args.ray is not None:
        from ..cluster import cli_distill
        result = cli_distill(args, scene, _distill_config(args))
    else:
        result = distill_scene(scene, config=_distill_config(args), overwrite=args.overwrite, progress=progress)
    t3 = time.perf_counter()
    print(f"language: extract {t1 - t0:.1f} s ({len(rep.timesteps_done)} new), train-ae {t2 - t1:.1f} s "
          f"(held-out cosine {ae.get('heldout_cosine')}), distill {t3 - t2:.1f} s; latents: {result.latents}")
    return 0


# ------------------------------------------------------------------------------------ benchmark
def run_bench_distill(args: argparse.Namespace) -> int:
    import torch
    from ..scene.bundle import load_bundle
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.scene in SYNTHETIC_SIZES:
        from ..eval.synthetic import ensure_demo_bundle
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
    from .autoencoder import ENCODER_FILE, load_encoder, train_autoencoder
    from .distill import DistillConfig, distill_scene, fidelity_reference, render_fidelity
    from .encoders import get_encoder
    from .extract import extract_features, feature_store
    from .store import select_timesteps

    root = Path(scene.root)
    prep = time.perf_counter()
    steps = select_timesteps(scene.num_timesteps, timesteps)
    # every timestep (cached): the autoencoder trained here is then the scene's own, the one the query
    # pipeline would train, instead of one fitted to the timed subset that later runs refuse to mix with
    extract_features(scene, get_encoder("simulated", scene=scene), progress=progress)
    ae = train_autoencoder(scene, progress=progress)
    prep = time.perf_counter() - prep
    runs: list[tuple[str, DistillConfig]] = []
    for mode in modes:
        if mode == "lift":
            runs += [(f"lift (teacher stride {s})", DistillConfig(mode="lift", teacher_stride=s))
                     for s in teacher_strides]
            runs.append(("lift (views at 0.5x, teacher stride 1)",
                         DistillConfig(mode="lift", teacher_stride=1, view_scale=0.5)))
        elif mode == "lift+refine":
            runs.append((f"lift+refine {refine_iterations}",
                         DistillConfig(mode="lift+refine", iterations=refine_iterations)))
        elif mode == "optimize":
            runs += [(f"optimize {n}", DistillConfig(mode="optimize", iterations=n)) for n in optimize_iterations]
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
    from .store import StepStore
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
    from ..fileio import write_bytes_atomic, write_json_atomic
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
