"""CLI: ``fourlegs extract | train-ae | distill | language``.

Each stage works on a scene bundle, writes per-timestep results atomically into it, resumes where it
stopped, refuses results of another configuration unless ``--overwrite``, and splits across
independent workers with ``--timesteps a:b`` and ``--shard i/n``.
"""
from __future__ import annotations

import argparse
import functools
import json
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from ..errors import InputError
from .options import add_demo_argument, add_ray_arguments, ray_options_from_args
from .plan_options import plan_and_check

if TYPE_CHECKING:
    from ..language.distill import DistillOptions, DistillResult
    from ..language.extract import ExtractOptions, ExtractReport
    from ..scene.scene import Scene


# ------------------------------------------------------------------------------------ parsers
def register(subparsers: Any) -> None:
    from .options import add_encoder_arguments
    from .plan_options import add_plan_arguments

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
    add_plan_arguments(p)
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
    _ae_arguments(p)  # the main job's epochs: fewer reconstruct as well but leave queries unanswered
    _distill_arguments(p)
    p.add_argument("--overwrite", action="store_true", help="discard results of other configurations")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--frame-scale", type=float, default=1.0,
                   help="extract: render frames at this fraction of the resolution (default 1)")
    add_plan_arguments(p)
    add_ray_arguments(p)
    p.set_defaults(func=run_language)


def _scene_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", nargs="?", help="scene bundle directory")
    add_demo_argument(p)


def _split_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--timesteps", default=None, help="a:b (python slice, a:b:step) or a,b,c (default: all)")
    p.add_argument("--shard", default=None, help="i/n: this worker takes every n-th selected timestep from i")
    if not any(a.dest == "overwrite" for a in p._actions):
        p.add_argument("--overwrite", action="store_true", help="discard results of another configuration")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _ae_arguments(p: argparse.ArgumentParser, epochs: int = 4) -> None:
    g = p.add_argument_group("autoencoder")
    g.add_argument("--epochs", type=int, default=epochs, help=f"training epochs (default {epochs})")
    g.add_argument("--samples", type=int, default=32768, help="pixel features sampled for training (default 32768)")
    g.add_argument("--ae-batch-size", type=int, default=1024, help="training batch size (default 1024)")
    g.add_argument("--lr", type=float, default=7e-4, help="Adam learning rate (default 7e-4)")
    g.add_argument("--holdout-camera", type=int, default=-1,
                   help="training camera held out (default the last one with evidence)")
    g.add_argument("--ae-balance", choices=("auto", "directions", "none"), default="auto",
                   help="training sample: an equal share per cluster of feature directions, so a small object's "
                        "label is learnt (directions), or uniform over pixels (none); auto: directions for "
                        "annotation masks, else none")
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
        from ..demo.synthetic import ensure_demo_bundle
        return load_bundle(ensure_demo_bundle())
    path = Path(args.scene)
    if not is_bundle(path):
        raise InputError("is not a scene bundle; the language stages write into a bundle (convert the scene "
                         "first, e.g. with the scene loaders + write_bundle)", file=path)
    return load_bundle(path)


def _ratios(spec: str, steps: int) -> tuple[float, ...]:
    from ..language.pyramid import pyramid_ratios
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
    if not 1 <= size <= 4096:
        raise InputError(f"must be 1..4096 pixels, got {size}", field="--crop-size")
    return size


def _encoder(args: argparse.Namespace, scene: Any):
    from .options import encoder_options_from_args
    from ..pipeline import text_encoder
    return text_encoder(scene, encoder_options_from_args(args))


def _ae_options(args: argparse.Namespace):
    from ..language.autoencoder import AETrainOptions
    return AETrainOptions(epochs=args.epochs, samples=args.samples, batch_size=args.ae_batch_size, lr=args.lr,
                         holdout_camera=args.holdout_camera, seed=args.seed, balance=args.ae_balance)


