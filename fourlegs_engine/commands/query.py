"""CLI: ``fourlegs query``."""
from __future__ import annotations

import argparse
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, Optional

def register(subparsers: Any) -> None:
    from .options import add_demo_argument, bounded
    from ..query.options import MAX_CODEBOOK_SIZE, MAX_RESOLUTION_SCALE, MAX_SKETCH_RANK, MAX_TIMESTEP_ARGUMENT, \
        QUERY_PATHS, QueryOptions

    p = subparsers.add_parser(
        "query", help="when and where a text query happens in a scene (segment, peak, maps)",
        description="Localize a text query in a scene with a distilled language field: prints the "
                    "temporal segment, its peak and an s_t sparkline; optionally writes JSON, an s_t plot "
                    "and relevancy/depth/alpha maps as multi-channel EXR files.")
    p.add_argument("scene", nargs="*", metavar="SCENE... TEXT",
                   help="bundle directory(ies) with a language field, then the query, e.g. \"a ball flying in "
                        "the air\"; with several scenes they are ranked by max_t s_t (paper §6.2, on every "
                        "--scene-stride-th timestep) and the query is localized in the best one")
    add_demo_argument(p)
    p.add_argument("--json", metavar="PATH", help="write the localization as JSON")
    p.add_argument("--plot", metavar="PATH", help="s_t plot (PNG); default beside --json as *.st.png")
    p.add_argument("--exr", metavar="DIR", help="write relevancy/depth/alpha EXR maps into DIR")
    p.add_argument("--views", nargs="+", metavar="CAM",
                   help="camera names for the EXR maps (default: the best view)")
    p.add_argument("--frames", nargs="+", metavar="T",
                   help="timesteps for the EXR maps: integers, python slices (0:150 = every timestep of 150, "
                        "0:150:10 every 10th), a,b,c lists, or 'peak' (default: peak)")
    p.add_argument("--path", choices=QUERY_PATHS, default=QueryOptions.path,
                   help="temporal localization: the sketch (a per-pair sketch of the relevancy built once per "
                        "field, stored beside it; the Gaussians it cannot decide are scored exactly), the "
                        "codebook (K codes, exact re-scoring where a decision depends on it), or every latent "
                        "decoded (default %(default)s)")
    p.add_argument("--sketch-rank", type=bounded(int, 1, MAX_SKETCH_RANK), default=QueryOptions.sketch_rank,
                   help="rank of --path sketch's per-pair sketch (default %(default)s)")
    p.add_argument("--codebook-size", type=bounded(int, 1, MAX_CODEBOOK_SIZE), default=QueryOptions.codebook_size,
                   help="K of --path codebook (default %(default)s)")
    p.add_argument("--codebook-refine", type=float, default=QueryOptions.codebook_refine, metavar="MARGIN",
                   help="--path codebook: make the temporal decisions exact where they depend on it: R_avg "
                        "corrected by a sample of exact scores, and the Gaussians of codes within MARGIN of "
                        "R_avg decoded at the timesteps whose s_t > 1/T decision they can change; the maps "
                        "score the Gaussians near or above 0.5 exactly (default %(default)s; 0: lookup only)")
    p.add_argument("--codebook-samples", type=int, default=None, metavar="N",
                   help="--path sketch, and codebook with --codebook-refine: exact scores sampled for R_avg (grown 4x "
                        "at a time, up to 16x, while R_avg's interval leaves a decision open; default: the "
                        "engine's, 4096)")
    p.add_argument("--spatial", choices=("exact", "fast"), default=QueryOptions.spatial,
                   help="maps: 128-channel render + per-pixel decode, or 1-channel relevancy render "
                        "(default %(default)s)")
    p.add_argument("--view-scale", type=bounded(float, 0, 1, low_open=True), default=QueryOptions.view_scale,
                   help="best view: every camera scored at this fraction of the map resolution, then the "
                        "--view-confirm best re-scored at full (default %(default)s; 1: all at full)")
    p.add_argument("--view-confirm", type=bounded(int, 1, MAX_TIMESTEP_ARGUMENT), default=QueryOptions.view_confirm,
                   help="best view: cameras re-scored at the map resolution (default %(default)s)")
    p.add_argument("--view-score", choices=("relevant", "mean"), default=QueryOptions.view_score,
                   help="best view: rank the cameras by the mass of relevancy above 0.5 (relevant: follows a small "
                        "subject) or by the mean relevancy (mean: the paper's) (default %(default)s)")
    p.add_argument("--scale", type=bounded(float, 0, MAX_RESOLUTION_SCALE, low_open=True), default=1.0,
                   help=f"resolution scale of the maps, in (0, {MAX_RESOLUTION_SCALE:g}] (default 1)")
    p.add_argument("--stride", type=bounded(int, 1, MAX_TIMESTEP_ARGUMENT), default=1,
                   help="temporal stride (default 1: every timestep)")
    p.add_argument("--dilation", type=bounded(int, 0, MAX_TIMESTEP_ARGUMENT), default=1,
                   help="temporal dilation radius, >= 0 (default 1)")
    p.add_argument("--negatives", nargs="+", default=(), metavar="PHRASE",
                   help="scene-specific negative phrases added to the canonical ones")
    p.add_argument("--no-spatial", action="store_true", help="temporal localization only")
    p.add_argument("--scene-stride", type=bounded(int, 1, MAX_TIMESTEP_ARGUMENT), default=None, metavar="K",
                   help="several scenes: rank them on every K-th timestep (default 10, as the paper)")
    p.add_argument("--overwrite", action="store_true", help="replace existing output files")
    from .options import add_encoder_arguments
    add_encoder_arguments(p, default="auto")  # 'auto': the encoder recorded with the field (masks need no flags)
    p.set_defaults(func=run_query)


