"""``fourlegs highlight`` (the main job) and ``fourlegs build-extension``.

``highlight`` runs ``python -m fourlegs_addon.headless --options-json FILE`` in a child process: the
engine's process never imports bpy, Blender's state never leaks between runs, and every option reaches
the child because the job's options dataclass itself is what crosses the process boundary. Ctrl-C reaches the child too (same
process group), SIGTERM to the parent stops the child, and a child whose parent dies (even by SIGKILL)
ends itself (:func:`fourlegs_engine.api.die_with_parent`); the language stages resume on the next run.
"""
from __future__ import annotations

import argparse
import os
import signal
import subprocess
import threading
import sys
import tempfile
from pathlib import Path


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


def headless_command(options_file: str | Path) -> list[str]:
    """The child's command line: the job's options travel as data (:meth:`HighlightJobOptions.to_json`)."""
    return [sys.executable, "-m", "fourlegs_addon.headless", "--options-json", str(options_file)]


def run_highlight(args: argparse.Namespace) -> int:
    from fourlegs_engine.commands.options import highlight_job_options

    options = highlight_job_options(args)
    with tempfile.TemporaryDirectory(prefix="fourlegs-highlight-") as tmp:
        options_file = Path(tmp) / "options.json"
        options_file.write_text(options.to_json(), encoding="utf-8")
        return run_child(headless_command(options_file), stage_file=Path(tmp) / "stage.txt")


class _Terminated(Exception):
    """The parent was asked to stop (SIGTERM)."""


#: exit statuses of a child that crashed in native code: killed by a signal (negative), or a crash handler's
#: exit(-signal) (245: SIGSEGV, 250: SIGABRT) or the shell's 128 + signal
_CRASH_SIGNALS = {245: signal.SIGSEGV, 250: signal.SIGABRT, 134: signal.SIGABRT, 139: signal.SIGSEGV,
                  247: signal.SIGKILL, 137: signal.SIGKILL}


def describe_crash(code: int, stage: str | None) -> str | None:
    """One line for a child that crashed in native code (None for an ordinary exit status)."""
    if code < 0:
        sig = signal.Signals(-code) if -code in signal.Signals._value2member_map_ else None
    else:
        sig = _CRASH_SIGNALS.get(code)
    if sig is None or sig in (signal.SIGTERM, signal.SIGINT):
        return None
    where = f" during the {stage!r} stage" if stage else " while starting"
    return (f"the Blender child crashed ({sig.name}, exit status {code}){where}; the likely cause is running out of "
            "memory: lower --resolution, --fps or the shots' durations, or close other programs, then run the "
            "same command again (finished frames are kept)")


def run_child(cmd: list[str], *, stage_file: Path | None = None) -> int:
    """Run the headless job and return its exit code; Ctrl-C and SIGTERM stop it for real (143 for SIGTERM). A
    native crash of the child is one line naming the stage it was in (read from ``stage_file``), exit 1."""
    from fourlegs_engine.api import PARENT_PID_ENV, STAGE_FILE_ENV, print_error

    env = {**os.environ, PARENT_PID_ENV: str(os.getpid())}
    if stage_file is not None:
        env[STAGE_FILE_ENV] = str(stage_file)
    proc = subprocess.Popen(cmd, env=env)

    def on_sigterm(signum, frame):
        raise _Terminated()

    in_main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, on_sigterm) if in_main else None
    try:
        code = proc.wait()
        stage = (stage_file.read_text(encoding="utf-8").strip()
                 if stage_file is not None and stage_file.is_file() else None)
        message = describe_crash(code, stage)
        if message is not None:
            print_error(message)
            return 1
        return code
    except (KeyboardInterrupt, _Terminated) as exc:
        # Blender's own SIGINT handler in the child only flags a break; stop it for real. Every stage
        # writes whole files atomically (features, latents, frames), so the next run resumes.
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        if isinstance(exc, _Terminated):
            print("fourlegs: stopped (SIGTERM); run the same command again to resume", file=sys.stderr)
            return 143
        raise
    finally:
        if in_main:
            signal.signal(signal.SIGTERM, previous)


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