def _distill_options(args: argparse.Namespace):
    from ..language.distill import DistillOptions
    if args.no_attention and args.blur:
        raise InputError("choose at most one of --no-attention and --blur", field="--blur")
    smoothing = "none" if args.no_attention else ("blur" if args.blur else "attention")
    return DistillOptions(mode=args.mode, iterations=args.iterations, smoothing=smoothing,
                         smoothness=args.smoothness, neighbours=args.neighbours,
                         views_per_iteration=args.views_per_iteration, teacher_stride=args.teacher_stride,
                         view_scale=args.view_scale, seed=args.distill_seed,
                         lift_smoothing=args.lift_smoothing).check()


def _print_evidence(encoder: Any, scene: Any, split: str = "train") -> None:
    """What annotation masks cover (the encoder reads masks); nothing for other encoders."""
    if hasattr(encoder, "evidence_line"):
        encoder.check_masks(scene.cameras.cameras(0, split), scene.num_timesteps)
        print(encoder.evidence_line())


def _lock_scene(args: argparse.Namespace, scene: Any) -> None:
    """Hold the scene's run lock until the command ends (shared by ``--shard`` workers of one stage)."""
    from ..runlock import hold_run_lock
    hold_run_lock(scene.root, shared=bool(getattr(args, "shard", None)))


def _print_check(report: dict[str, Any]) -> int:
    print(json.dumps(report, indent=2))
    return 0 if report.get("complete") else 1


# ----------------------------------------------------------------------------------- commands
def run_extract(args: argparse.Namespace) -> int:
    from ..language.extract import ExtractOptions, check_features, extract_features
    scene = resolve_bundle(args)
    if args.check:
        return _print_check(check_features(scene))
    _lock_scene(args, scene)
    if args.batch_size is not None and args.batch_size < 1:
        raise InputError(f"must be >= 1, got {args.batch_size}", field="--batch-size")
    config = ExtractOptions(ratios=_ratios(args.ratios, args.steps), crop_size=_crop_size(args.crop_size),
                           batch_size=args.batch_size, frame_scale=args.frame_scale)
    encoder = _encoder(args, scene)
    config, go = plan_and_check(args, scene, encoder, config, timesteps=args.timesteps, shard=args.shard)
    if not go:
        return 0
    if args.ray is not None:
        report = extract_with_ray(args, scene, functools.partial(_encoder, args), config, timesteps=args.timesteps,
                             shard=args.shard)
    else:
        report = extract_features(scene, encoder, config, timesteps=args.timesteps, shard=args.shard,
                                  overwrite=args.overwrite, progress=not args.no_progress)
        _print_evidence(encoder, scene, config.split)
    filled = f", {len(report.timesteps_filled)} filled" if report.timesteps_filled else ""
    copied = f", {report.clips_copied} copied by the early exit" if report.clips_copied else ""
    print(f"extract: {len(report.timesteps_done)} timestep(s) encoded{filled}, {len(report.timesteps_skipped)} "
          f"already done, {report.seconds:.1f} s (render {report.render_seconds:.1f} s, encoder "
          f"{report.encode_seconds:.1f} s), {report.clips_encoded} clips encoded{copied}, "
          f"{report.crops_per_timestep} crops per timestep")
    return 0


def run_train_ae(args: argparse.Namespace) -> int:
    from ..language.autoencoder import train_autoencoder
    scene = resolve_bundle(args)
    _lock_scene(args, scene)
    report = train_autoencoder(scene, _ae_options(args), overwrite=args.overwrite, progress=True)
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print(f"train-ae: {'already trained' if report.get('skipped') else 'trained'}; reconstruction cosine: "
              f"{heldout_text(report)}, training views {report.get('train_cosine', float('nan')):.4f}")
    return 0


def build_query_index(scene: "Scene") -> str:
    """The default query path's index (the per-pair sketch; the codebook for a field without a relevancy
    head) built once beside the new field, so that the first query answers as fast as the later ones;
    returns a line saying what it did."""
    from ..pipeline import open_query_engine, text_encoder
    from ..scene.bundle import load_bundle

    start = time.perf_counter()
    fresh = load_bundle(Path(scene.root))
    engine = open_query_engine(fresh, text_encoder(fresh))
    engine.load_index()
    what = (f"sketch rank {engine.options.sketch_rank}" if engine.path == "sketch" and engine.sketch_path.available
            else f"codebook K={engine.options.codebook_size}")
    return f"query index ({what}) ready in {time.perf_counter() - start:.1f} s"


