"""``fourlegs plan``: text query -> highlight plan JSON (+ a contact-sheet preview)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from .options import (add_demo_argument, add_effect_arguments, add_encoder_arguments, bounded, effects_of,
                      encoder_options_from_args, parse_resolution)
from ..errors import InputError
from ..pipeline import EncoderOptions, QueryOptions
from ..query.options import QUERY_PATHS


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "plan", help="plan a highlight (shots, camera and time keys, render passes) for a text query",
        description="Plan a highlight of a text query: SCENE \"text\" (a scene with a distilled language "
                    "field), or --demo \"text\" for the bundled synthetic demo scene. Writes the plan JSON "
                    "(docs/CONTRACTS.md) and optionally a contact-sheet preview rendered by the engine.")
    p.add_argument("inputs", nargs="*", metavar="SCENE QUERY",
                   help="scene path and query text (the query alone with --demo)")
    add_demo_argument(p)
    p.add_argument("--preset", default="broadcast", help="preset name or .toml path (default: broadcast)")
    p.add_argument("--preset-dir", action="append", default=[], metavar="DIR",
                   help="extra preset directory (searched first; also $FOURLEGS_PRESETS)")
    p.add_argument("--list-presets", action="store_true", help="list the available presets and exit")
    add_effect_arguments(p)
    p.add_argument("-o", "--output", metavar="PLAN.json", help="where to write the plan")
    p.add_argument("--preview", metavar="PNG", help="also write a contact sheet of sampled frames")
    p.add_argument("--overlay", action="store_true", help="overlay relevancy on every preview tile")
    p.add_argument("--preview-width", type=bounded(int, 16, 4096), default=320, help="width of a preview tile (px)")
    p.add_argument("--per-shot", type=bounded(int, 1, 64), default=4, help="preview frames per shot (1..64)")
    p.add_argument("--fps", type=bounded(float, 0, 240, low_open=True), help="override the preset's output frame rate")
    p.add_argument("--resolution", metavar="WxH", help="override the preset's output resolution")
    p.add_argument("--query-path", choices=QUERY_PATHS, default="exact",
                   help="per-Gaussian relevancy path of the query engine (default: exact)")
    p.add_argument("--spatial", choices=("exact", "fast"), default="fast",
                   help="relevancy maps for the best view / action centre: exact (128-channel render, "
                        "paper) or fast (1-channel per-Gaussian relevancy render; default, it scores the "
                        "same as exact on the bench scene, see `fourlegs bench accuracy-time`)")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    add_encoder_arguments(p, default="auto")  # 'auto': the encoder the field was distilled with
    p.set_defaults(func=run_plan)


def open_scene_and_localizer(scene_path: str | Path | None, *, demo: bool, encoder: EncoderOptions = EncoderOptions(),
                             options: QueryOptions = QueryOptions()):
    """The scene (or the demo scene) and a query engine on it, through :mod:`fourlegs_engine.pipeline`
    (a scene without a language field gets one first). Returns (scene, engine)."""
    from .. import pipeline

    if demo:
        scene = pipeline.open_scene(demo="demo")
    elif scene_path is None:
        raise InputError("no scene given (SCENE QUERY, or --demo QUERY)", field="scene")
    else:
        scene = pipeline.open_scene(scene_path)
    from ..runlock import hold_run_lock
    hold_run_lock(scene.root, shared=True)  # read while no one writes it; released when the command ends
    text_encoder = pipeline.text_encoder(scene, encoder)
    scene = pipeline.ensure_language_field(scene, text_encoder, progress=True)
    return scene, pipeline.open_query_engine(scene, text_encoder, options=options)


def run_plan(args: argparse.Namespace) -> int:
    from ..highlights.presets import available_presets, load_preset

    if args.list_presets:
        for name, path in sorted(available_presets(args.preset_dir).items()):
            preset = load_preset(path)
            print(f"{name:20s} {preset.description}  [{path}]")
        return 0
    if args.demo:
        if len(args.inputs) != 1:
            raise InputError("expected --demo QUERY" if not args.inputs else
                             "give either --demo QUERY or SCENE QUERY, not both", field="inputs")
        scene_path, query = None, args.inputs[0]
    else:
        if len(args.inputs) != 2:
            raise InputError("expected SCENE QUERY (or --demo QUERY)", field="inputs")
        scene_path, query = args.inputs
    from ..validate import check_text
    if not check_text(query, "query").strip():
        raise InputError("the query text is empty", field="query")
    if not args.output:
        raise InputError("missing -o PLAN.json", field="--output")
    out = Path(args.output)
    preview = Path(args.preview) if args.preview else None
    for path in (out, preview):
        if path is not None and path.exists() and not args.overwrite:
            from ..errors import OutputExistsError
            raise OutputExistsError(path)
    if args.per_shot < 1 or args.preview_width < 16:
        raise InputError("--per-shot must be >= 1 and --preview-width >= 16", field="preview")

    preset = load_preset(args.preset, args.preset_dir).select_effects(effects_of(args), args.no_effect)

    from ..highlights.planner import plan_highlight
    scene, localizer = open_scene_and_localizer(scene_path, demo=args.demo,
                                                encoder=encoder_options_from_args(args),
                                                options=QueryOptions(path=args.query_path, spatial=args.spatial))
    plan = plan_highlight(scene, localizer, query, preset, resolution=parse_resolution(args.resolution),
                          fps=args.fps)
    plan.save(out, overwrite=args.overwrite)
    loc = plan.localization
    print(f"plan: {out}  ({plan.frame_end - plan.frame_start + 1} frames at {plan.fps:g} fps, "
          f"{plan.resolution[0]}x{plan.resolution[1]})")
    print(f"  query {query!r}: found={loc['found']} segment={loc['segment']} peak={loc['peak']} "
          f"best view={loc['best_view']} action centre="
          f"{None if loc['action_centre'] is None else [round(v, 3) for v in loc['action_centre']]}")
    for s in plan.shots:
        print(f"  {s.name:14s} {s.effect:22s} frames {s.frame_start}-{s.frame_end}")
    print("  passes: " + ", ".join(f"{k} {v}" for k, v in plan.passes.items()))
    for m in plan.messages:
        print(f"  note: {m}", file=sys.stderr)
    if preview is not None:
        from ..highlights.preview import write_contact_sheet
        write_contact_sheet(preview, scene, plan, localizer=localizer, overlay=args.overlay,
                            per_shot=args.per_shot, width=args.preview_width, overwrite=args.overwrite)
        print(f"preview: {preview}")
    return 0
