"""The main job, headless through the bpy module: scene -> language field -> query -> plan -> video.

    python -m fourlegs_addon.headless --demo "a ball flying in the air" --preset broadcast -o out/

(``fourlegs highlight ...`` runs exactly this in a subprocess, so the engine's process never imports
bpy.) Stages:

1. scene: ``--demo`` generates/reuses the synthetic demo bundle; otherwise SCENE is a bundle,
   params.npz directory, PLY file or PLY directory (non-bundles are converted to a bundle in the
   cache, because the language stages store their results inside the bundle);
2. language field (only if the bundle has none): extract features -> train the autoencoder -> distil
   by lifting (the fast, learning-free mode); every stage resumes where it stopped;
3. query + plan: the engine's QueryEngine localizes only what the preset needs, the planner writes
   the plan;
4. Blender: import the point cloud and cameras, Generate Highlight, render every frame with the
   "4-LEGS Splats" engine (Relevancy only on frames the plan lists) through the compositor to
   H.264 MP4, save the .blend.

``out/`` receives highlight.mp4, highlight.blend, plan.json, report.json (timings, localization,
render statistics) and scores.png (the s_t curve). A finished job (report.json present) is
never overwritten unless --overwrite; an interrupted one resumes: the language stages and the
rendered frames (kept in ``out/.frames-<plan hash>/`` until the MP4 is encoded) are reused. Every
file is written to a temporary name and renamed when complete.
"""
from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Any, Optional, Sequence

OUTPUT_NAMES = {"video": "highlight.mp4", "blend": "highlight.blend", "plan": "plan.json",
                "report": "report.json", "plot": "scores.png"}


#: the main job's query paths: fast (1-channel) spatial maps score like the exact ones for a fraction of
#: the time; the temporal path stays exact (a codebook pays off only over many queries of one scene);
#: docs/benchmarks.md has the figures
DEFAULT_QUERY_PATH = "exact"
DEFAULT_SPATIAL = "fast"


def build_parser(parser: Optional[argparse.ArgumentParser] = None) -> argparse.ArgumentParser:
    """The options of the main job (shared with ``fourlegs highlight``)."""
    from fourlegs_engine.cli_options import add_encoder_arguments

    p = parser or argparse.ArgumentParser(prog="fourlegs highlight", description=__doc__.splitlines()[0])
    p.add_argument("scene", nargs="?", default=None,
                   help="scene: bundle dir, params.npz dir, .ply file or dir of .ply files (or --demo)")
    p.add_argument("query", help="what to find, e.g. \"a ball flying in the air\"")
    p.add_argument("--demo", action="store_true", help="use the synthetic demo scene (generated on first use)")
    p.add_argument("--demo-size", default="demo", choices=("tiny", "demo", "bench", "full"),
                   help="size of the synthetic demo scene (default demo: 30k Gaussians, 48 timesteps)")
    p.add_argument("--preset", default="broadcast", help="highlight preset name or .toml file (default broadcast)")
    p.add_argument("-o", "--output", required=True, help="output directory")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    p.add_argument("--resolution", default=None,
                   help="output WIDTHxHEIGHT (default: 640x360 for --demo, else the preset's)")
    p.add_argument("--fps", type=float, default=None, help="output frame rate (default: the preset's)")
    p.add_argument("--render-threads", type=int, default=1, metavar="N",
                   help="torch threads for the per-frame rasterization (default 1: small per-frame work, "
                        "extra threads mostly wait; 0 = torch's default)")
    p.add_argument("--format", default="MP4", choices=("MP4", "PNG", "EXR"), help="video or image sequence")
    p.add_argument("--no-effect", action="append", default=[], metavar="EFFECT",
                   help="leave out the preset's shots with this effect (repeatable)")
    p.add_argument("--query-path", default=DEFAULT_QUERY_PATH, choices=("exact", "codebook"),
                   help="per-Gaussian relevancy path of the query engine (default %(default)s; see "
                        "`fourlegs bench accuracy-time` for what each costs and scores)")
    p.add_argument("--spatial", default=DEFAULT_SPATIAL, choices=("exact", "fast"),
                   help="relevancy maps for the best view and the action centre: exact (128-channel render, "
                        "per-pixel decode, paper) or fast (1-channel per-Gaussian relevancy render); "
                        "default %(default)s")
    add_encoder_arguments(p, default="auto")
    return p


