"""CLI: ``fourlegs generate`` (synthetic scene bundles) and ``fourlegs bench grounding``."""
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
