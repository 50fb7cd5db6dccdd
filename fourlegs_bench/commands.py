"""CLI of the benchmarks: ``fourlegs generate`` (synthetic scene bundles) and every ``fourlegs bench ...``.

Only argument parsers live here (the implementations are imported when a command runs), so
``fourlegs --help`` stays fast.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
from typing import Any

SIZE_CHOICES = ("tiny", "demo", "bench", "full")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "generate", help="write a synthetic 4D grounding scene (bundle with labels and queries.json)",
        description="Generate a Panoptic-like synthetic scene with exact space-time ground truth: a dome "
                    "of cameras, a court, three people and a ball acting out a scripted scene. "
                    "Deterministic from --seed.")
    p.add_argument("--size", choices=SIZE_CHOICES, default="demo",
                   help="tiny (tests), demo (~30k Gaussians), bench (~100k), full (~300k); default demo")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("-o", "--output", required=True, help="bundle directory to create")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.add_argument("--ground-truth", action="store_true",
                   help="also render and store the ground-truth masks of the test cameras")
    p.set_defaults(func=_generate)


def register_bench(bench_subparsers: argparse._SubParsersAction) -> None:
    p = bench_subparsers.add_parser(
        "grounding", help="spatio-temporal grounding benchmark on a synthetic scene (vAP, vIoU, tIoU, ...)",
        description="Run every registered grounding method on a synthetic scene and print the paper-style "
                    "table (per query and overall; ± is the standard deviation over the test views).")
    p.add_argument("--scene", choices=SIZE_CHOICES, default="bench", help="scene size (default bench)")
    p.add_argument("--seed", type=int, default=0, help="scene seed (default 0)")
    p.add_argument("--bundle", default=None,
                   help="use this synthetic bundle instead of the cached one for --scene/--seed")
    p.add_argument("--methods", default=None,
                   help="comma-separated method names (default: every registered method)")
    p.add_argument("--views", default=None,
                   help="comma-separated camera names to evaluate (default: the test cameras)")
    p.add_argument("--pixel-stride", default="2",
                   help="2D baseline: relevancy on every N-th pixel, upsampled (default 2); a list such as "
                        "1,2,4 runs one variant per stride (the speed/accuracy table and plot)")
    p.add_argument("--plot", default=None, metavar="PNG", help="write a seconds-vs-accuracy plot")
    p.add_argument("--threads", type=int, default=None,
                   help="torch CPU threads (default: torch's choice; 1 is fastest on a busy machine)")
    p.add_argument("--json", default=None, metavar="PATH", help="also write the results as JSON")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --json file")
    p.set_defaults(func=_bench_grounding)

    c = bench_subparsers.add_parser(
        "compare", help="rows of several accuracy-time runs (e.g. scene seeds) side by side, with means",
        description="Tabulate one metric of every row of several `fourlegs bench accuracy-time` runs, its "
                    "mean over the runs and its mean seconds; with --reference, each row's ratio to that "
                    "row and the runs where it falls below --target times it. Writes a table, JSON and a "
                    "plot with --out.")
    c.add_argument("reports", nargs="+", metavar="RUN",
                   help="accuracy_time.json files or the directories holding them")
    c.add_argument("--metric", default="vAP", help="metric to compare (default vAP)")
    c.add_argument("--reference", default=None, metavar="ROW", help="row name to compare against, e.g. "
                   "'optimize 2000 it'")
    c.add_argument("--groups", default=None, help="comma-separated row groups to keep (default: all)")
    c.add_argument("--target", type=float, default=0.95,
                   help="with --reference: count the runs below this share of it (default 0.95)")
    c.add_argument("--out", default=None, metavar="PREFIX", help="write PREFIX.json, .md and .png")
    c.add_argument("--overwrite", action="store_true", help="replace existing --out files")
    c.set_defaults(func=_bench_compare)
    _add_render(bench_subparsers)
    _add_query(bench_subparsers)
    _add_distill(bench_subparsers)
    _add_viclip(bench_subparsers)
    _add_blender(bench_subparsers)


# exact work per found query of `fourlegs bench accuracy-time --scene bench`'s K=65536 ±0.0075 row (100k
# Gaussians x 60 timesteps), forced by `bench query-speed` on its random latents
BENCH_RESCORE_SHARE = 0.00023
BENCH_SAMPLES = 4096


def _add_render(bench_sub: Any) -> None:
    p = bench_sub.add_parser("render", help="rasterizer speed, memory and accuracy (JSON, Markdown table, plot)",
                             description="Median ms/frame and peak memory of the rasterizer (forward and "
                             "forward+backward) on the documented benchmark scene, the float64 oracle and the "
                             "dense-tile implementation side by side at a small N, the accuracy knobs "
                             "(tile size, extent, feature dtype) as time next to error, each fused CPU kernel "
                             "generation side by side, the frame's pair counts with the ratio to the machine's "
                             "floor, and (--busy) a fit-like step beside a competing busy process.")
    p.add_argument("--sizes", default="10000,100000,300000", help="Gaussian counts, comma-separated")
    p.add_argument("--outputs", default="rgb,features,depth", help="any of rgb,features,depth")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    p.add_argument("--backend", choices=("torch", "gsplat", "all"), default=None,
                   help="default: torch on cpu, both (all) on cuda when gsplat is installed")
    p.add_argument("--repeats", type=int, default=3, help="timed runs per case (median reported)")
    p.add_argument("--channels", type=int, default=128, help="feature channels")
    p.add_argument("--resolution", default="640x360", help="WxH of the speed cases")
    p.add_argument("--small-n", type=int, default=2000, help="N of the oracle/dense-tile baselines and the knobs")
    p.add_argument("--small-resolution", default="320x180", help="WxH of the baselines and the knobs")
    p.add_argument("--skip-baselines", action="store_true", help="skip the oracle / dense-tile comparison")
    p.add_argument("--skip-knobs", action="store_true", help="skip the accuracy knobs")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")
    p.add_argument("--kernels", default="v2,v1",
                   help="fused CPU kernel generations of the CPU speed rows (RasterOptions.kernel), comma-separated")
    p.add_argument("--skip-floor", action="store_true",
                   help="skip the pair counts, the measured peak of one core and the ratio to the floor")
    p.add_argument("--busy", action="store_true",
                   help="also time a fit-like step beside a competing busy process (fresh processes, both "
                        "OpenMP wait policies)")
    p.add_argument("--busy-n", type=int, default=100_000, help="Gaussians of the --busy step")
    p.add_argument("--busy-threads", type=int, default=2, help="torch threads and kernel workers of the --busy step")
    p.add_argument("--json", default=None, metavar="PATH", help="write the records as a JSON list")
    p.add_argument("--markdown", default=None, metavar="PATH", help="write the Markdown tables")
    p.add_argument("--plot", default=None, metavar="PATH", help="write the knob plot (PNG)")
    p.add_argument("--overwrite", action="store_true", help="replace existing output files")
    p.set_defaults(func=_bench_render)


def _add_query(bench_subparsers: Any) -> None:
    p = bench_subparsers.add_parser(
        "accuracy-time", help="every query-speed knob: seconds and the six grounding metrics, same run",
        description="Sweep the speed/accuracy knobs of querying (codebook K, temporal stride, resolution "
                    "scale, fast vs exact maps, distillation mode/iterations, kNN k, fp32 vs fp16) on a "
                    "synthetic scene; each row reports its time and vAP, vIoU, tIoU, tRec, tPrec, tAP. "
                    "Writes a Markdown table, JSON and a Pareto plot (accuracy vs seconds).")
    p.add_argument("--scene", default="bench", choices=("tiny", "demo", "bench", "full"),
                   help="synthetic scene size (default bench; tiny for a quick run)")
    p.add_argument("--bundle", default=None, help="use this synthetic bundle instead of the cached one")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", metavar="PATH", help="results JSON (default OUT/accuracy_time.json)")
    p.add_argument("--out", metavar="DIR", help="output directory (default <bundle>/bench/accuracy_time)")
    p.add_argument("--skip", default="", help="comma-separated knob groups to skip (e.g. distill,knn)")
    p.add_argument("--distill-iterations", default="25,100",
                   help="optimize iteration counts of the distillation rows, comma-separated (default 25,100; "
                        "the paper uses 2000, affordable on the tiny scene)")
    p.add_argument("--distill-timesteps", type=int, default=0,
                   help="distillation variants: distil every k-th timestep only (0: automatic)")
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: torch default)")
    p.add_argument("--overwrite", action="store_true")
    p.set_defaults(func=_bench_accuracy_time)

    s = bench_subparsers.add_parser(
        "query-speed", help="temporal query time at 300k Gaussians x 150 timesteps (synthetic latents)",
        description="Time the temporal query (codebook and exact paths) and the spatial maps on random "
                    "latents of the paper's size written as a memmap in a temporary directory (no "
                    "distillation needed); reports seconds per query and peak RSS.")
    s.add_argument("--gaussians", type=int, default=300_000)
    s.add_argument("--timesteps", type=int, default=150)
    s.add_argument("--codebook", default="4096,65536", help="comma-separated K values (default 4096,65536)")
    s.add_argument("--refine", default="0,0.0075",
                   help="comma-separated exact re-scoring margins timed for each K (default 0,0.0075)")
    s.add_argument("--rescore-share", type=float, default=BENCH_RESCORE_SHARE,
                   help="re-scoring rows: also time the exact re-scoring of this share of all (t,g) pairs "
                        f"(random latents need none; default {BENCH_RESCORE_SHARE:g}, what K=65536 ±0.0075 re-scored "
                        "per found query on bench)")
    s.add_argument("--sample-count", type=int, default=BENCH_SAMPLES,
                   help="re-scoring rows: also time this many exact scores sampled for R_avg (default "
                        f"{BENCH_SAMPLES}, what K=65536 ±0.0075 sampled per found query on bench)")
    s.add_argument("--tiled-scene", default="none", choices=("none", "tiny", "demo", "bench"),
                   help="also time the re-scoring rows on this synthetic scene's distilled field tiled to the "
                        "benchmark's size, with every scene query and its answers checked against the exact "
                        "path (default none; bench needs its language field, built on first use)")
    s.add_argument("--repeats", type=int, default=5, help="timed queries per configuration (default 5)")
    s.add_argument("--exact-timesteps", type=int, default=3,
                   help="exact path: time this many timesteps and extrapolate to all (0: all)")
    s.add_argument("--spatial-scene", default="bench", choices=("none", "tiny", "demo", "bench", "full"),
                   help="synthetic scene whose geometry times the 640x360 maps (default bench; none: skip)")
    s.add_argument("--threads", type=int, default=0, help="torch threads (0: torch default)")
    s.add_argument("--json", metavar="PATH", help="write the results as JSON")
    s.add_argument("--overwrite", action="store_true")
    s.set_defaults(func=_bench_query_speed)
    i = bench_subparsers.add_parser(
        "query-interactive", help="the default query path on one scene: index build, first and later answer, "
                                  "and the exact path's segments, peak and best view beside them",
        description="Time the one-time index build (the sketch, or the codebook, stored with the field), each query's first and "
                    "later answer on the default path in one engine (wall and CPU seconds), then the exact path's "
                    "answers, and report whether segments, peak and best view agree.")
    i.add_argument("scene", help="bundle directory with a language field")
    i.add_argument("queries", nargs="+", help="query texts")
    i.add_argument("--rebuild-index", action="store_true", help="delete the stored index first (times the build)")
    i.add_argument("--no-exact", action="store_true", help="skip the exact path's comparison")
    i.add_argument("--json", metavar="PATH", help="write the report as JSON")
    i.set_defaults(func=_bench_query_interactive)


def _add_distill(bench_subparsers: Any) -> None:
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
    p.set_defaults(func=_bench_distill)


def _add_viclip(bench_subparsers: Any) -> None:
    p = bench_subparsers.add_parser(
        "viclip", help="ViCLIP encoder: seconds per clip/phrase and accuracy per precision and batch size",
        description="Seconds per 8-frame clip and per phrase, and the worst cosine to a float64 reference, "
                    "for every precision and batch size, in one run. With --dataset: the real configuration "
                    "(L/14, 8 frames, the 5-scale crop pyramid, 572 clips per camera-timestep at 640x360) on "
                    "the capture's real frames through extraction's crop code, with random weights; pre-processing "
                    "timed apart from the network, and the whole scene extrapolated.")
    p.add_argument("--dataset", default=None, metavar="DIR",
                   help="real-frames mode: a Dynamic 3D Gaussians capture (train_meta.json, ims/), e.g. "
                        "../shared/data/panoptic-basketball (default: random clips)")
    p.add_argument("--size", default=None, choices=("b", "l"),
                   help="ViCLIP size (default b = B/16; l = L/14 with --dataset)")
    p.add_argument("--checkpoint", default=None,
                   help="real weights (default: random weights from --seed; not with --dataset)")
    p.add_argument("--dtypes", default=None,
                   help="precisions to measure (default float32,bfloat16; float32,bfloat16,float16 with --dataset)")
    p.add_argument("--batch-sizes", default=None, help="clips per forward pass (default 1,4; 1,2 with --dataset)")
    p.add_argument("--reference", default="float64", choices=("float64", "float32", "bfloat16", "float16"),
                   help="precision of the reference embeddings (default float64)")
    p.add_argument("--clips", type=int, default=None,
                   help="clips encoded per measurement (default 4; 2 real clips with --dataset)")
    p.add_argument("--phrases", type=int, default=None, help="phrases encoded per measurement (default 16; 8 with "
                   "--dataset)")
    p.add_argument("--repeats", type=int, default=2,
                   help="timed repeats, the median is reported (default 2; --dataset times one pass)")
    p.add_argument("--cameras", default="1", help="--dataset: training camera ids whose pyramids are cut (default 1)")
    p.add_argument("--timesteps", default="75", help="--dataset: timesteps of those pyramids (default 75)")
    p.add_argument("--subsets", default=None,
                   help="--dataset: NAME:CAMERASxTIMESTEPS entries to extrapolate to (default "
                        "'all:27x150,8 cameras:8x150,8 cameras 1 s:8x30')")
    p.add_argument("--device", default="auto", help="cpu, cuda or auto (default)")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (default: torch's choice)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="output prefix (default bench/viclip; bench/viclip_real with --dataset)")
    p.add_argument("--overwrite", action="store_true", help="replace existing output files")
    p.set_defaults(func=_bench_viclip)


def _add_blender(bench_subparsers: Any) -> None:
    b = bench_subparsers.add_parser(
        "blender", help="Blender layer: import seconds (300k Gaussians, or --scene: a real scene's import, peak RSS, "
                        "timeline scrubbing and viewport draws), per-frame render seconds through Blender "
                        "vs the engine directly, and the max pixel difference between the two")
    from . import blender
    blender.build_parser(b)
    b.set_defaults(func=_bench_blender)
    n = bench_subparsers.add_parser(
        "native-render", help="the same highlight frames by the 4-LEGS Splats engine (bpy 5.0) and by Blender 5.3's "
                              "EEVEE and Cycles: PSNR against the 4-LEGS render and seconds per frame")
    from . import native_render
    native_render.build_parser(n)
    n.set_defaults(func=native_render.run)
    c = bench_subparsers.add_parser(
        "prepare-cost", help="CPU seconds of one language field: the main job's chain against the panel's "
                             "Prepare Language Field (bpy), and whether the two fields are identical")
    from . import prepare_cost
    prepare_cost.build_parser(c)
    c.set_defaults(func=prepare_cost.run)


def _generate(args: argparse.Namespace) -> int:
    import time

    from tqdm import tqdm

    from fourlegs_engine.demo.synthetic import write_synthetic_bundle

    start = time.perf_counter()
    with tqdm(total=None, desc=f"generating {args.size}", unit="step", leave=False) as bar:
        def progress(done: int, total: int) -> None:
            bar.total = total
            bar.update(done - bar.n)
        path = write_synthetic_bundle(args.output, args.size, args.seed, overwrite=args.overwrite,
                                      progress=progress)
    print(f"wrote {path} ({args.size}, seed {args.seed}) in {time.perf_counter() - start:.1f} s")
    if args.ground_truth:
        from fourlegs_engine.scene.bundle import load_bundle
        from .ground_truth import ensure_ground_truth
        ensure_ground_truth(load_bundle(path), progress=True)
        print(f"ground truth in {path / 'ground_truth'}")
    return 0


def _bench_grounding(args: argparse.Namespace) -> int:
    from .grounding import run_grounding_benchmark_cli
    return run_grounding_benchmark_cli(args)


def _bench_compare(args: argparse.Namespace) -> int:
    from .compare import run_compare_cli
    return run_compare_cli(args)


def _bench_render(args: argparse.Namespace) -> int:
    from .render import run_render_cli
    return run_render_cli(args)


def _bench_accuracy_time(args: argparse.Namespace) -> int:
    from .accuracy_time import run_accuracy_time_cli
    return run_accuracy_time_cli(args)


def _bench_query_speed(args: argparse.Namespace) -> int:
    from .query_speed import run_query_speed_cli
    return run_query_speed_cli(args)


def _bench_query_interactive(args: argparse.Namespace) -> int:
    from .query_interactive import run_query_interactive
    run_query_interactive(args.scene, args.queries, exact=not args.no_exact, rebuild_index=args.rebuild_index,
                          out=args.json)
    return 0


def _bench_distill(args: argparse.Namespace) -> int:
    from .distill import run_bench_distill
    return run_bench_distill(args)


def _bench_viclip(args: argparse.Namespace) -> int:
    from .viclip import run_bench_viclip
    return run_bench_viclip(args)


def _bench_blender(args: argparse.Namespace) -> int:
    """Runs in a child process: Blender's bpy module never loads into the ``fourlegs`` process."""
    from . import blender
    return subprocess.call([sys.executable, "-m", "fourlegs_bench.blender", *blender.forward_argv(args)])
