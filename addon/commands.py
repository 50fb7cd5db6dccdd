"""``fourlegs highlight`` (the main job) and ``fourlegs build-extension``.

``highlight`` runs ``python -m fourlegs_addon.headless`` in a child process: the engine's process
never imports bpy, and Blender's state never leaks between runs. Ctrl-C reaches the child too (same
process group); the language stages resume on the next run.
"""
from __future__ import annotations

import argparse
import subprocess
import sys


def register(subparsers) -> None:
    hl = subparsers.add_parser(
        "highlight", help="the main job: scene -> query -> plan -> Blender -> highlight video (+ .blend, report)",
        description="Make a highlight video of a text query in a 4D scene, headless through Blender's bpy "
                    "module. Example: fourlegs highlight --demo \"a ball flying in the air\" --preset "
                    "broadcast -o out/")
    from fourlegs_engine.commands.options import add_highlight_arguments

    add_highlight_arguments(hl)
    hl.set_defaults(func=run_highlight)

    be = subparsers.add_parser("build-extension", help="build the Blender extension zip (add-on + engine + wheels)")
    be.add_argument("-o", "--output", required=True, help="output directory for the zip(s)")
    be.add_argument("--fetch-wheels", action="store_true",
                    help="download the dependency wheels (scipy, plyfile, tqdm, safetensors, numba, llvmlite; "
                         "cp311 + cp313; 4 platforms) from PyPI")
    be.add_argument("--wheels-dir", default=None, help="where dependency wheels are (default <cache>/extension-wheels)")
    be.add_argument("--no-wheels", action="store_true",
                    help="bundle no dependency wheels (Blender's Python must provide torch, scipy, tqdm)")
    be.add_argument("--extra-wheel", action="append", default=[], metavar="WHL",
                    help="bundle this wheel too (e.g. a torch CPU wheel for one platform); repeatable")
    be.add_argument("--split-platforms", action="store_true", help="one zip per platform")
    be.add_argument("--platform", action="append", default=None, dest="platforms", metavar="PLATFORM",
                    help="build for this Blender platform only (windows-x64, linux-x64, macos-arm64, macos-x64); "
                         "repeatable; default: all four")
    be.add_argument("--overwrite", action="store_true", help="replace existing zips")
    be.set_defaults(func=run_build_extension)


def headless_argv(args: argparse.Namespace) -> list[str]:
    """Re-create the command line of the headless job from parsed ``fourlegs highlight`` arguments."""
    argv = [] if args.scene is None else [args.scene]
    argv += [args.query, "--demo-size", args.demo_size, "--preset", args.preset, "-o", args.output, "--format", args.format,
             "--query-path", args.query_path, "--spatial", args.spatial]
    if args.encoder != "auto":  # "auto" is the default, not one of the encoder choices
        argv += ["--encoder", args.encoder]
    if args.demo:
        argv.append("--demo")
    if args.overwrite:
        argv.append("--overwrite")
    for flag, value in (("--resolution", args.resolution), ("--fps", args.fps), ("--checkpoint", args.checkpoint),
                        ("--vocab", args.vocab), ("--viclip-size", args.viclip_size), ("--device", args.device),
                        ("--encoder-dtype", args.encoder_dtype),
                        ("--encoder-batch-size", args.encoder_batch_size),
                        ("--pixel-normalization", args.pixel_normalization)):
        if value is not None:
            argv += [flag, str(value)]
    for effect in args.no_effect:
        argv += ["--no-effect", effect]
    return argv


def run_highlight(args: argparse.Namespace) -> int:
    cmd = [sys.executable, "-m", "fourlegs_addon.headless", *headless_argv(args)]
    proc = subprocess.Popen(cmd)
    try:
        return proc.wait()
    except KeyboardInterrupt:
        # Blender's own SIGINT handler in the child only flags a break; stop it for real. Every stage
        # writes whole files atomically (features, latents, frames), so the next run resumes.
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        raise


def run_build_extension(args: argparse.Namespace) -> int:
    from fourlegs_engine.errors import InputError

    from . import build

    try:
        zips = build.build(args.output, wheels_dir=args.wheels_dir, fetch=args.fetch_wheels,
                           extra_wheels=args.extra_wheel, with_wheels=not args.no_wheels,
                           split_platforms=args.split_platforms, platforms=args.platforms,
                           overwrite=args.overwrite)
    except build.BuildError as exc:
        raise InputError(str(exc), field="build-extension") from None
    for z in zips:
        print(z)
    return 0
