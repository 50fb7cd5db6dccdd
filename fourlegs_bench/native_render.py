"""The same highlight frames rendered by the 4-LEGS Splats engine (bpy 5.0, PyTorch) and by Blender 5.3's
own EEVEE and Cycles: image agreement (PSNR against the 4-LEGS render) and seconds per frame.

    fourlegs bench native-render --out docs/bench/native_render        # runs both Blenders

Two interpreters, because no Blender has both: ``--python311`` (bpy 5.0.1 + PyTorch, default .venv) renders
with the 4-LEGS engine and ``--python313`` (bpy 5.3, default .venv313) with EEVEE and Cycles. The scene is
the demo scene (30k Gaussians, 320x180 cameras); the frames are a plan of ``--frames`` frames from the
camera that sees the flying ball best, at the ball's timesteps, every other frame desaturated around the
ball (relevancy 1 on the ball's Gaussians: the same mask for every renderer, stored beside the scene the
way Generate Highlight stores a query's relevancy). Seconds are wall seconds of ``bpy.ops.render.render``
and CPU seconds of this process (all threads); on a shared machine the CPU seconds are the steadier figure.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
QUERY = "a ball flying in the air"


def make_plan(scene, frames: int, width: int, height: int) -> dict:
    """Frames at the ball's timesteps from the camera that sees it nearest the image centre."""
    names = scene.metadata["labels"]
    ball_id = names.index("ball flying in the air")
    steps = [t for t in range(scene.num_timesteps) if (scene.gaussians.labels[t] == ball_id).sum() > 50]
    steps = [steps[int(i)] for i in np.linspace(0, len(steps) - 1, frames).round()]
    t0 = steps[len(steps) // 2]
    centre = np.asarray(scene.gaussians.means[t0])[scene.gaussians.labels[t0] == ball_id].mean(axis=0)

    def off_centre(cam):
        uv, z = cam.project(centre[None])
        return float(np.hypot(*(uv[0] - [cam.width / 2, cam.height / 2]))) if z[0] > 0 else 1e9

    cam = min(scene.cameras.cameras(t0, "train"), key=off_centre)
    key = {"c2w": cam.c2w.tolist(), "focal_px": float(cam.fx) * width / cam.width, "sensor_width_mm": 36.0,
           "lens_mm": float(cam.fx) * 36.0 / cam.width}
    weights = {str(f): float(f % 2 == 1) for f in range(1, frames + 1)}
    return {"format": "fourlegs-highlight-plan", "version": 1,
            "scene": {"name": scene.name, "path": None, "num_timesteps": scene.num_timesteps, "fps": scene.fps},
            "query": QUERY,
            "localization": {"found": True, "message": "", "segment": [steps[0], steps[-1]], "peak": t0,
                             "segments": [[steps[0], steps[-1]]], "scores": [], "action_centre": centre.tolist(),
                             "best_view": cam.name},
            "fps": 24, "resolution": [width, height], "frame_start": 1, "frame_end": frames,
            "shots": [{"name": "replay", "effect": "desaturate_background", "frame_start": 1, "frame_end": frames,
                       "camera_keys": [dict(key, frame=f) for f in range(1, frames + 1)],
                       "time_keys": [{"frame": f, "timestep": float(t)} for f, t in enumerate(steps, 1)],
                       "interpolation": "linear", "params": {}}],
            "passes": {"rgb": [[1, frames]], "relevancy": [[1, frames]]},
            "desaturate": {"ranges": [[1, frames]], "fade_in": 0, "fade_out": 0, "strength": 1.0, "weights": weights},
            "messages": []}


def render(out: Path, engines: list[str], samples: dict[str, int], frames: list[int]) -> None:
    """In a Blender Python: import the copied scene, apply the plan, render ``frames`` with ``engines``."""
    import bpy

    from fourlegs_addon import highlight_ops, registration

    registration.register()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    assert bpy.ops.fourlegs.import_scene(filepath=str(out / "scene" / "scene.json")) == {"FINISHED"}
    scene = bpy.context.scene
    plan = json.loads((out / "plan.json").read_text())
    scene.fourlegs.renderer = "FOURLEGS" if engines == ["FOURLEGS_SPLATS"] else "NATIVE"
    highlight_ops.generate_highlight(scene, plan)
    timings = {}
    for engine in engines:
        scene.render.engine = engine
        scene.cycles.samples, scene.eevee.taa_render_samples = samples["CYCLES"], samples["BLENDER_EEVEE"]
        rows = []
        for frame in frames:
            scene.frame_set(frame)
            scene.render.filepath = str(out / "frames" / f"{engine}_{frame:03d}.png")
            cpu, wall = time.process_time(), time.perf_counter()
            assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
            rows.append({"frame": frame, "seconds": time.perf_counter() - wall, "cpu_seconds": time.process_time() - cpu})
        timings[engine] = rows
    (out / f"timings_{'_'.join(engines)}.json").write_text(json.dumps(
        {"blender": bpy.app.version_string, "samples": samples, "frames": timings}, indent=1))


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(1.0 / mse)


def compare(out: Path, frames: int) -> dict:
    from PIL import Image

    def load(engine, f):
        path = out / "frames" / f"{engine}_{f:03d}.png"
        return np.asarray(Image.open(path).convert("RGB"), np.float64) / 255.0 if path.is_file() else None

    rows = {}
    for engine in ("BLENDER_EEVEE", "CYCLES"):
        timing = out / f"timings_{engine}.json"
        if not timing.is_file():
            continue
        times = {r["frame"]: r for r in json.loads(timing.read_text())["frames"][engine]}
        per = [{"frame": f, "desaturated": f % 2 == 1, "psnr_db": psnr(load(engine, f), load("FOURLEGS_SPLATS", f)),
                **{k: round(v, 2) for k, v in times[f].items() if k != "frame"}}
               for f in range(1, frames + 1) if f in times and load(engine, f) is not None]
        rows[engine] = per
    ours = json.loads((out / "timings_FOURLEGS_SPLATS.json").read_text())["frames"]["FOURLEGS_SPLATS"]
    rows["FOURLEGS_SPLATS"] = [{"frame": r["frame"], "desaturated": r["frame"] % 2 == 1,
                                **{k: round(v, 2) for k, v in r.items() if k != "frame"}} for r in ours]
    summary = {engine: {"frames": len(per),
                        "mean_psnr_db": round(float(np.mean([r["psnr_db"] for r in per])), 2) if "psnr_db" in per[0] else None,
                        "seconds_per_frame": round(float(np.mean([r["seconds"] for r in per])), 2),
                        "cpu_seconds_per_frame": round(float(np.mean([r["cpu_seconds"] for r in per])), 2)}
               for engine, per in rows.items() if per}
    result = {"frames": rows, "summary": summary, "load_average": os.getloadavg()}
    (out / "comparison.json").write_text(json.dumps(result, indent=1))
    return result


def build_parser(parser: argparse.ArgumentParser) -> None:
    """The options of ``fourlegs bench native-render`` (and of its internal per-Blender runs)."""
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "bench" / "native_render",
                        help="folder of the frames, timings and comparison.json (default docs/bench/native_render)")
    parser.add_argument("--frames", type=int, default=6, help="frames of the plan (default 6)")
    parser.add_argument("--eevee-frames", type=int, default=2, help="EEVEE renders only the first N frames (slow "
                                                                    "without a GPU; default 2)")
    parser.add_argument("--python311", default=str(REPO / ".venv" / "bin" / "python"),
                        help="a Python with bpy 5.0 and PyTorch (the 4-LEGS Splats engine)")
    parser.add_argument("--python313", default=str(REPO / ".venv313" / "bin" / "python"),
                        help="a Python with bpy 5.3 (EEVEE and Cycles)")
    parser.add_argument("--cycles-samples", type=int, default=16, help="Cycles samples (default 16)")
    parser.add_argument("--eevee-samples", type=int, default=4, help="EEVEE samples (default 4)")
    parser.add_argument("--render", nargs="+", help=argparse.SUPPRESS)  # internal: engines to render here


