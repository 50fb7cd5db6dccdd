"""The main job, headless through the bpy module: scene -> language field -> query -> plan -> video.

    python -m fourlegs_addon.headless --demo "a ball flying in the air" --preset broadcast -o out/

(``fourlegs highlight ...`` runs this in a subprocess, so the engine's process never imports bpy, and
hands it the job's options as data: ``--options-json FILE``, :meth:`HighlightJobOptions.to_json`.) The engine's half of the job (stages 1-3, the outputs, report.json) is
:mod:`fourlegs_engine.highlight_job` behind the facade; this module is the Blender half. Stages:

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
import shutil
import sys
import time
from pathlib import Path
from typing import Any, Optional, Sequence

try:  # Ctrl-C while the engine is imported: a quiet cancel (exit 130), not a traceback
    from fourlegs_engine import api
    from fourlegs_engine.commands.options import add_highlight_arguments, highlight_job_options

    from .process import blender_log_silenced, heap_kept
except KeyboardInterrupt:
    sys.exit(130)


def build_parser() -> argparse.ArgumentParser:
    """The job's command line (the same options as ``fourlegs highlight``, or ``--options-json FILE``)."""
    parser = argparse.ArgumentParser(prog="python -m fourlegs_addon.headless", description=__doc__.splitlines()[0])
    parser.add_argument("--options-json", metavar="FILE",
                        help="the job's options as JSON (what `fourlegs highlight` writes), instead of the "
                             "arguments below")
    add_highlight_arguments(parser)
    return parser


def job_options(argv: Optional[Sequence[str]] = None) -> api.HighlightJobOptions:
    """The job's options: read from ``--options-json FILE``, or built from ``fourlegs highlight``'s arguments."""
    argv = list(sys.argv[1:] if argv is None else argv)
    first = argparse.ArgumentParser(add_help=False)
    first.add_argument("--options-json", default=None)
    known, rest = first.parse_known_args(argv)
    if known.options_json is None:
        return highlight_job_options(build_parser().parse_args(argv))
    if rest:
        raise api.InputError(f"replaces every other argument, got also {' '.join(rest)}", field="--options-json")
    path = Path(known.options_json)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise api.InputError(f"cannot read the job's options ({exc})", file=path, field="--options-json") from None
    return api.HighlightJobOptions.from_json(text, file=path)


def blender_stage(scene: Any, plan: dict, engine: Any, query: str, out: dict[str, Path], fmt: str,
                  timer: api.StageTimer, render_threads: Optional[int] = 1) -> dict[str, Any]:
    """Import, Generate Highlight, render through the splat engine + compositor, save the .blend.

    ``render_threads``: torch threads while rendering frames (None keeps torch's default: the per-frame
    rasterization is thousands of small tensor ops, and on a busy machine extra OpenMP threads mostly
    wait at barriers). The fused blending kernel gets a worker per usable core: they block when idle,
    so they help on a quiet machine and cost nothing on a busy one.
    """
    import bpy
    from tqdm import tqdm

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
                api.torch_threads(render_threads), api.kernel_threads(api.usable_cpu_count()), heap_kept():
            progress = lambda done, n: bar.update(done - bar.n)  # noqa: E731
            if fmt == "EXR":
                video.render_animation(bl_scene, out["video"], fmt=fmt, overwrite=True, on_frame=progress)
            else:  # frame by frame into a resumable directory (an interrupted run continues from there)
                frames_dir = out["video"] if fmt == "PNG" else out["video"].parent / f".frames-{api.plan_digest(plan)}"
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
            "render_threads": render_threads, "render_kernel_threads": api.usable_cpu_count()}


def run(options: api.HighlightJobOptions) -> dict[str, Any]:
    """The whole job: the engine plans it, Blender renders it, the engine reports it. Returns the report."""
    timer = api.StageTimer()
    with api.run_lock(options.output):  # one job per output folder; an earlier killed run's temporaries go
        import bpy

        job = api.prepare_highlight_job(options, timer)  # holds the scene's lock shared until released
        try:
            render_info = blender_stage(job.scene, job.plan, job.engine, options.query, job.outputs, options.format,
                                        timer, render_threads=options.render_threads)
        finally:
            job.release()
        return api.finish_highlight_job(job, render_info, timer, versions={"blender": bpy.app.version_string})


def main(argv: Optional[Sequence[str]] = None) -> int:
    api.die_with_parent()  # started by `fourlegs highlight`: end with it

    def job() -> int:
        report = run(job_options(argv))
        print(f"[fourlegs] done in {report['total_seconds']:.1f} s: {report['outputs'].get('video')}", flush=True)
        return 0

    return api.exit_code_of(job)


if __name__ == "__main__":
    sys.exit(main())
