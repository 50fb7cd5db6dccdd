"""The ``fourlegs`` command.

Each package contributes its sub-commands from a ``commands`` module with ``register(subparsers)``
(and optionally ``register_bench(bench_subparsers)``); heavy imports happen inside the command
functions so ``fourlegs --help`` stays fast. Errors from bad input print one line (no traceback).
"""
from __future__ import annotations

import argparse
import importlib
import sys
from typing import Sequence

from . import __version__
from .errors import FourlegsError

COMMAND_MODULES = (
    "fourlegs_engine.scene.commands",
    "fourlegs_engine.render.commands",
    "fourlegs_engine.eval.commands",
    "fourlegs_engine.language.commands",
    "fourlegs_engine.language.viclip.commands",
    "fourlegs_engine.query.commands",
    "fourlegs_engine.highlights.commands",
    "fourlegs_addon.commands",
    "fourlegs_engine.fit.commands",
    "benchmarks.fit",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fourlegs", description="4-LEGS highlights: find when and where a text query happens in a dynamic "
        "3D Gaussian scene and turn it into a highlight video.")
    parser.add_argument("--version", action="version", version=f"fourlegs {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    bench = sub.add_parser("bench", help="benchmarks: speed and accuracy, as tables, JSON and plots")
    bench_sub = bench.add_subparsers(dest="bench_command", metavar="BENCH")
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name is not None and name.startswith(exc.name):
                continue  # that part of the product is not installed
            raise
        if hasattr(module, "register"):
            module.register(sub)
        if hasattr(module, "register_bench"):
            module.register_bench(bench_sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except FourlegsError as exc:
        print(f"fourlegs: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # output piped into e.g. `head`
        sys.stderr.close()
        return 0
    except KeyboardInterrupt:
        print("fourlegs: cancelled; run the same command again to resume", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
