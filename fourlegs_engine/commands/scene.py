"""``fourlegs info PATH | --demo [--json]``: what a scene holds, without loading latents."""
from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Any

from ..errors import InputError
from .options import add_demo_argument


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "info", help="summarize a scene: timesteps, Gaussians, cameras, bounds, memory, language field",
        description="Print T, N, cameras (train/test), image size, scene bounds, foreground share, memory "
                    "footprint and whether a language field is present. PATH: a bundle directory, a Dynamic "
                    "3D Gaussians directory (params.npz), a 3DGS .ply file or a directory of per-frame .ply files.")
    p.add_argument("path", nargs="?", help="scene to describe")
    add_demo_argument(p)
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=run_info)


def run_info(args: argparse.Namespace) -> int:
    from ..scene.loaders import load_scene

    if bool(args.demo) == bool(args.path):
        raise InputError("give either a scene PATH or --demo (exactly one)", field="info")
    path = demo_bundle_path() if args.demo else args.path
    scene = load_scene(path)
    summary = scene.summary()
    if scene.root is not None:
        from ..scene.disk_usage import bundle_disk_usage
        summary["disk_bytes"] = bundle_disk_usage(scene.root)
    try:
        print(json.dumps(summary, indent=2) if args.json else format_summary(summary), flush=True)
    except BrokenPipeError:  # e.g. `fourlegs info --demo | head -3`: the reader left, not an error
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    return 0


def demo_bundle_path():
    """The demo bundle from the synthetic benchmark generator (built into the cache on first use)."""
    try:
        from ..demo.synthetic import ensure_demo_bundle
    except ImportError as exc:
        raise InputError(f"the demo scene generator is not available ({exc})", field="--demo") from None
    return ensure_demo_bundle()


def _mib(n: int) -> str:
    return f"{n / 2**20:.1f} MiB"


def format_summary(s: dict[str, Any]) -> str:
    """Human-readable lines for :meth:`Scene.summary`."""
    size = f"{s['image_size'][0]}x{s['image_size'][1]}" if s.get("image_size") else "-"
    fg = "-" if s.get("foreground_share") is None else f"{100 * s['foreground_share']:.1f}%"
    lang = "no"
    if s.get("language_field"):
        lang = f"yes (latent dim {s.get('latent_dim')}, {_mib(s.get('latents_bytes_on_disk', 0))} on disk)"
    rows = [
        ("scene", s.get("name")),
        ("location", s.get("root") or "-"),
        ("timesteps (T)", f"{s['num_timesteps']} at {s.get('fps', 0):g} fps"),
        ("Gaussians (N)", f"{s['num_gaussians']:,}"),
        ("cameras", f"{s['num_train_cameras']} train, {s['num_test_cameras']} test"),
        ("image size", size),
        ("bounds min", " ".join(f"{v:.3f}" for v in s["bounds_min"])),
        ("bounds max", " ".join(f"{v:.3f}" for v in s["bounds_max"])),
        ("foreground", fg),
        ("colour model", s.get("color_model")),
        ("memory", _mib(s["memory_bytes"])),
        ("language field", lang),
    ]
    disk = s.get("disk_bytes")
    if disk:
        parts = sorted(((k, v) for k, v in disk.items() if k != "total" and v), key=lambda kv: -kv[1])
        rows.append(("on disk", f"{_mib(disk['total'])} (" + ", ".join(f"{k} {_mib(v)}" for k, v in parts) + ")"))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)
