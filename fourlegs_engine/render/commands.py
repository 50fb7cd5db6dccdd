"""CLI: ``fourlegs bench render``."""
from __future__ import annotations

import argparse
import shlex
import sys


def register_bench(bench_sub) -> None:
    p = bench_sub.add_parser("render", help="rasterizer speed, memory and accuracy (JSON, Markdown table, plot)",
                             description="Median ms/frame and peak memory of the rasterizer (forward and "
                             "forward+backward) on the documented benchmark scene, the float64 oracle and the "
                             "dense-tile implementation side by side at a small N, and the accuracy knobs "
                             "(tile size, extent, feature dtype) as time next to error.")
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
    p.add_argument("--json", default=None, metavar="PATH", help="write the records as a JSON list")
    p.add_argument("--markdown", default=None, metavar="PATH", help="write the Markdown tables")
    p.add_argument("--plot", default=None, metavar="PATH", help="write the knob plot (PNG)")
    p.add_argument("--overwrite", action="store_true", help="replace existing output files")
    p.set_defaults(func=bench_render)


def _ints(text: str, name: str) -> tuple[int, ...]:
    from ..errors import InputError
    try:
        values = tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise InputError(f"expected comma-separated integers, got {text!r}", field=name) from None
    if not values or any(v < 0 for v in values):
        raise InputError(f"expected non-negative integers, got {text!r}", field=name)
    return values


def _resolution(text: str, name: str) -> tuple[int, int]:
    from ..errors import InputError
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"expected WxH, got {text!r}", field=name) from None
    if w <= 0 or h <= 0:
        raise InputError(f"expected a positive size, got {text!r}", field=name)
    return w, h


def bench_render(args: argparse.Namespace) -> int:
    from pathlib import Path

    import torch
    from tqdm import tqdm

    from ..errors import InputError, OutputExistsError
    from ..fileio import atomic_path, write_json_atomic
    from .backends import gsplat_available
    from .bench import OUTPUT_CHOICES, BenchConfig, environment, markdown_report, plot_knobs, run_bench

    outputs = tuple(o.strip() for o in args.outputs.split(",") if o.strip())
    bad = [o for o in outputs if o not in OUTPUT_CHOICES]
    if bad or not outputs:
        raise InputError(f"unknown output(s) {bad}; choose from {OUTPUT_CHOICES}", field="--outputs")
    if args.device == "cuda" and not torch.cuda.is_available():
        raise InputError("CUDA is not available on this machine", field="--device")
    backend = args.backend or ("all" if args.device == "cuda" and gsplat_available() else "torch")
    backends = ("torch", "gsplat") if backend == "all" else (backend,)
    if "gsplat" in backends and (args.device != "cuda" or not gsplat_available()):
        raise InputError("the gsplat backend needs --device cuda and gsplat installed", field="--backend")
    for path in (args.json, args.markdown, args.plot):
        if path and Path(path).exists() and not args.overwrite:
            raise OutputExistsError(path)
    if args.repeats < 1:
        raise InputError("must be >= 1", field="--repeats")
    w, h = _resolution(args.resolution, "--resolution")
    sw, sh = _resolution(args.small_resolution, "--small-resolution")
    cfg = BenchConfig(sizes=_ints(args.sizes, "--sizes"), outputs=outputs, device=args.device, backends=backends,
                      repeats=args.repeats, channels=args.channels, width=w, height=h, small_n=args.small_n,
                      small_width=sw, small_height=sh, baselines=not args.skip_baselines, knobs=not args.skip_knobs)
    n_cases = len(cfg.sizes) * len(outputs) * len(backends) * 2 + (12 if cfg.baselines else 0) + (14 if cfg.knobs else 0)
    bar = tqdm(total=n_cases, desc="bench render", unit="case", file=sys.stderr)

    def progress(rec: dict) -> None:
        bar.update(1)
        bar.set_postfix_str(f"{rec.get('impl') or rec.get('knob') or ''} n={rec['n']} {rec['output']} "
                            f"{rec['mode']} {rec['ms_median']:.0f} ms")

    threads_before = torch.get_num_threads()
    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        records = run_bench(cfg, progress)
    finally:
        torch.set_num_threads(threads_before)
        bar.close()
    command = "fourlegs " + " ".join(shlex.quote(a) for a in sys.argv[1:]) if sys.argv[1:] else "fourlegs bench render"
    env = dict(environment(), threads=args.threads or threads_before)
    report = markdown_report(records, command, env)
    print(report)
    if args.json:
        write_json_atomic(args.json, [dict(r, command=command, threads=env["threads"], torch=env["torch"])
                                      for r in records], overwrite=args.overwrite)
    if args.markdown:
        with atomic_path(args.markdown, overwrite=args.overwrite) as tmp:
            Path(tmp).write_text(report + "\n", encoding="utf-8")
    if args.plot and cfg.knobs:
        plot_knobs(records, args.plot)
    return 0