# ------------------------------------------------------------------------------------ query
def _open(args: argparse.Namespace, inputs: QueryInputs):
    from ..errors import InputError
    from ..pipeline import QueryOptions, ensure_language_field, open_query_engine, text_encoder
    from ..scene.bundle import is_bundle, load_bundle

    if args.demo:
        from ..demo.synthetic import ensure_demo_bundle
        path = ensure_demo_bundle()
    else:
        if inputs.scene is None or inputs.text is None:
            raise InputError("expected SCENE TEXT (or --demo TEXT)", field="arguments")
        path = Path(inputs.scene)
        if not is_bundle(path):
            raise InputError("not a scene bundle (scene.json missing); `fourlegs query` reads bundles only: "
                             "`fourlegs plan` and `fourlegs highlight` take this scene directly (they convert "
                             "it), or write a bundle with fourlegs_engine.scene.write_bundle(load_scene(PATH), "
                             "OUT) and run `fourlegs language OUT`", file=path)
    from ..validate import check_text
    check_text(inputs.text, "text")
    if not inputs.text or not inputs.text.strip():
        raise InputError("the query text is empty", field="text")
    from ..runlock import hold_run_lock
    hold_run_lock(path, shared=True)  # read while no one writes it; released when the command ends
    scene = load_bundle(path)
    if not scene.language and not (scene.metadata or {}).get("labels"):
        raise InputError("the scene has no distilled language field; run `fourlegs language` first",
                         file=path, field="language")
    from .options import encoder_options_from_args
    encoder = text_encoder(scene, encoder_options_from_args(args))
    scene = ensure_language_field(scene, encoder, progress=True)
    options = QueryOptions(path=args.path, codebook_size=args.codebook_size, codebook_refine=args.codebook_refine,
                           sketch_rank=args.sketch_rank,
                           negatives=tuple(args.negatives), temporal_stride=args.stride, spatial=args.spatial,
                           resolution_scale=args.scale, dilation=args.dilation, view_scale=args.view_scale,
                           view_confirm=args.view_confirm, view_score=args.view_score)
    if args.codebook_samples is not None:
        options = options.replace(codebook_samples=args.codebook_samples)
    with stage_bar("opening the field") as report:
        engine = open_query_engine(scene, encoder, options=options, progress=report)
    return scene, engine


@contextmanager
def stage_bar(desc: str) -> Iterator[Callable[[float, str], None]]:
    """A tqdm bar (percent, current stage) for a ``progress(fraction, stage)`` callback: on a terminal's
    stderr, once the work has taken half a second, and erased when done (a log or an error keeps its one
    line)."""
    import sys

    from tqdm import tqdm

    terminal = bool(getattr(sys.stderr, "isatty", lambda: False)())
    bar = tqdm(total=100, desc=desc, bar_format="{desc}: {percentage:3.0f}%|{bar:20}| {elapsed}{postfix}",
               leave=False, delay=0.5, disable=not terminal, file=sys.stderr)

    shown = {"stage": "", "done": 0}

    def report(fraction: float, stage: str) -> None:
        done = int(round(100 * min(max(fraction, 0.0), 1.0)))
        if stage and stage != shown["stage"]:
            shown["stage"] = stage
            bar.set_postfix_str(stage, refresh=False)
        if done > shown["done"]:
            bar.update(done - shown["done"])
            shown["done"] = done

    try:
        yield report
    finally:
        bar.close()