def run(args: argparse.Namespace) -> int:
    """Prepare the plan and relevancy, render with each Blender in its own process, print the summary."""
    samples = {"CYCLES": args.cycles_samples, "BLENDER_EEVEE": args.eevee_samples}
    out = args.out.resolve()
    if args.render:
        frames = list(range(1, (args.eevee_frames if args.render == ["BLENDER_EEVEE"] else args.frames) + 1))
        render(out, args.render, samples, frames)
        return 0

    from fourlegs_addon import relevancy_store
    from fourlegs_engine.scene import load_scene
    from fourlegs_engine.demo.synthetic import ensure_demo_bundle

    shutil.rmtree(out / "scene", ignore_errors=True)
    (out / "frames").mkdir(parents=True, exist_ok=True)
    shutil.copytree(ensure_demo_bundle("demo"), out / "scene")
    scene = load_scene(out / "scene")
    plan = make_plan(scene, args.frames, 320, 180)
    (out / "plan.json").write_text(json.dumps(plan, indent=1))
    ball_id = scene.metadata["labels"].index("ball flying in the air")
    for key in plan["shots"][0]["time_keys"]:
        t = int(key["timestep"])
        relevancy_store.save(scene, QUERY, t, (scene.gaussians.labels[t] == ball_id).astype(np.float32))
    base = ["-m", "fourlegs_bench.native_render", "--out", str(out), "--frames", str(args.frames),
            "--eevee-frames", str(args.eevee_frames), "--cycles-samples", str(args.cycles_samples),
            "--eevee-samples", str(args.eevee_samples)]
    env = dict(os.environ, FOURLEGS_CACHE=os.environ.get("FOURLEGS_CACHE", str(REPO / ".cache" / "fourlegs")))
    runs = [(args.python311, ["FOURLEGS_SPLATS"]), (args.python313, ["CYCLES"])]
    runs += [(args.python313, ["BLENDER_EEVEE"])] if args.eevee_frames > 0 else []
    for python, engines in runs:
        subprocess.run([python, *base, "--render", *engines], check=True, env=env, cwd=REPO)
    shutil.rmtree(out / "scene", ignore_errors=True)  # the demo scene: regenerated by ensure_demo_bundle
    print(json.dumps(compare(out, args.frames)["summary"], indent=1))
    return 0


if __name__ == "__main__":  # the per-Blender runs: python -m fourlegs_bench.native_render --render ENGINE
    _parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    build_parser(_parser)
    sys.exit(run(_parser.parse_args()))
