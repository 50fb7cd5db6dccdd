"""CPU seconds of one language field: the main job's chain (``ensure_language_field``, plain Python) against
the panel's Prepare Language Field (bpy, its background job), each in its own process on a fresh copy of
the synthetic scene. Prints JSON: both CPU and wall seconds, their ratio, and whether the two fields are
bit-identical. CPU seconds include every thread of the child process.

    fourlegs bench prepare-cost tiny|demo [--out DIR]
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

CHAIN = """
from fourlegs_engine import pipeline
pipeline.ensure_language_field(pipeline.open_scene({path!r}))
"""
PANEL = """
import bpy
from fourlegs_addon import registration
registration.register()
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.fourlegs.import_scene(filepath={path!r} + "/scene.json")
assert bpy.ops.fourlegs.prepare_field() == {{"FINISHED"}}
"""


def children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def build_parser(parser: argparse.ArgumentParser) -> None:
    """The options of ``fourlegs bench prepare-cost``."""
    parser.add_argument("size", nargs="?", default="tiny", help="synthetic scene size (tiny, demo, ...)")
    parser.add_argument("--out", type=Path, default=None, help="work folder (default: a temporary one)")


def run(args: argparse.Namespace) -> int:
    """Build the field both ways in fresh processes and print the JSON line."""
    from fourlegs_engine.demo.synthetic import ensure_demo_bundle

    root = args.out or Path(tempfile.mkdtemp(prefix="prepare-cost-"))
    shutil.rmtree(root, ignore_errors=True)
    source = ensure_demo_bundle(args.size)
    out: dict = {"size": args.size}
    for name, code in (("chain", CHAIN), ("panel", PANEL)):
        shutil.copytree(source, root / name)
        cpu, wall = children_cpu(), time.perf_counter()
        subprocess.run([sys.executable, "-c", code.format(path=str(root / name))], check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        out[f"{name}_cpu_s"] = round(children_cpu() - cpu, 1)
        out[f"{name}_wall_s"] = round(time.perf_counter() - wall, 1)
        out[f"load_average_after_{name}"] = round(os.getloadavg()[0], 2)
    out["ratio"] = round(out["panel_cpu_s"] / out["chain_cpu_s"], 3)
    out["identical_latents"] = bool(np.array_equal(np.load(root / "chain" / "language" / "latents.npy"),
                                                   np.load(root / "panel" / "language" / "latents.npy")))
    print(json.dumps(out))
    shutil.rmtree(root, ignore_errors=True)
    return 0