@dataclass(frozen=True)
class QueryInputs:
    """``SCENE... TEXT`` of ``fourlegs query``: the scene paths, the one scene (None for the demo or
    several scenes) and the query text."""

    scenes: tuple[str, ...]
    scene: Optional[str]
    text: Optional[str]


def _split_inputs(args: argparse.Namespace) -> QueryInputs:
    """``SCENE... TEXT`` (the ``scene`` positional) into :class:`QueryInputs`; usage errors as InputError."""
    from ..errors import InputError

    items = list(args.scene or [])
    text = items.pop() if items else None
    if args.demo and items:
        raise InputError("give either --demo TEXT or SCENE TEXT, not both", field="scene")
    if not args.demo and not items:
        raise InputError("expected SCENE TEXT (or SCENE SCENE... TEXT, or --demo TEXT)", field="arguments")
    if len(set(map(str, items))) != len(items):
        raise InputError("a scene is given twice", field="scene")
    return QueryInputs(tuple(items), items[0] if len(items) == 1 else None, text)


def run_query(args: argparse.Namespace) -> int:
    inputs = _split_inputs(args)
    if len(inputs.scenes) > 1:
        return run_multiscene(args, inputs)
    if args.scene_stride is not None:
        from ..errors import InputError
        raise InputError("--scene-stride ranks several scenes; give at least two", field="--scene-stride")
    return _run_one(args, inputs)


def run_multiscene(args: argparse.Namespace, inputs: QueryInputs) -> int:
    """Rank the scenes by max_t s_t of the query and localize it in the best one (paper §6.2)."""
    from ..errors import InputError, OutputExistsError
    from ..fileio import write_json_atomic
    from ..query.multiscene import DEFAULT_SCENE_STRIDE, rank_scenes_opening

    for flag in ("exr", "plot", "views", "frames"):
        if getattr(args, flag):
            raise InputError("writes maps/plots of one scene; query that scene alone", field=f"--{flag}")
    if args.json and Path(args.json).exists() and not args.overwrite:
        raise OutputExistsError(args.json)
    from ..validate import check_text
    check_text(inputs.text, "text")
    if not inputs.text or not inputs.text.strip():
        raise InputError("the query text is empty", field="text")

    scenes = list(inputs.scenes)

    def opener(path: str):
        def open_engine():
            return _open(args, QueryInputs((path,), path, inputs.text))[1]
        return open_engine

    stride = args.scene_stride or DEFAULT_SCENE_STRIDE
    for path in scenes:  # a wrong path fails before any field is opened
        from ..scene.bundle import is_bundle
        if not is_bundle(Path(path)):
            raise InputError("not a scene bundle (scene.json missing)", file=path)
    need = {"temporal"} if args.no_spatial else {"temporal", "best_view", "action_centre"}
    start = time.perf_counter()
    ranked = rank_scenes_opening({p: opener(p) for p in scenes}, inputs.text, stride=stride, need=need,
                                 on_scene=lambda name, r: print(f"scored {name}: max_t s_t = {r:.4f}", flush=True))
    print(f'"{inputs.text}" in {len(scenes)} scenes (ranked by max_t s_t on every {stride}th timestep, '
          f"{time.perf_counter() - start:.1f} s)")
    width = max(len(p) for p in scenes)
    print(f"{'rank':>4}  {'scene':<{width}}  max_t s_t")
    for i, (name, score) in enumerate(ranked.ranking, 1):
        print(f"{i:>4}  {name:<{width}}  {score:.4f}" + ("  <- best" if name == ranked.best else ""))
    loc = ranked.localization
    if ranked.best is None:
        print("not found in any scene")
    elif loc.temporal is not None and loc.temporal.found:
        a, b = loc.temporal.segment
        print(f"best scene {ranked.best}: segment {a}..{b} (inclusive), peak t={loc.temporal.peak}"
              + (f", best view {loc.best_view}" if loc.best_view else ""))
    if args.json:
        result = ranked.to_dict()
        result.update(query=inputs.text, scene_stride=stride)
        write_json_atomic(args.json, result, overwrite=args.overwrite)
        print(f"wrote {args.json}")
    return 0


