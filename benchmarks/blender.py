"""``fourlegs bench blender``: seconds and accuracy of the Blender layer, in one run (bpy child process).

Measures
- import: N Gaussians into one point-cloud object (seconds), and one scene-timestep switch (seconds);
- render: per frame, the "4-LEGS Splats" engine through Blender (bpy.ops.render.render) against the
  engine's rasterizer called directly for the same camera and timestep (seconds each), and the
  accuracy of the Blender path: max |Combined pass - direct RGB| (must be ~0: Blender adds nothing).

    python -m benchmarks.blender --gaussians 300000 --resolution 640x360 --frames 3 --json b.json --plot b.png
"""
from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np


def bench_import(n: int, seed: int = 0) -> dict[str, float]:
    import bpy

    from fourlegs_addon import importer
    from fourlegs_engine import scene as scene_pkg

    rng = np.random.default_rng(seed)
    T = 2
    rot = np.zeros((T, n, 4), np.float32)
    rot[..., 0] = 1
    g = scene_pkg.GaussianSequence(means=rng.normal(size=(T, n, 3)).astype(np.float32), rotations=rot,
                                   log_scales=np.full((n, 3), math.log(0.01), np.float32),
                                   opacity_logits=np.zeros(n, np.float32),
                                   colors=rng.uniform(size=(T, n, 3)).astype(np.float32))
    scene = scene_pkg.Scene(gaussians=g, cameras=scene_pkg.CameraRig(), name="bench")
    bpy.ops.wm.read_factory_settings(use_empty=True)
    t0 = time.perf_counter()
    importer.import_scene(bpy.context.scene, scene, with_cameras=False)
    t_import = time.perf_counter() - t0
    t0 = time.perf_counter()
    bpy.context.scene.fourlegs.timestep = 1.0
    t_switch = time.perf_counter() - t0
    return {"gaussians": n, "import_s": t_import, "timestep_switch_s": t_switch}


def bench_render(scene_path: Optional[str], width: int, height: int, frames: int) -> list[dict[str, Any]]:
    import bpy
    import OpenEXR
    import torch

    from fourlegs_addon import convert, importer, render_engine
    from fourlegs_engine.render import rasterize
    from fourlegs_engine.scene.synthetic import ensure_demo_bundle

    if scene_path is None:
        scene_path = str(ensure_demo_bundle("demo"))
    scene = importer.load_engine_scene(scene_path)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bl_scene = bpy.context.scene
    importer.import_scene(bl_scene, scene, source=scene_path)
    bl_scene.render.engine = render_engine.ENGINE_ID
    bl_scene.render.resolution_x, bl_scene.render.resolution_y = width, height
    bl_scene.view_layers[0].use_pass_z = True
    rows = []
    timesteps = np.linspace(0, scene.num_timesteps - 1, frames).round().astype(int)
    with tempfile.TemporaryDirectory() as tmp:
        for i, t in enumerate(timesteps):
            bl_scene.fourlegs.timestep = float(t)
            t0 = time.perf_counter()
            bpy.ops.render.render()
            t_blender = time.perf_counter() - t0
            exr = Path(tmp) / f"{i}.exr"
            bl_scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
            bpy.data.images["Render Result"].save_render(str(exr))
            combined = None
            for part in OpenEXR.File(str(exr)).parts:
                for name, ch in part.channels.items():
                    if name.endswith("ViewLayer.Combined"):
                        combined = np.asarray(ch.pixels, np.float32)[..., :3]
            camera = render_engine.scene_camera(bl_scene, bpy.context.evaluated_depsgraph_get(), width, height)
            frame = scene.gaussians.at(int(t))
            t0 = time.perf_counter()
            with torch.no_grad():
                direct = rasterize(frame.means, frame.rotations, frame.log_scales, frame.opacity_logits, camera,
                                   colors=frame.colors, outputs=("rgb", "alpha", "depth"))["rgb"].numpy()
            t_direct = time.perf_counter() - t0
            rows.append({"timestep": int(t), "blender_s": t_blender, "direct_s": t_direct,
                         "overhead_s": t_blender - t_direct,
                         "max_abs_diff": float(np.abs(combined - convert.srgb_to_linear(direct)).max())})
    return rows


def write_plot(path: Path, result: dict[str, Any]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result["render"]
    fig, ax = plt.subplots(figsize=(7, 3.2), dpi=100)
    x = np.arange(len(rows))
    ax.bar(x - 0.2, [r["direct_s"] for r in rows], 0.4, label="engine rasterize (direct)")
    ax.bar(x + 0.2, [r["blender_s"] for r in rows], 0.4, label="through Blender (F12)")
    ax.set_xticks(x, [f"t={r['timestep']}\nmax|Δ|={r['max_abs_diff']:.1e}" for r in rows])
    ax.set_ylabel("seconds per frame")
    res = result["resolution"]
    imp = result["import"]
    ax.set_title(f"{res[0]}x{res[1]}; import {imp['gaussians']:,} Gaussians: {imp['import_s']:.2f} s")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def build_parser(p: Optional[argparse.ArgumentParser] = None) -> argparse.ArgumentParser:
    """Options (shared with ``fourlegs bench blender``, which forwards them to a bpy child process)."""
    p = p or argparse.ArgumentParser(prog="fourlegs bench blender", description=__doc__.splitlines()[0])
    p.add_argument("--gaussians", type=int, default=300_000, help="Gaussians for the import benchmark")
    p.add_argument("--scene", default=None, help="scene for the render benchmark (default: the demo scene)")
    p.add_argument("--resolution", default="640x360", help="render resolution WIDTHxHEIGHT (default 640x360)")
    p.add_argument("--frames", type=int, default=3, help="frames (timesteps spread over the scene) to render")
    p.add_argument("--json", default=None, help="write the measurements here")
    p.add_argument("--plot", default=None, help="write a bar chart (PNG) here")
    return p


def forward_argv(args: argparse.Namespace) -> list[str]:
    out = ["--gaussians", str(args.gaussians), "--resolution", args.resolution, "--frames", str(args.frames)]
    for flag, value in (("--scene", args.scene), ("--json", args.json), ("--plot", args.plot)):
        if value is not None:
            out += [flag, str(value)]
    return out


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    import bpy

    from fourlegs_addon import registration

    registration.register()
    width, height = (int(v) for v in args.resolution.lower().split("x"))
    result = {"import": bench_import(args.gaussians), "resolution": [width, height],
              "render": bench_render(args.scene, width, height, args.frames),
              "threads": __import__("torch").get_num_threads(), "blender": bpy.app.version_string}
    imp = result["import"]
    print(f"import {imp['gaussians']:,} Gaussians: {imp['import_s']:.3f} s; timestep switch {imp['timestep_switch_s']:.3f} s")
    print(f"{'timestep':>8} {'blender s':>10} {'direct s':>9} {'overhead s':>10} {'max|diff|':>10}")
    for r in result["render"]:
        print(f"{r['timestep']:>8} {r['blender_s']:>10.3f} {r['direct_s']:>9.3f} {r['overhead_s']:>10.3f} "
              f"{r['max_abs_diff']:>10.2e}")
    from fourlegs_engine import fileio

    if args.json:
        fileio.write_json_atomic(args.json, result)
    if args.plot:
        with fileio.atomic_path(args.plot) as tmp:
            write_plot(tmp, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
