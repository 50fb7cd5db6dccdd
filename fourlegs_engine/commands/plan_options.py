"""The extraction plan's command-line options (``extract`` and ``language``): the named plan, each cost
knob, the time budget and the dry run; and the step that prints the plan and refuses one above budget."""
from __future__ import annotations

import argparse
from typing import Any

from ..errors import InputError
from .options import bounded


def add_plan_arguments(parser: argparse.ArgumentParser) -> None:
    """``--plan`` and its knobs, ``--budget``, ``--over-budget``, ``--dry-run``."""
    from ..language.plans import EARLY_EXITS, FILL_MODES, PLAN_NAMES

    g = parser.add_argument_group("plan (what the teacher features cost; docs/benchmarks_language_cost.md)")
    g.add_argument("--plan", default="auto", choices=PLAN_NAMES,
                   help="full: the paper's extraction (every camera and timestep, 5-level pyramid, half-crop "
                        "overlap); default: the measured cheap plan; auto (default): 'default' for ViCLIP, 'full' "
                        "for the simulated and annotation-mask encoders (their features cost next to nothing)")
    g.add_argument("--camera-subset", type=bounded(int, 1), default=None, metavar="K",
                   help="encode K of the training cameras, chosen for coverage (the others give no evidence)")
    g.add_argument("--timestep-stride", type=bounded(int, 1), default=None, metavar="N",
                   help="encode every N-th timestep and the last; the others are filled from their neighbours")
    g.add_argument("--timestep-seconds", type=bounded(float, 0, low_open=True), default=None, metavar="S",
                   help="encode timesteps S seconds apart (the stride is the most whole timesteps within S at "
                        "the scene's frame rate, at least 1; the default plan's: 0.2); replaces --timestep-stride")
    g.add_argument("--fill", default=None, choices=FILL_MODES,
                   help="how skipped timesteps are filled: interpolate their neighbours' features (default), reuse the "
                        "nearer one's, or latents: lift only the encoded timesteps and give each Gaussian the "
                        "interpolation of its own latents (the fill moves with the Gaussians)")
    g.add_argument("--levels", default=None, metavar="I,J,...",
                   help="keep these pyramid scales (indices into --ratios/--steps, 0 = smallest)")
    g.add_argument("--crop-stride", type=bounded(float, 0, 1, low_open=True), default=None, metavar="F",
                   help="crop spacing as a fraction of the crop side (paper 0.5; 1 = no overlap)")
    g.add_argument("--early-exit", default=None, choices=EARLY_EXITS,
                   help="copy the features of crops whose clip did not change since the previous encoded "
                        "timestep: judged by the foreground or by the frame difference")
    g.add_argument("--budget", default=None, metavar="TIME",
                   help="refuse a plan estimated above TIME (e.g. 30m, 2h, 1.5d) unless --over-budget")
    g.add_argument("--over-budget", action="store_true", help="start even when the estimate is above --budget")
    g.add_argument("--dry-run", action="store_true",
                   help="print the plan and its estimate (clips, TFLOP, time on this device) and stop")
    g.add_argument("--plan-json", default=None, metavar="FILE", help="also write the plan and estimate as JSON")


def _levels(text: str | None) -> tuple[int, ...] | None:
    if text is None:
        return None
    try:
        levels = tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise InputError(f"expected scale indices such as 1,2,3,4, got {text!r}", field="--levels") from None
    if not levels:
        raise InputError("names no scale", field="--levels")
    return levels


def plan_from_args(args: argparse.Namespace, encoder: Any):
    """The :class:`~fourlegs_engine.language.plans.ExtractPlan` of the options (named plan + knobs)."""
    from ..language.plans import resolve_plan
    return resolve_plan(getattr(args, "plan", "auto"), encoder).with_(
        cameras=getattr(args, "camera_subset", None), timestep_stride=getattr(args, "timestep_stride", None),
        timestep_seconds=getattr(args, "timestep_seconds", None),
        fill=getattr(args, "fill", None), levels=_levels(getattr(args, "levels", None)),
        crop_stride=getattr(args, "crop_stride", None), early_exit=getattr(args, "early_exit", None))


def plan_and_check(args: argparse.Namespace, scene: Any, encoder: Any, base: Any, *,
                   timesteps: Any = None, shard: Any = None) -> tuple[Any, bool]:
    """Estimate the plan (a few seconds of calibration), print it, refuse it above ``--budget``.

    Returns ``(extract config, go)``: ``go`` is False after ``--dry-run``."""
    from ..fileio import write_json_atomic
    from ..language.budget import check_budget, estimate_plan, parse_duration

    budget = parse_duration(getattr(args, "budget", None))
    estimate = estimate_plan(scene, encoder, plan_from_args(args, encoder), base, timesteps=timesteps, shard=shard)
    for line in estimate.lines():
        print(line, flush=True)
    if getattr(args, "plan_json", None):
        write_json_atomic(args.plan_json, {**estimate.to_dict(), "budget_s": budget}, overwrite=True)
    if getattr(args, "dry_run", False):
        if budget is not None:
            print(f"  budget {args.budget}: {'within' if estimate.within(budget) else 'ABOVE (would be refused)'}")
        return estimate.config, False
    check_budget(estimate, budget, go_on=getattr(args, "over_budget", False))
    return estimate.config, True
