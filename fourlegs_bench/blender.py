"""``fourlegs bench blender``: seconds and accuracy of the Blender layer, in one run (bpy child process).

Measures
- import: N Gaussians into one point-cloud object (seconds), and one scene-timestep switch (seconds);
- render: per frame, the "4-LEGS Splats" engine through Blender (bpy.ops.render.render) against the
  engine's rasterizer called directly for the same camera and timestep (seconds each), and the
  accuracy of the Blender path: max |Combined pass - direct RGB| (must be ~0: Blender adds nothing).

With ``--scene DIR`` (a fitted bundle, e.g. what ``fourlegs fit`` writes) the import is the real scene's
instead of N synthetic Gaussians, through the add-on's import operator, and the run also measures what
an editor feels on it (:func:`bench_real_scene`): import seconds and the Blender process's peak memory,
the per-frame cost of scrubbing the timeline over every timestep (the frame-change handler plus the
depsgraph evaluation of the point instances), checked against the scene's means, and the Rendered-shading
viewport's draw cost (``render_engine.viewport_image``) at sampled timesteps.

    python -m fourlegs_bench.blender --gaussians 300000 --resolution 640x360 --frames 3 --json b.json --plot b.png
    python -m fourlegs_bench.blender --scene basketball/ --frames 3 --json b.json --plot b.png
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

from fourlegs_engine.errors import InputError


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


def memory_mb() -> dict[str, float]:
    """This process's resident memory in MB from ``/proc/self/status`` (Linux): ``rss`` (now), ``peak``
    (VmHWM, since the last :func:`reset_peak_memory`), ``anon`` (heap and other private pages) and ``file``
    (memory-mapped file pages, e.g. a bundle's arrays). Empty where /proc is missing."""
    fields = {"VmRSS": "rss", "VmHWM": "peak", "RssAnon": "anon", "RssFile": "file"}
    try:
        lines = Path("/proc/self/status").read_text().splitlines()
    except OSError:
        return {}
    out = {}
    for line in lines:
        key, _, value = line.partition(":")
        if key in fields:
            out[fields[key]] = int(value.split()[0]) / 1024.0
    return out


def reset_peak_memory() -> bool:
    """Restart the kernel's peak-RSS counter (VmHWM) at the current RSS; False where it cannot be."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _evaluated_positions(obj: Any) -> np.ndarray:
    """(N,3) point positions of the object's evaluated point instances (what the viewport draws)."""
    import bpy

    geometry = obj.evaluated_get(bpy.context.evaluated_depsgraph_get()).evaluated_geometry()  # keeps the cloud alive
    cloud = geometry.pointcloud
    out = np.empty(len(cloud.points) * 3, np.float32)
    cloud.attributes["position"].data.foreach_get("vector", out)
    return out.reshape(-1, 3)


def _view_from_camera(cam_obj: Any, width: int, height: int) -> tuple[Any, Any]:
    """(view_matrix, window_matrix) of a 3D viewport looking through ``cam_obj`` at ``width`` x ``height``."""
    import bpy

    view = cam_obj.matrix_world.inverted()
    window = cam_obj.calc_matrix_camera(bpy.context.evaluated_depsgraph_get(), x=width, y=height)
    return view, window


def bench_real_scene(scene_path: str, *, viewport_frames: int = 3, viewport_size: tuple[int, int] = (1280, 720)
                     ) -> dict[str, Any]:
    """A fitted scene in Blender at its real N and T: import, memory, scrubbing, viewport draw.

    Args:
        scene_path: a scene directory the import operator accepts (bundle, params.npz directory, PLY).
        viewport_frames: timesteps (spread over the scene) at which the Rendered-shading viewport is drawn.
        viewport_size: region size in pixels of that viewport (the image is rasterized at
            ``render_engine.viewport_size`` of it).
    Returns:
        ``import`` (seconds, CPU seconds, memory), ``scrub`` (per-frame seconds over every timestep, plus
        the largest |evaluated position - means[t]|), ``viewport`` (seconds per draw) and the scene's N, T.
    """
    import bpy

    from fourlegs_addon import importer, keyframes, render_engine

    bpy.ops.wm.read_factory_settings(use_empty=True)
    bl_scene = bpy.context.scene
    importer._SCENES.clear()
    before = memory_mb()
    peak_reset = reset_peak_memory()
    wall0, cpu0 = time.perf_counter(), time.process_time()
    try:
        result = bpy.ops.fourlegs.import_scene(filepath=str(Path(scene_path).resolve()))
    except RuntimeError as exc:  # the operator's one-line report, raised by bpy.ops
        raise InputError(str(exc).strip().splitlines()[0].removeprefix("Error: ")) from None
    import_s, import_cpu_s = time.perf_counter() - wall0, time.process_time() - cpu0
    after = memory_mb()
    if result != {"FINISHED"}:
        raise InputError("the import operator refused it (its report is above)", file=scene_path)
    obj = bl_scene.fourlegs.splat_object
    g = importer.engine_scene_for(obj).gaussians
    T, N = g.num_timesteps, g.num_gaussians
    imported = {"import_s": import_s, "import_cpu_s": import_cpu_s, "rss_before_mb": before.get("rss"),
                "peak_rss_mb": after.get("peak") if peak_reset else None, "rss_after_mb": after.get("rss"),
                "anon_after_mb": after.get("anon"), "file_after_mb": after.get("file")}

    # the timeline plays the capture: frame f shows timestep f - 1 (what a highlight plan's time keys do)
    action = keyframes.ensure_action(bl_scene, "bench scene time")
    keyframes.write_fcurve(bl_scene, action, keyframes.TIMESTEP_PATH, 0, [1, T], [0.0, float(T - 1)],
                           ["LINEAR", "LINEAR"])
    bl_scene.frame_start, bl_scene.frame_end = 1, T
    bl_scene.frame_set(1)
    reset_peak_memory()
    wall, cpu, worst = [], [], 0.0
    for frame in list(range(2, T + 1)) + [1]:
        wall0, cpu0 = time.perf_counter(), time.process_time()
        bl_scene.frame_set(frame)
        bpy.context.evaluated_depsgraph_get()
        wall.append(time.perf_counter() - wall0)
        cpu.append(time.process_time() - cpu0)
        if frame in (2, T // 2 + 1, T, 1):
            worst = max(worst, float(np.abs(_evaluated_positions(obj) - np.asarray(g.means[frame - 1])).max()))
    scrub_mem = memory_mb()
    reset_peak_memory()
    # half-way frames (slow motion): two timesteps blended per frame
    bl_scene.frame_set(1)
    half = []
    for t in np.linspace(0.5, T - 1.5, min(T - 1, 20)) if T > 1 else []:
        wall0 = time.perf_counter()
        bl_scene.fourlegs.timestep = float(t)
        bpy.context.evaluated_depsgraph_get()
        half.append(time.perf_counter() - wall0)
    # after a query: the (T,N) relevancy is stored and its heat colours are rewritten on every frame too
    relevancy = np.random.default_rng(0).uniform(size=(T, N)).astype(np.float32)
    importer.set_relevancy(obj, relevancy)
    with_relevancy, with_relevancy_cpu = [], []
    for frame in list(range(2, T + 1)) + [1]:
        wall0, cpu0 = time.perf_counter(), time.process_time()
        bl_scene.frame_set(frame)
        bpy.context.evaluated_depsgraph_get()
        with_relevancy.append(time.perf_counter() - wall0)
        with_relevancy_cpu.append(time.process_time() - cpu0)
    importer.show_relevancy(obj, False)
    importer._RELEVANCY.pop(importer.source_key(obj), None)
    scrub = {"frames": len(wall), "median_s": float(np.median(wall)), "p95_s": float(np.percentile(wall, 95)),
             "max_s": float(np.max(wall)), "median_cpu_s": float(np.median(cpu)), "per_frame_s": wall,
             "fractional_median_s": float(np.median(half)) if half else None,
             "with_relevancy_median_s": float(np.median(with_relevancy)),
             "with_relevancy_median_cpu_s": float(np.median(with_relevancy_cpu)),
             "max_abs_position_error": worst, "peak_rss_mb": scrub_mem.get("peak") if peak_reset else None}

    cam_obj = next((o for o in bl_scene.objects if o.type == "CAMERA"), None)
    draws, first, draw_base = [], None, None
    if cam_obj is not None:
        view, window = _view_from_camera(cam_obj, *viewport_size)
        wall0, cpu0 = time.perf_counter(), time.process_time()  # the first draw also warms the rasterizer up
        render_engine.viewport_image(bl_scene, view, window, *viewport_size, near=cam_obj.data.clip_start,
                                     far=cam_obj.data.clip_end)
        first = {"s": time.perf_counter() - wall0, "cpu_s": time.process_time() - cpu0,
                 "peak_rss_mb": memory_mb().get("peak") if peak_reset else None}
        draw_base = memory_mb().get("rss")
        reset_peak_memory()
        for t in np.linspace(0, T - 1, max(1, viewport_frames)).round().astype(int):
            bl_scene.fourlegs.timestep = float(t)
            wall0, cpu0 = time.perf_counter(), time.process_time()
            rgba = render_engine.viewport_image(bl_scene, view, window, *viewport_size,
                                                near=cam_obj.data.clip_start, far=cam_obj.data.clip_end)
            draws.append({"timestep": int(t), "s": time.perf_counter() - wall0, "cpu_s": time.process_time() - cpu0,
                          "coverage": float(rgba[..., 3].mean())})
    viewport = {"rss_before_draws_mb": draw_base, "peak_rss_mb": memory_mb().get("peak") if peak_reset else None,
                "region": list(viewport_size),
                "image": list(render_engine.viewport_size(*viewport_size)),
                "camera": cam_obj.name if cam_obj else None, "first_draw": first,
                "draws": draws}
    return {"scene": str(scene_path), "gaussians": N, "timesteps": T,
            "foreground_share": None if g.foreground is None else float(np.mean(g.foreground)),
            "import": imported, "scrub": scrub, "viewport": viewport}


def bench_render(scene_path: Optional[str], width: int, height: int, frames: int) -> list[dict[str, Any]]:
    import bpy
    import OpenEXR
    import torch

    from fourlegs_addon import convert, importer, render_engine
    from fourlegs_engine.render import rasterize
    from fourlegs_engine.demo.synthetic import ensure_demo_bundle

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
            t0, c0 = time.perf_counter(), time.process_time()
            bpy.ops.render.render()
            t_blender, c_blender = time.perf_counter() - t0, time.process_time() - c0
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
            t0, c0 = time.perf_counter(), time.process_time()
            with torch.no_grad():
                direct = rasterize(frame.means, frame.rotations, frame.log_scales, frame.opacity_logits, camera,
                                   colors=frame.colors, outputs=("rgb", "alpha", "depth"))["rgb"].numpy()
            t_direct, c_direct = time.perf_counter() - t0, time.process_time() - c0
            rows.append({"timestep": int(t), "blender_s": t_blender, "direct_s": t_direct,
                         "overhead_s": t_blender - t_direct, "blender_cpu_s": c_blender, "direct_cpu_s": c_direct,
                         "max_abs_diff": float(np.abs(combined - convert.srgb_to_linear(direct)).max())})
    return rows


def write_plot(path: Path, result: dict[str, Any]) -> None:
    """Bar chart of the render rows; with a real scene, also its scrub seconds per frame and viewport draws."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    real = result.get("real_scene")
    fig, axes = plt.subplots(1, 2 if real else 1, figsize=(12 if real else 7, 3.4), dpi=100, squeeze=False)
    ax = axes[0, 0]
    rows = result["render"]
    x = np.arange(len(rows))
    ax.bar(x - 0.2, [r["direct_s"] for r in rows], 0.4, label="engine rasterize (direct)")
    ax.bar(x + 0.2, [r["blender_s"] for r in rows], 0.4, label="through Blender (F12)")
    ax.set_xticks(x, [f"t={r['timestep']}\nmax|Δ|={r['max_abs_diff']:.1e}" for r in rows])
    ax.set_ylabel("seconds per frame")
    res = result["resolution"]
    imp = result["import"]
    ax.set_title(f"F12 at {res[0]}x{res[1]}; import {imp['gaussians']:,} Gaussians: {imp['import_s']:.2f} s",
                 fontsize=9)
    ax.legend(fontsize=8)
    if real:
        ax = axes[0, 1]
        scrub, viewport = real["scrub"], real["viewport"]
        frames = np.arange(2, len(scrub["per_frame_s"]) + 1)
        ax.plot(frames, 1e3 * np.asarray(scrub["per_frame_s"][:-1]), lw=0.8,
                label=f"scrub: frame change + depsgraph (median {1e3 * scrub['median_s']:.2f} ms)")
        ax.set_xlabel("timeline frame (= timestep + 1)")
        ax.set_ylabel("milliseconds per frame")
        ax.set_yscale("log")
        if viewport["draws"]:
            ax.scatter([d["timestep"] + 1 for d in viewport["draws"]], [1e3 * d["s"] for d in viewport["draws"]],
                       color="C3", zorder=3, label="Rendered viewport draw {}x{}".format(*viewport["image"]))
        i = real["import"]
        peak = "" if i["peak_rss_mb"] is None else f", peak RSS {i['peak_rss_mb']:.0f} MB"
        shown = [1e3 * v for v in scrub["per_frame_s"]] + [1e3 * d["s"] for d in viewport["draws"]]
        ax.set_ylim(0.5 * min(shown), 300.0 * max(shown))  # room for the legend above the data
        ax.set_title(f"{Path(real['scene']).name}: N={real['gaussians']:,}, T={real['timesteps']}; "
                     f"import {i['import_s']:.2f} s{peak}", fontsize=9)
        ax.legend(fontsize=8, loc="upper center")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def build_parser(p: Optional[argparse.ArgumentParser] = None) -> argparse.ArgumentParser:
    """Options (shared with ``fourlegs bench blender``, which forwards them to a bpy child process)."""
    p = p or argparse.ArgumentParser(prog="fourlegs bench blender", description=__doc__.splitlines()[0])
    p.add_argument("--gaussians", type=int, default=300_000,
                   help="synthetic Gaussians for the import benchmark (without --scene)")
    p.add_argument("--scene", default=None,
                   help="a real scene (e.g. a `fourlegs fit` bundle): import, memory, timeline scrubbing and "
                        "viewport draws at its real N and T, and the render rows (default: synthetic N and the "
                        "demo scene)")
    p.add_argument("--viewport-frames", type=int, default=3,
                   help="with --scene: timesteps at which the Rendered-shading viewport is drawn")
    p.add_argument("--resolution", default="640x360", help="render resolution WIDTHxHEIGHT (default 640x360)")
    p.add_argument("--frames", type=int, default=3, help="frames (timesteps spread over the scene) to render")
    p.add_argument("--threads", type=int, default=0,
                   help="torch CPU threads (default 0: torch's choice); 1 gives repeatable CPU seconds on shared cores")
    p.add_argument("--json", default=None, help="write the measurements here")
    p.add_argument("--plot", default=None, help="write a bar chart (PNG) here")
    return p


def forward_argv(args: argparse.Namespace) -> list[str]:
    out = ["--gaussians", str(args.gaussians), "--resolution", args.resolution, "--frames", str(args.frames),
           "--viewport-frames", str(args.viewport_frames), "--threads", str(args.threads)]
    for flag, value in (("--scene", args.scene), ("--json", args.json), ("--plot", args.plot)):
        if value is not None:
            out += [flag, str(value)]
    return out


def print_real_scene(real: dict[str, Any]) -> None:
    i, sc, vp = real["import"], real["scrub"], real["viewport"]
    peak = "-" if i["peak_rss_mb"] is None else f"{i['peak_rss_mb']:.0f}"
    print(f"real scene {real['scene']}: N={real['gaussians']:,} T={real['timesteps']}")
    print(f"{'import s':>9} {'cpu s':>6} {'RSS before MB':>13} {'peak RSS MB':>11} {'after: anon MB':>14} "
          f"{'file MB':>7} {'scrub s/frame':>13} {'p95':>7} {'half-step':>9} {'+relevancy':>10} {'max|pos-means|':>14}")
    half = "-" if sc["fractional_median_s"] is None else f"{sc['fractional_median_s']:.4f}"
    print(f"{i['import_s']:>9.3f} {i['import_cpu_s']:>6.2f} {i['rss_before_mb']:>13.0f} {peak:>11} "
          f"{i['anon_after_mb']:>14.0f} {i['file_after_mb']:>7.0f} {sc['median_s']:>13.4f} {sc['p95_s']:>7.4f} "
          f"{half:>9} {sc['with_relevancy_median_s']:>10.4f} {sc['max_abs_position_error']:>14.1e}")
    print(f"CPU s per frame: scrub {sc['median_cpu_s']:.5f}, with relevancy {sc['with_relevancy_median_cpu_s']:.5f}")
    if vp["first_draw"]:
        print(f"viewport first draw (one-time: torch import unless --threads, rasterizer warm-up): {vp['first_draw']['s']:.3f} s "
              f"({vp['first_draw']['cpu_s']:.2f} CPU s)")
    for d in vp["draws"]:
        print(f"viewport draw {vp['image'][0]}x{vp['image'][1]} through {vp['camera']} at t={d['timestep']}: "
              f"{d['s']:.3f} s ({d['cpu_s']:.2f} CPU s), coverage {d['coverage']:.2f}")
    if vp["peak_rss_mb"] is not None:
        print(f"peak RSS: import {peak} MB, scrubbing every frame {sc['peak_rss_mb']:.0f} MB, first viewport draw "
              f"{vp['first_draw']['peak_rss_mb']:.0f} MB, later draws {vp['peak_rss_mb']:.0f} MB "
              f"(from {vp['rss_before_draws_mb']:.0f} MB)")


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    import bpy

    from fourlegs_addon import registration

    registration.register()
    if args.threads > 0:
        import torch

        torch.set_num_threads(args.threads)
    width, height = (int(v) for v in args.resolution.lower().split("x"))
    result: dict[str, Any] = {}
    if args.scene:  # first, so the import's memory is measured in a process that has loaded nothing else
        try:
            real = bench_real_scene(args.scene, viewport_frames=args.viewport_frames)
        except InputError as exc:
            print(f"fourlegs bench blender: {exc}", file=sys.stderr)
            return 2
        result["real_scene"] = real
        result["import"] = {"gaussians": real["gaussians"], "import_s": real["import"]["import_s"],
                            "timestep_switch_s": real["scrub"]["median_s"]}
    else:
        result["import"] = bench_import(args.gaussians)
    result.update({"resolution": [width, height], "render": bench_render(args.scene, width, height, args.frames),
                   "threads": __import__("torch").get_num_threads(), "blender": bpy.app.version_string})
    imp = result["import"]
    print(f"import {imp['gaussians']:,} Gaussians: {imp['import_s']:.3f} s; timestep switch {imp['timestep_switch_s']:.3f} s")
    if args.scene:
        print_real_scene(result["real_scene"])
    print(f"{'timestep':>8} {'blender s':>10} {'direct s':>9} {'overhead s':>10} {'blender CPU s':>13} "
          f"{'direct CPU s':>12} {'max|diff|':>10}")
    for r in result["render"]:
        print(f"{r['timestep']:>8} {r['blender_s']:>10.3f} {r['direct_s']:>9.3f} {r['overhead_s']:>10.3f} "
              f"{r['blender_cpu_s']:>13.2f} {r['direct_cpu_s']:>12.2f} {r['max_abs_diff']:>10.2e}")
    from fourlegs_engine import fileio

    if args.json:
        fileio.write_json_atomic(args.json, result)
    if args.plot:
        with fileio.atomic_path(args.plot) as tmp:
            write_plot(tmp, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