def heldout_text(report: dict) -> str:
    """The autoencoder report's held-out reconstruction cosine in words (which camera, or why none)."""
    cosine, camera = report.get("heldout_cosine"), report.get("heldout_camera")
    if cosine is not None:
        return f"held-out camera {camera} cosine {cosine:.4f}"
    return f"no held-out cosine: {report.get('heldout_note') or 'the held-out camera has no evidence'}"


def run_distill(args: argparse.Namespace) -> int:
    from ..language.distill import check_distill, distill_scene
    scene = resolve_bundle(args)
    _lock_scene(args, scene)
    if args.check:
        report = check_distill(scene)
        if report.get("missing") == [] and not report.get("bad") and not report.get("merged"):
            # every timestep is finished (workers split the work): merge now
            result = distill_scene(scene, config=_distill_options(args), progress=False)
            report = check_distill(scene)
            report["merged_into"] = result.latents
        return _print_check(report)
    if args.ray is not None:
        result = distill_with_ray(args, scene, _distill_options(args), timesteps=args.timesteps, shard=args.shard)
    else:
        result = distill_scene(scene, config=_distill_options(args), timesteps=args.timesteps, shard=args.shard,
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
    from ..language.autoencoder import train_autoencoder
    from ..language.distill import distill_scene
    from ..language.extract import ExtractOptions, extract_features
    scene = resolve_bundle(args)
    _lock_scene(args, scene)
    progress = not args.no_progress
    t0 = time.perf_counter()
    encoder = _encoder(args, scene)
    config, go = plan_and_check(args, scene, encoder, ExtractOptions(frame_scale=args.frame_scale))
    if not go:
        return 0
    if args.ray is not None:
        rep = extract_with_ray(args, scene, functools.partial(_encoder, args), config)
    else:
        rep = extract_features(scene, encoder, config, overwrite=args.overwrite, progress=progress)
    _print_evidence(encoder, scene)
    t1 = time.perf_counter()
    ae = train_autoencoder(scene, _ae_options(args), overwrite=args.overwrite, progress=progress)
    t2 = time.perf_counter()
    if args.ray is not None:
        result = distill_with_ray(args, scene, _distill_options(args))
    else:
        result = distill_scene(scene, config=_distill_options(args), overwrite=args.overwrite, progress=progress)
    t3 = time.perf_counter()
    index = build_query_index(scene) if result.latents else "query index: built on the first query"
    print(f"language: extract {t1 - t0:.1f} s ({len(rep.timesteps_done)} new), train-ae {t2 - t1:.1f} s "
          f"({heldout_text(ae)}), distill {t3 - t2:.1f} s; latents: {result.latents}; {index}")
    return 0


def extract_with_ray(args: argparse.Namespace, scene: "Scene", encoder_factory: Callable[["Scene"], Any],
                config: "ExtractOptions", *, timesteps: Any = None, shard: Any = None) -> "ExtractReport":
    """``fourlegs extract|language --ray``: extraction on the cluster; prints a one-line task summary."""
    from ..cluster.stages import extract_on_ray as run_on_ray

    report, tasks = run_on_ray(scene, encoder_factory, config, timesteps=timesteps, shard=shard,
                               overwrite=args.overwrite, progress=not args.no_progress,
                               options=ray_options_from_args(args), device=getattr(args, "device", None))
    print(tasks.summary(), flush=True)
    return report


def distill_with_ray(args: argparse.Namespace, scene: "Scene", config: "DistillOptions", *, timesteps: Any = None,
                shard: Any = None) -> "DistillResult":
    """``fourlegs distill|language --ray``: distillation on the cluster, merged when complete."""
    from ..cluster.stages import distill_on_ray as run_on_ray

    result, tasks = run_on_ray(scene, config, timesteps=timesteps, shard=shard, overwrite=args.overwrite,
                               progress=not args.no_progress, options=ray_options_from_args(args))
    print(tasks.summary(), flush=True)
    return result
