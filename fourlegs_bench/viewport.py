"""Milliseconds per viewport frame of the 4-LEGS Splats engine's view_draw image (CPU rasterizer).

    python -m fourlegs_bench.viewport [--size demo] [--region 1920x1080] [--repeats 5]

Generates the synthetic scene of ``--size`` in memory, imports it with the add-on (bpy module), and times
``render_engine.viewport_image`` (what view_draw rasterizes before uploading it as a texture) from the
scene's first camera for a region of ``--region`` pixels: wall and process CPU time per frame, median.
"""
from __future__ import annotations

import argparse
import statistics
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="demo")
    ap.add_argument("--region", default="1920x1080")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--max-side", type=int, default=None, help="interactive size (default: the add-on's)")
    args = ap.parse_args()
    import bpy

    from fourlegs_addon import importer, registration, render_engine
    from fourlegs_engine.demo.synthetic import generate_scene

    registration.register()
    scene = generate_scene(args.size)
    bl_scene = bpy.context.scene
    importer.import_scene(bl_scene, scene)
    rw, rh = map(int, args.region.split("x"))
    depsgraph = bpy.context.evaluated_depsgraph_get()
    cam = bl_scene.camera.evaluated_get(depsgraph)
    window = cam.calc_matrix_camera(depsgraph, x=rw, y=rh)
    view = cam.matrix_world.inverted()
    max_side = args.max_side or render_engine.VIEWPORT_MAX_SIDE
    render_engine.viewport_image(bl_scene, view, window, rw, rh, max_side=max_side)  # warm-up
    walls, cpus = [], []
    for i in range(args.repeats):
        bl_scene.fourlegs.timestep = i % scene.num_timesteps
        w0, c0 = time.perf_counter(), time.process_time()
        img = render_engine.viewport_image(bl_scene, view, window, rw, rh, max_side=max_side)
        walls.append(time.perf_counter() - w0)
        cpus.append(time.process_time() - c0)
    print(f"{args.size}: N={scene.num_gaussians}, region {rw}x{rh} -> image {img.shape[1]}x{img.shape[0]}: "
          f"{1e3 * statistics.median(walls):.0f} ms wall, {1e3 * statistics.median(cpus):.0f} ms CPU per frame "
          f"(median of {args.repeats})")


if __name__ == "__main__":
    main()
