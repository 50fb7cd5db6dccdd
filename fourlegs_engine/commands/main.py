"""The ``fourlegs`` command.

Each module of this package contributes a command family with ``register(subparsers)`` (and
optionally ``register_bench(bench_subparsers)``). Other installed
packages (the Blender add-on, the benchmarks) add theirs through the entry-point group
``fourlegs.commands`` (pyproject.toml), so the engine never imports them by name. Heavy imports happen
inside the command functions so ``fourlegs --help`` stays fast. Errors from bad input print one line
(no traceback), and so do the machine's limits (:func:`~fourlegs_engine.errors.exit_code_of`).
"""
from __future__ import annotations

import argparse
import importlib
import sys
from importlib.metadata import entry_points
from types import ModuleType
from typing import Iterator, Sequence

from .. import __version__
from ..errors import exit_code_of

COMMAND_MODULES = (
    "fourlegs_engine.commands.scene",
    "fourlegs_engine.commands.language",
    "fourlegs_engine.commands.viclip",
    "fourlegs_engine.commands.query",
    "fourlegs_engine.commands.highlights",
    "fourlegs_engine.commands.fit",
)
ENTRY_POINT_GROUP = "fourlegs.commands"


def command_modules() -> Iterator[ModuleType]:
    """The engine's own command modules, then those other installed packages declare (by entry-point name)."""
    for name in COMMAND_MODULES:
        yield importlib.import_module(name)
    for ep in sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
        try:
            yield ep.load()
        except ModuleNotFoundError as exc:
            if exc.name is not None and ep.value.startswith(exc.name):
                continue  # declared by a distribution whose package is no longer importable
            raise


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fourlegs", description="4-LEGS highlights: find when and where a text query happens in a dynamic "
        "3D Gaussian scene and turn it into a highlight video.")
    parser.add_argument("--version", action="version", version=f"fourlegs {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    bench = sub.add_parser("bench", help="benchmarks: speed and accuracy, as tables, JSON and plots")
    bench_sub = bench.add_subparsers(dest="bench_command", metavar="BENCH")
    for module in command_modules():
        if hasattr(module, "register"):
            module.register(sub)
        if hasattr(module, "register_bench"):
            module.register_bench(bench_sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    try:  # the command modules' imports take seconds: Ctrl-C then is a quiet cancel too
        parser = build_parser()
        args = parser.parse_args(argv)
    except KeyboardInterrupt:
        print("fourlegs: cancelled", file=sys.stderr)
        return 130
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    from ..runlock import release_all

    try:
        return exit_code_of(lambda: args.func(args))
    finally:
        release_all()


if __name__ == "__main__":
    sys.exit(main())