def _run_one(args: argparse.Namespace, inputs: QueryInputs) -> int:
    from ..errors import OutputExistsError
    from ..fileio import output_group, write_json_atomic
    from ..query.exr import write_exr
    from ..query.plots import plot_temporal
    from ..query.temporal import sparkline

    plot = Path(args.plot) if args.plot else (Path(args.json).with_suffix(".st.png") if args.json else None)
    for out in (args.json, plot):
        if out is not None and Path(out).exists() and not args.overwrite:
            raise OutputExistsError(out)
    scene, engine = _open(args, inputs)
    _timesteps_of_frames(args.frames or [], scene)  # before the query: a bad --frames costs nothing
    need = {"temporal"} if args.no_spatial else {"temporal", "best_view", "action_centre"}
    start = time.perf_counter()
    with stage_bar("query") as report:
        loc = engine.localize(inputs.text, need, progress=report)
    loc.timings["total"] = time.perf_counter() - start
    tmp = loc.temporal
    print(f'"{inputs.text}" in {scene.name} (T={scene.num_timesteps}, N={scene.num_gaussians}, path={args.path})')
    print(f"s_t |{sparkline(tmp.scores, 80)}|")
    if tmp.found:
        a, b = tmp.segment
        print(f"segment {a}..{b} (inclusive), peak t={tmp.peak}; all segments: "
              + ", ".join(f"{x}..{y}" for x, y in tmp.segments))
    else:
        print(f"not found: {tmp.message}")
    if tmp.undecided:
        print(f"timesteps {', '.join(map(str, tmp.undecided))}: counts within the index's error of the mean, "
              "so a segment end next to them may differ from --path exact's")
    if loc.best_view is not None:
        label = "relevant mass" if args.view_score == "relevant" else "mean relevancy"
        print(f"best view {loc.best_view} ({label} {loc.view_scores[loc.best_view]:.4f})")
    if loc.action_centre is not None:
        print("action centre (world) " + ", ".join(f"{v:.3f}" for v in loc.action_centre)
              + f"; pixel {loc.centre_px[0]:.1f}, {loc.centre_px[1]:.1f} in {loc.best_view}; box {loc.bbox}")
    for m in loc.messages:
        if m != tmp.message:
            print(m)
    print("timings: " + ", ".join(f"{k} {v:.3f} s" for k, v in loc.timings.items()))
    result = loc.to_dict()
    with output_group() as written:  # a failure part-way leaves none of this run's outputs behind
        if args.exr:
            result["exr"] = _write_maps(args, inputs.text, scene, engine, loc, write_exr, written)
        if args.json:
            if not Path(args.json).exists():
                written.append(Path(args.json))
            write_json_atomic(args.json, result, overwrite=args.overwrite)
            print(f"wrote {args.json}")
        if plot is not None:
            if not plot.exists():
                written.append(plot)
            plot_temporal(tmp, plot, query=inputs.text, overwrite=args.overwrite)
            print(f"wrote {plot}")
    return 0


def _timesteps_of_frames(values: list[str], scene) -> list[int]:
    """The timesteps ``--frames`` values name ('peak' skipped; an integer, or a python slice ``a:b`` /
    ``a:b:step``, or ``a,b,c``), each checked against T."""
    from ..language.store import parse_timesteps

    from ..errors import InputError

    out: list[int] = []
    for f in values:
        if f == "peak":
            continue
        if not any(c in f for c in ":,") and not f.strip().lstrip("-").isdigit():
            raise InputError(f"{f!r} is neither a timestep nor 'peak'", field="--frames")
        out += parse_timesteps(f, scene.num_timesteps, field="--frames")
    return out


def _write_maps(args, text: str, scene, engine, loc, write_exr, written: list[Path]) -> list[str]:
    from ..errors import InputError

    frames: list[int] = []
    for f in args.frames or ["peak"]:
        if f == "peak":
            if loc.temporal.peak is None:
                raise InputError("no peak to write maps at (query not found); pass --frames T", field="--frames")
            frames.append(int(loc.temporal.peak))
        else:
            frames += _timesteps_of_frames([f], scene)
    frames = list(dict.fromkeys(frames))
    names = args.views or ([loc.best_view] if loc.best_view else [])
    if not names:
        cams = scene.cameras.cameras(0, "all")
        if not cams:
            raise InputError("the scene has no cameras", field="--views")
        names = [cams[0].name]
    paths = []
    for t in frames:
        for name in names:
            cam = scene.cameras.find(name, t)
            maps = engine.relevancy_map(text, cam, t)
            path = Path(args.exr) / f"{name or 'view'}_t{t:04d}.exr"
            if not path.exists():
                written.append(path)
            write_exr(path, maps, overwrite=args.overwrite)
            paths.append(str(path))
            print(f"wrote {path} (relevancy, depth, alpha; {maps['relevancy'].shape[1]}x"
                  f"{maps['relevancy'].shape[0]})")
    return paths
