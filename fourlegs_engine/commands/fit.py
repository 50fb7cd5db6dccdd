"""``fourlegs fit DATASET -o SCENE``: fit dynamic Gaussians to a calibrated multiview video."""
from __future__ import annotations

import argparse
import functools
from pathlib import Path
from typing import Any, Sequence

from ..errors import InputError
from ..fit.presets import FIT_PRESETS
from .options import add_ray_arguments, ray_options_from_args, uses_ray


def parse_timesteps(text: str) -> tuple[int, int]:
    """``"a:b"`` (half-open; ``b`` may be empty for the end, then -1) or ``"a"`` (that one timestep)."""
    try:
        if ":" in text:
            a, b = text.split(":", 1)
            return int(a or 0), int(b) if b.strip() else -1
        t = int(text)
        return t, t + 1
    except ValueError:
        raise InputError(f"must look like a:b (e.g. 0:150), got {text!r}", field="--timesteps") from None


def parse_cameras(text: str) -> tuple[str, ...]:
    ids = tuple(s.strip() for s in text.split(",") if s.strip())
    if not ids:
        raise InputError("must list camera ids separated by commas (e.g. 1,2,5)", field="--cameras")
    return ids


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "fit", help="fit dynamic 3D Gaussians to a calibrated multiview video (Dynamic 3D Gaussians layout)",
        description="Fit dynamic 3D Gaussians (Luiten et al. 3DV 2024) to DATASET (train_meta.json, "
        "test_meta.json, ims/, optional seg/) and write a scene bundle. Finished timesteps are kept beside "
        "the output; run the same command again after a cancel to resume. Several datasets are fitted one "
        "after the other, or side by side as Ray tasks with --ray (one task per dataset: a fit's timesteps "
        "depend on each other).")
    p.add_argument("dataset", nargs="+", help="dataset directory (several: one scene each, in OUTPUT/NAME)")
    p.add_argument("-o", "--output", required=True,
                   help="scene bundle directory to write (several datasets: the folder of their bundles)")
    p.add_argument("--timesteps", type=str, default=None, help="half-open range a:b (default: all)")
    p.add_argument("--cameras", type=str, default=None, help="training camera ids, comma separated (default: all)")
    p.add_argument("--preset", choices=tuple(FIT_PRESETS), default="default",
                   help="knob set: default (320x180, about 16 CPU minutes for 150 timesteps) or accurate (640x360, "
                   "hours); the options below override it")
    p.add_argument("--resolution-scale", type=float, default=None,
                   help="image scale for fitting (default: the preset's, 0.5 for default)")
    p.add_argument("--first-iterations", type=int, default=None, help="steps of the first (static) timestep")
    p.add_argument("--iterations", type=int, default=None,
                   help="steps of every later timestep (with --max-iterations: the base of the residual-driven schedule)")
    p.add_argument("--max-iterations", type=int, default=None,
                   help="cap of the residual-driven schedule: later timesteps get more steps where the forecast "
                   "misses the moving pixels (0: every later timestep gets --iterations)")
    p.add_argument("--min-iterations", type=int, default=None, help="floor of the residual-driven schedule")
    p.add_argument("--max-gaussians", type=int, default=None, help="cap on the number of Gaussians")
    p.add_argument("--motion-step-range", type=float, default=None,
                   help="later timesteps scale each centre's steps by its speed over the median, within "
                        "[1/range, range] (default 1: the same step for all)")
    p.add_argument("--part-extent", type=float, default=None,
                   help="later timesteps first move rigid parts of the foreground (what touches, cut to at most "
                   "this many metres) so a thrown ball follows whole (default 0.4; 0: off)")
    p.add_argument("--lr-colors-later", type=float, default=None,
                   help="later timesteps also fit the foreground's colours at this learning rate, so the scene's "
                   "colours vary per timestep (default 0.0025, the paper's code's; 0: the first timestep's "
                   "throughout)")
    p.add_argument("--init", choices=("hull", "features", "hull+features"), default=None,
                   help="initial Gaussians: visual hull + background proxy (hull), triangulated SIFT matches "
                   "(features, needs OpenCV: pip install 'fourlegs[fit-features]') or both (default: hull)")
    p.add_argument("--init-foreground", type=int, default=None, help="cap on initial visual-hull points")
    p.add_argument("--init-background", type=int, default=None, help="cap on initial background points")
    p.add_argument("--no-densify", action="store_true", help="no clone/split/prune in the first timestep")
    p.add_argument("--clean-plate-samples", type=int, default=None,
                   help="timesteps whose background pixels make each camera's clean plate, the first timestep's "
                   "background target (default 8; 0: none)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto")
    p.add_argument("--overwrite", action="store_true", help="replace SCENE / restart a partial fit with other options")
    p.add_argument("--no-test-psnr", action="store_true",
                   help="skip the closing PSNR/SSIM of the capture's test cameras (held out of the fit)")
    add_ray_arguments(p)
    p.set_defaults(func=run_fit)