def parse_resolution(text: Optional[str], demo: bool) -> Optional[tuple[int, int]]:
    from fourlegs_engine.cli_options import parse_resolution as parse

    if text is None:
        return (640, 360) if demo else None
    return parse(text, even=True)


class Timer:
    def __init__(self) -> None:
        self.timings: dict[str, float] = {}
        #: CPU seconds of this process (all threads) per stage: on a shared machine a steadier
        #: measure of a stage's work than its wall time
        self.cpu_timings: dict[str, float] = {}

    def __call__(self, name: str):
        timer = self

        class _Stage:
            def __enter__(self):
                self.t0, self.c0 = time.perf_counter(), time.process_time()
                print(f"[fourlegs] {name} ...", flush=True)

            def __exit__(self, *exc):
                timer.timings[name] = round(time.perf_counter() - self.t0, 3)
                timer.cpu_timings[name] = round(time.process_time() - self.c0, 3)
                if exc[0] is None:
                    print(f"[fourlegs] {name}: {timer.timings[name]:.1f} s", flush=True)

        return _Stage()


# ----------------------------------------------------------------------------- engine stages (no bpy)
def encoder_config(args: argparse.Namespace):
    from fourlegs_engine.cli_options import encoder_config_from_args

    return encoder_config_from_args(args)


def query_options(args: argparse.Namespace):
    from fourlegs_engine import api

    return api.QueryOptions(path=args.query_path, spatial=getattr(args, "spatial", DEFAULT_SPATIAL))


def write_scores_plot(path: Path, scores: Sequence[float], positive: Sequence[bool], segment, peak,
                      query: str) -> None:
    """s_t per timestep (bars; positive ones highlighted), the threshold 1/T, segment and peak."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fourlegs_engine import api

    s = list(scores)
    T = len(s)
    fig, ax = plt.subplots(figsize=(8, 3), dpi=100)
    colours = ["tab:orange" if p else "tab:gray" for p in positive]
    ax.bar(range(T), s, color=colours, width=0.9)
    if T:
        ax.axhline(1.0 / T, color="black", lw=0.8, ls="--", label="k = 1/T")
    if segment is not None:
        ax.axvspan(segment[0] - 0.5, segment[1] + 0.5, color="tab:blue", alpha=0.15, label="segment")
    if peak is not None:
        ax.axvline(peak, color="tab:red", lw=1.2, label="peak")
    ax.set_xlabel("timestep t")
    ax.set_ylabel("s_t")
    ax.set_title(f"temporal relevancy: {query!r}")
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    with api.atomic_path(path) as tmp:
        fig.savefig(tmp)
    plt.close(fig)


# ----------------------------------------------------------------------------- Blender stage
@contextlib.contextmanager
def blender_log_silenced():
    """Send Blender's per-frame log lines (C-level stdout) to /dev/null; tqdm reports progress on stderr."""
    sys.stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def torch_threads(n: Optional[int]):
    """The engine's scoped torch thread count (None or < 1: leave torch's setting).

    The per-frame rasterization is thousands of small tensor ops: on a busy machine extra OpenMP threads
    mostly wait at barriers, so the render uses one thread by default.
    """
    from fourlegs_engine import api

    return api.torch_threads(n)


def kernel_threads(n: Optional[int]):
    """The engine's scoped worker count of the fused blending kernel (None or < 1: leave it)."""
    from fourlegs_engine import api

    return api.kernel_threads(n)


