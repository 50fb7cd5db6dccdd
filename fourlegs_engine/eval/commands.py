"""CLI: ``fourlegs generate`` (synthetic scene bundles), ``fourlegs bench grounding`` and
``fourlegs bench compare``."""
from __future__ import annotations

import argparse

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


def _generate(args: argparse.Namespace) -> int:
    import time

    from tqdm import tqdm

    from .synthetic import write_synthetic_bundle

    start = time.perf_counter()
    with tqdm(total=None, desc=f"generating {args.size}", unit="step", leave=False) as bar:
        def progress(done: int, total: int) -> None:
            bar.total = total
            bar.update(done - bar.n)
        path = write_synthetic_bundle(args.output, args.size, args.seed, overwrite=args.overwrite,
                                      progress=progress)
    print(f"wrote {path} ({args.size}, seed {args.seed}) in {time.perf_counter() - start:.1f} s")
    if args.ground_truth:
        from ..scene.bundle import load_bundle
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