def options_from_args(args: argparse.Namespace):
    """:class:`~fourlegs_engine.fit.FitOptions` from parsed arguments (unset knobs keep their defaults)."""
    from ..fit.options import preset_options

    kw: dict[str, Any] = {"seed": args.seed, "device": args.device, "densify": not args.no_densify}
    if args.resolution_scale is not None:
        kw["resolution_scale"] = args.resolution_scale
    if args.timesteps is not None:
        kw["timesteps"] = parse_timesteps(args.timesteps)
    if args.cameras is not None:
        kw["cameras"] = parse_cameras(args.cameras)
    for name in ("first_iterations", "iterations", "max_iterations", "min_iterations", "max_gaussians", "init",
                 "init_foreground", "init_background", "clean_plate_samples", "motion_step_range", "part_extent",
                 "lr_colors_later"):
        if getattr(args, name) is not None:
            kw[name] = getattr(args, name)
    return preset_options(args.preset, **kw)


def scene_outputs(datasets: Sequence[str], output: str) -> list[Path]:
    """Where each dataset's scene goes: OUTPUT itself for one dataset, OUTPUT/<dataset folder name> for several."""
    if len(datasets) == 1:
        return [Path(output)]
    names = [Path(d).resolve().name for d in datasets]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise InputError(f"datasets share the folder name {', '.join(repeated)}: their scenes would collide in "
                         f"{output}; fit them in separate commands", field="dataset")
    return [Path(output) / n for n in names]


def fit_one(job: tuple[str, str], *, options: Any, overwrite: bool, progress: bool, check_test_frames: bool = True) -> str:
    """Fit one ``(dataset, output)`` pair; returns the scene path (a Ray task's function)."""
    from ..fit.fitter import fit_capture

    from ..runlock import run_lock

    dataset, output = job
    with run_lock(output):  # one fit per output scene
        return str(fit_capture(dataset, output, options, overwrite=overwrite, progress=progress,
                               check_test_frames=check_test_frames))


def run_fit(args: argparse.Namespace) -> int:
    from ..cluster.runner import map_on_ray

    options = options_from_args(args)
    jobs = [(str(d), str(o)) for d, o in zip(args.dataset, scene_outputs(args.dataset, args.output))]
    if uses_ray(args):
        ray_options = ray_options_from_args(args)
        if not ray_options.shared_fs:
            raise InputError("fit reads its dataset and writes its scene in place: the datasets and the output "
                             "must be on a filesystem every node sees", field="--ray-no-shared-fs")
        gpus = ray_options.num_gpus if ray_options.num_gpus is not None else float(args.device == "cuda")
        task = functools.partial(fit_one, options=options, overwrite=args.overwrite, progress=False,
                                 check_test_frames=not args.no_test_psnr)
        written = map_on_ray(task, jobs, options=ray_options, stage="fit", num_gpus=gpus)
    else:
        written = [fit_one(job, options=options, overwrite=args.overwrite, progress=True,
                           check_test_frames=not args.no_test_psnr) for job in jobs]
    for (dataset, _), path in zip(jobs, written):
        print(f"wrote {path}")
        if not args.no_test_psnr:
            print(test_view_line(path, dataset, options.resolution_scale), flush=True)
    return 0


def test_view_line(scene: str, dataset: str, resolution_scale: float) -> str:
    """One line: the fitted scene's mean PSNR and SSIM on the capture's test cameras (held out of the fit)."""
    import numpy as np

    from ..fit.evaluate import evaluate_test_views

    metrics = evaluate_test_views(scene, dataset, resolution_scale=resolution_scale)
    if not metrics.psnr.size:
        return "test cameras: none in the capture (no held-out PSNR)"
    worst = np.unravel_index(int(np.argmin(metrics.psnr)), metrics.psnr.shape)
    return (f"test cameras {', '.join(metrics.cameras)}: PSNR {metrics.mean_psnr:.2f} dB, SSIM {metrics.mean_ssim:.3f} "
            f"(mean over {metrics.psnr.shape[0]} timesteps; lowest {metrics.psnr[worst]:.2f} dB, camera "
            f"{metrics.cameras[worst[1]]} at t={metrics.timesteps[worst[0]]})")