def render_kernel_threads() -> int:
    """Workers of the per-frame blending kernel: every core this process may run on. They block when
    idle (no barrier spinning), so unlike extra torch threads they help on a quiet machine and cost
    nothing on a busy one."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


#: glibc ``mallopt`` parameters and their defaults
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_DEFAULT_TRIM, _DEFAULT_MMAP = 128 * 1024, 128 * 1024


@contextlib.contextmanager
def heap_kept(mmap_threshold: int = 32 * 1024 * 1024, trim_threshold: int = 1024 * 1024 * 1024):
    """Keep freed memory in the process heap during the block (glibc; elsewhere a no-op).

    Every frame allocates and frees the rasterizer's tile buffers (megabytes each); by default glibc
    serves them with mmap or trims the heap top after each free, so every frame faults its memory in
    again. With large buffers kept in the heap the faults disappear. The heap is trimmed when the block
    ends.
    """
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt, malloc_trim = libc.mallopt, libc.malloc_trim
    except (OSError, AttributeError):  # not glibc
        yield
        return
    changed = bool(mallopt(_M_MMAP_THRESHOLD, int(mmap_threshold))) and bool(mallopt(_M_TRIM_THRESHOLD,
                                                                                    int(trim_threshold)))
    try:
        yield
    finally:
        if changed:
            mallopt(_M_TRIM_THRESHOLD, _DEFAULT_TRIM)
            mallopt(_M_MMAP_THRESHOLD, _DEFAULT_MMAP)
            malloc_trim(0)


def blender_stage(scene: Any, plan: dict, engine: Any, query: str, out: dict[str, Path], fmt: str,
                  timer: Timer, render_threads: Optional[int] = 1) -> dict[str, Any]:
    """Import, Generate Highlight, render through the splat engine + compositor, save the .blend.

    ``render_threads``: torch threads while rendering frames (see :func:`torch_threads`; None keeps
    torch's default).
    """
    import bpy
    from tqdm import tqdm

    from fourlegs_engine import api

    from . import importer, operators, registration, render_engine, video

    bpy.ops.wm.read_factory_settings(use_empty=True)
    try:
        registration.register()
    except ValueError:  # already registered in this process
        pass
    bl_scene = bpy.context.scene
    with timer("blender import"):
        obj = importer.import_scene(bl_scene, scene, source=str(scene.root))
    rel_provider = (lambda t: engine.gaussian_relevancy(query, int(t)).numpy()) if engine is not None else None
    if rel_provider is not None:
        importer.set_relevancy_provider(obj, rel_provider)
    with timer("generate highlight"):
        operators.generate_highlight(bl_scene, plan)
    render_engine.reset_stats()
    cpu_frames = 0.0
    total = bl_scene.frame_end - bl_scene.frame_start + 1
    cpu_start = time.process_time()
    with timer("render"):
        with tqdm(total=total, desc="render", unit="frame") as bar, blender_log_silenced(), \
                torch_threads(render_threads), kernel_threads(render_kernel_threads()), heap_kept():
            progress = lambda done, n: bar.update(done - bar.n)  # noqa: E731
            if fmt == "EXR":
                video.render_animation(bl_scene, out["video"], fmt=fmt, overwrite=True, on_frame=progress)
            else:  # frame by frame into a resumable directory (an interrupted run continues from there)
                frames_dir = out["video"] if fmt == "PNG" else out["video"].parent / f".frames-{plan_digest(plan)}"
                bl_scene.render.image_settings.compression = 0 if fmt == "MP4" else 15  # MP4: temporary frames
                frames = video.render_frames(bl_scene, frames_dir, on_frame=progress)
                if fmt == "MP4":
                    cpu_frames = time.process_time() - cpu_start
                    with timer("encode mp4"):
                        video.encode_mp4(frames, out["video"], fps=bl_scene.render.fps,
                                         fps_base=bl_scene.render.fps_base, overwrite=True)
                    shutil.rmtree(frames_dir, ignore_errors=True)
    cpu_render = time.process_time() - cpu_start
    stats = dict(render_engine.stats)
    if stats.get("last_error"):
        raise RuntimeError(f"the 4-LEGS Splats engine failed: {stats['last_error']}")
    # the viewport shows the query's relevancy at the peak
    peak = (plan.get("localization") or {}).get("peak")
    if rel_provider is not None and peak is not None:
        importer.set_relevancy(obj, rel_provider(int(peak)), show=False)
    bl_scene.frame_set(bl_scene.frame_start)
    operators.fill_from_plan(bl_scene, plan, output=str(out["video"]), fmt=fmt)  # the panel as it was made
    importer.relative_sources(out["blend"].parent)
    with timer("save .blend"):
        with api.atomic_path(out["blend"]) as tmp:
            tmp.unlink()  # saving over an existing file would leave a .blend1 backup beside it
            bpy.ops.wm.save_as_mainfile(filepath=str(tmp), copy=True, compress=True)
    return {"frames_total": total, "frames_rendered": stats["frames"],
            "frames_reused": total - stats["frames"] if fmt != "EXR" else 0,
            "relevancy_frames": stats["relevancy_frames"],
            "splat_render_seconds": round(stats["seconds"], 3),
            "seconds_per_frame": round(stats["seconds"] / max(stats["frames"], 1), 3),
            # CPU time of this process (all threads): on a busy machine closer to quiet wall time
            "render_cpu_seconds": round(cpu_render, 3),
            "cpu_seconds_per_frame": round((cpu_frames if fmt == "MP4" else cpu_render) / max(stats["frames"], 1), 3),
            "render_threads": render_threads, "render_kernel_threads": render_kernel_threads()}


# ----------------------------------------------------------------------------- main
def run(args: argparse.Namespace) -> dict[str, Any]:
    from fourlegs_engine import api
    started = time.perf_counter()
    timer = Timer()
    out_dir = Path(args.output)
    suffix = {"MP4": ".mp4", "PNG": "", "EXR": ""}[args.format]
    out = {k: out_dir / v for k, v in OUTPUT_NAMES.items()}
    out["video"] = out_dir / ("highlight" + suffix if suffix else "frames")
    # report.json marks a finished job; without it, files here are an interrupted run's, resumed
    existing = [str(out[k]) for k in ("video", "blend", "report") if out[k].exists()]
    if existing and not args.overwrite:
        raise api.OutputExistsError(", ".join(existing))
    api.check_text(args.query, "query")
    record_outputs = api.claim_outputs(out_dir, [out[k] for k in ("plan", "plot")], overwrite=args.overwrite)
    resolution = parse_resolution(args.resolution, args.demo)

    if args.demo and args.scene is not None:
        raise api.InputError("give either --demo or a scene path, not both", field="scene")
    if not args.demo and args.scene is None:
        raise api.InputError("no scene given (a path, or --demo)", field="scene")
    with timer("scene"):
        scene = api.open_scene(args.scene, demo=args.demo_size if args.demo else None)
    preset = api.load_preset(args.preset)
    if args.no_effect:
        preset = preset.with_shots([s.effect for s in preset.shots if s.effect not in set(args.no_effect)])
    needs = api.plan_needs(preset)
    engine = None
    if needs or preset_needs_relevancy(preset):
        encoder = api.text_encoder(scene, encoder_config(args))
        scene = api.ensure_language_field(scene, encoder, progress=True, stage=timer)
        with timer("open query engine"):
            engine = api.open_query_engine(scene, encoder, options=query_options(args))
    with timer("localize + plan"):
        plan_obj = api.plan_highlight(scene, engine, args.query, preset, resolution=resolution, fps=args.fps)
        plan = plan_obj.to_dict()
    record_outputs()
    api.write_json_atomic(out["plan"], plan, overwrite=True)
    loc = plan.get("localization") or {}
    if loc.get("scores"):
        write_scores_plot(out["plot"], loc["scores"], loc.get("positive") or
                          [s > 1.0 / len(loc["scores"]) for s in loc["scores"]],
                          loc.get("segment"), loc.get("peak"), args.query)
    for msg in plan.get("messages", []):
        print(f"[fourlegs] note: {msg}", flush=True)

    render_info = blender_stage(scene, plan, engine, args.query, out, args.format, timer,
                                render_threads=getattr(args, "render_threads", 1) or None)
    report = {
        "format": "fourlegs-highlight-report", "version": 1,
        "query": args.query, "scene": {"name": scene.name, "path": str(scene.root),
                                       "num_timesteps": scene.num_timesteps, "num_gaussians": scene.num_gaussians},
        "preset": preset.name, "resolution": plan["resolution"], "fps": plan["fps"],
        "frames": [plan["frame_start"], plan["frame_end"]],
        "shots": [{"name": s["name"], "effect": s["effect"], "frames": [s["frame_start"], s["frame_end"]]}
                  for s in plan["shots"]],
        "localization": loc, "passes": plan.get("passes"), "messages": plan.get("messages", []),
        "query_paths": {"temporal": args.query_path, "spatial": getattr(args, "spatial", DEFAULT_SPATIAL)},
        "query_stats": dict(engine.stats) if engine is not None else {},
        "render": render_info, "timings_s": timer.timings, "cpu_timings_s": timer.cpu_timings,
        "total_seconds": round(time.perf_counter() - started, 3),
        "outputs": {k: str(v) for k, v in out.items() if v.exists() or k == "report"},
        "versions": versions(),
    }
    api.write_json_atomic(out["report"], report, overwrite=True)
    (out_dir / api.OUTPUTS_MARKER).unlink(missing_ok=True)  # finished: report.json guards it now
    return report


def plan_digest(plan: dict) -> str:
    """Short hash of a plan: rendered frames are reused only for the same plan.

    Floats are rounded to 5 decimals first: re-planning the same query gives the same plan up to
    the last bits of multi-threaded sums (action centre), which must not invalidate finished frames.
    """
    def canonical(value: Any) -> Any:
        if isinstance(value, float):
            return round(value, 5) + 0.0  # +0.0 turns -0.0 into 0.0
        if isinstance(value, dict):
            return {k: canonical(v) for k, v in value.items() if k != "messages"}
        if isinstance(value, (list, tuple)):
            return [canonical(v) for v in value]
        return value

    return hashlib.sha256(json.dumps(canonical(plan), sort_keys=True).encode()).hexdigest()[:12]


def preset_needs_relevancy(preset: Any) -> bool:
    return any(s.effect == "desaturate_background" for s in preset.shots)


def versions() -> dict[str, str]:
    import platform

    import numpy
    import torch

    out = {"python": platform.python_version(), "numpy": numpy.__version__, "torch": torch.__version__}
    try:
        import bpy

        out["blender"] = bpy.app.version_string
    except ImportError:
        pass
    return out


def main(argv: Optional[Sequence[str]] = None) -> int:
    from fourlegs_engine import api

    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        report = run(args)
    except api.FourlegsError as exc:
        api.print_error(str(exc))
        return 2
    except (OSError, MemoryError, RuntimeError) as exc:
        message = api.describe_environment_error(exc)
        if message is None:
            raise
        api.print_error(message)
        return 1
    except KeyboardInterrupt:
        print("fourlegs: cancelled; run the same command again to resume", file=sys.stderr)
        return 130
    print(f"[fourlegs] done in {report['total_seconds']:.1f} s: {report['outputs'].get('video')}", flush=True)
    return 0


def bpy_deadlocks_at_exit() -> bool:
    """Whether the loaded bpy is one whose C++ static destructors can deadlock at interpreter exit.

    bpy 4.5 (seen with 4.5.15 LTS): the main thread destroys a condition variable
    (``GlobalState::~GlobalState``) that bpy's own ``delayed_close_thread_run`` thread still waits on,
    so the process never ends although its work is done and every output is closed. bpy 5.0 exits
    normally.
    """
    bpy = sys.modules.get("bpy")
    return bpy is not None and tuple(bpy.app.version) < (5, 0, 0)


def exit_without_destructors(code: int) -> None:
    """Flush Python's streams and logging, then end the process with ``code`` through ``os._exit``."""
    import logging

    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def exit_process(code: int) -> None:
    """End the headless process with ``code``, stepping around bpy's exit deadlock where it exists."""
    if bpy_deadlocks_at_exit():
        exit_without_destructors(code)
    sys.exit(code)


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    exit_process(main())
