"""The main job's engine half: scene -> language field -> query -> plan, its outputs and its report.

A front end that renders the plan (the Blender add-on's headless job) runs::

    timer = StageTimer()
    job = prepare_highlight_job(options, timer)      # claims the outputs, writes plan.json + scores.png
    render = ...                                     # render job.plan to job.outputs["video"], save the .blend
    report = finish_highlight_job(job, render, timer)  # writes report.json: the job is finished

``options.output`` receives highlight.mp4 (or a frames directory), highlight.blend, plan.json,
report.json and scores.png. A finished job (report.json present) is never overwritten unless
``overwrite``; files an interrupted run of the job left there are its own and are resumed.

This module sits above the pipeline in the data flow (it drives it), so it lives beside the facade
rather than in :mod:`fourlegs_engine.highlights`, which the pipeline's planner step uses.
"""
from __future__ import annotations

import hashlib
import json
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, ContextManager, Optional

from . import pipeline
from .errors import InputError, OutputExistsError
from .fileio import OUTPUTS_MARKER, claim_outputs, write_json_atomic
from .options_json import options_from_dict, options_to_dict
from .query.options import QueryOptions
from .runlock import RunLock
from .validate import check_text

__all__ = ["DEFAULT_QUERY_PATH", "DEFAULT_SPATIAL", "DEMO_RESOLUTION", "HighlightJob", "HighlightJobOptions",
           "STAGE_FILE_ENV", "record_stage",
           "OUTPUT_NAMES", "StageTimer", "VIDEO_FORMATS", "check_job_size", "finish_highlight_job", "job_outputs",
           "plan_digest", "prepare_highlight_job", "preset_needs_relevancy", "software_versions"]

OUTPUT_NAMES = {"video": "highlight.mp4", "blend": "highlight.blend", "plan": "plan.json",
                "report": "report.json", "plot": "scores.png"}
#: output formats: an H.264 video, or a PNG / EXR image sequence in ``frames/``
VIDEO_FORMATS = ("MP4", "PNG", "EXR")

#: the main job's query paths are the query engine's defaults (the sketch path, fast maps);
#: docs/benchmarks.md has the figures
DEFAULT_QUERY_PATH: str = QueryOptions.path
DEFAULT_SPATIAL: str = QueryOptions.spatial
#: output size of the synthetic demo scene unless one is given (the presets' sizes are for real captures)
DEMO_RESOLUTION = (640, 360)


@dataclass(frozen=True)
class HighlightJobOptions:
    """What the main job makes.

    Attributes:
        query: the text to find, e.g. "a ball flying in the air".
        output: the output directory.
        scene: a bundle, params.npz directory, .ply file or directory of .ply files (None with ``demo``).
        demo: size of the synthetic demo scene to use instead ("tiny", "demo", "bench", "full"), or None.
        preset: a highlight preset name or .toml file.
        overwrite: replace a finished job's outputs (and foreign files of the same names).
        resolution: (width, height) of the output; None: :data:`DEMO_RESOLUTION` for the demo, else the preset's.
        fps: output frame rate; None: the preset's.
        format: one of :data:`VIDEO_FORMATS`.
        effects: only the preset's shots with these effects are kept (empty: all of them).
        no_effect: the preset's shots with these effects are left out.
        query_path / spatial: the query engine's temporal and spatial relevancy paths
            (:class:`~fourlegs_engine.query.options.QueryOptions` ``path`` / ``spatial``).
        encoder: the video-text encoder (used only when the scene needs a language field or relevancy).
        render_threads: torch threads while rendering frames (None: torch's setting).
    """

    query: str
    output: str | Path
    scene: Optional[str | Path] = None
    demo: Optional[str] = None
    preset: str = "broadcast"
    overwrite: bool = False
    resolution: Optional[tuple[int, int]] = None
    fps: Optional[float] = None
    format: str = "MP4"
    effects: tuple[str, ...] = ()
    no_effect: tuple[str, ...] = ()
    query_path: str = DEFAULT_QUERY_PATH
    spatial: str = DEFAULT_SPATIAL
    encoder: pipeline.EncoderOptions = field(default_factory=pipeline.EncoderOptions)
    render_threads: Optional[int] = 1

    def to_json(self) -> str:
        """Every field as JSON: how ``fourlegs highlight`` hands the job to its Blender child."""
        return json.dumps(options_to_dict(self), indent=1)

    @classmethod
    def from_json(cls, text: str, *, file: Optional[str | Path] = None) -> "HighlightJobOptions":
        """The options :meth:`to_json` wrote; InputError naming ``file`` and the field for malformed JSON,
        an unknown field or a value of the wrong type."""
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise InputError(f"not valid JSON ({exc})", file=file) from None
        return options_from_dict(cls, data, file=file)


class StageTimer:
    """Wall and CPU seconds per named stage: ``with timer("render"): ...``.

    CPU seconds are this process's (all threads): on a shared machine a steadier measure of a stage's
    work than its wall time. Each stage is announced on stdout when it starts and ends.
    """

    def __init__(self) -> None:
        self.started = time.perf_counter()
        self.timings: dict[str, float] = {}
        self.cpu_timings: dict[str, float] = {}

    def __call__(self, name: str) -> ContextManager[None]:
        return _Stage(self, name)

    def total_seconds(self) -> float:
        """Wall seconds since the timer was made."""
        return round(time.perf_counter() - self.started, 3)


class _Stage:
    def __init__(self, timer: StageTimer, name: str) -> None:
        self.timer, self.name = timer, name

    def __enter__(self) -> None:
        self.t0, self.c0 = time.perf_counter(), time.process_time()
        print(f"[fourlegs] {self.name} ...", flush=True)
        record_stage(self.name)

    def __exit__(self, *exc: Any) -> None:
        self.timer.timings[self.name] = round(time.perf_counter() - self.t0, 3)
        self.timer.cpu_timings[self.name] = round(time.process_time() - self.c0, 3)
        if exc[0] is None:
            print(f"[fourlegs] {self.name}: {self.timer.timings[self.name]:.1f} s", flush=True)


#: a file the job writes the name of its current stage into (set by ``fourlegs highlight`` for its child, which
#: reports a native crash of the child with the stage it was in)
STAGE_FILE_ENV = "FOURLEGS_STAGE_FILE"


def record_stage(name: str) -> None:
    """Write ``name`` into :data:`STAGE_FILE_ENV`'s file when it is set (a parent reads it after a crash)."""
    import os

    target = os.environ.get(STAGE_FILE_ENV)
    if target:
        try:
            Path(target).write_text(name, encoding="utf-8")
        except OSError:
            pass


@dataclass
class HighlightJob:
    """A planned job, ready to render: its options, output paths, scene, preset, query engine (None when
    the preset needs no localization) and plan (the dict written to plan.json)."""

    options: HighlightJobOptions
    outputs: dict[str, Path]
    scene: Any
    preset: Any
    engine: Any
    plan: dict[str, Any]
    #: the scene's run lock, held shared while the job reads the scene (:meth:`release` lets it go)
    scene_lock: Any = None

    def release(self) -> None:
        """Let go of the scene's run lock (the job reads the scene no more)."""
        if self.scene_lock is not None:
            self.scene_lock.release()
            self.scene_lock = None


def job_outputs(output_dir: str | Path, fmt: str = "MP4") -> dict[str, Path]:
    """The job's output paths by role (:data:`OUTPUT_NAMES`; an image sequence goes to ``frames/``)."""
    if fmt not in VIDEO_FORMATS:
        raise InputError(f"unknown output format {fmt!r} (one of {', '.join(VIDEO_FORMATS)})", field="format")
    out_dir = Path(output_dir)
    out = {k: out_dir / v for k, v in OUTPUT_NAMES.items()}
    out["video"] = out_dir / ("highlight.mp4" if fmt == "MP4" else "frames")
    return out


def prepare_highlight_job(options: HighlightJobOptions,
                          stage: Callable[[str], ContextManager[Any]]) -> HighlightJob:
    """Everything before rendering: claim the outputs, open the scene (building its language field if it
    has none), localize the query, plan the preset, write plan.json and scores.png.

    ``stage`` times each step (a :class:`StageTimer`). OutputExistsError before any work if a finished
    job's outputs (or foreign files of the same names) are there and ``options.overwrite`` is false.
    """
    from .highlights import load_preset

    out = job_outputs(options.output, options.format)
    # report.json marks a finished job; without it, files here are an interrupted run's, resumed
    existing = [str(out[k]) for k in ("video", "blend", "report") if out[k].exists()]
    if existing and not options.overwrite:
        raise OutputExistsError(", ".join(existing))
    check_text(options.query, "query")
    record_outputs = claim_outputs(Path(options.output), [out[k] for k in ("plan", "plot")],
                                   overwrite=options.overwrite)
    resolution = options.resolution
    if resolution is None and options.demo is not None:
        resolution = DEMO_RESOLUTION

    if options.demo is not None and options.scene is not None:
        raise InputError("give either --demo or a scene path, not both", field="scene")
    if options.demo is None and options.scene is None:
        raise InputError("no scene given (a path, or --demo)", field="scene")
    preset = load_preset(options.preset).select_effects(options.effects, options.no_effect)
    with stage("scene"):
        scene = pipeline.open_scene(options.scene, demo=options.demo)
    scene_lock = RunLock(scene.root, shared=True).acquire()  # no one writes the scene while the job reads it
    try:
        return _plan_job(options, out, scene, preset, resolution, stage, record_outputs, scene_lock)
    except BaseException:
        scene_lock.release()
        raise


def _plan_job(options: HighlightJobOptions, out: dict[str, Path], scene: Any, preset: Any, resolution: Any,
              stage: Callable[[str], ContextManager[Any]], record_outputs: Callable[[], None],
              scene_lock: Any) -> HighlightJob:
    """The rest of :func:`prepare_highlight_job` once the scene is open and read-locked."""
    from .highlights import plan_highlight, plan_needs
    from .query.plots import write_scores_plot

    engine = None
    if plan_needs(preset) or preset_needs_relevancy(preset):
        encoder = pipeline.text_encoder(scene, options.encoder)
        scene = pipeline.ensure_language_field(scene, encoder, progress=True, stage=stage)
        with stage("open query engine"):
            engine = pipeline.open_query_engine(
                scene, encoder, options=pipeline.QueryOptions(path=options.query_path, spatial=options.spatial))
    with stage("localize + plan"):
        plan = plan_highlight(scene, engine, options.query, preset, resolution=resolution,
                              fps=options.fps).to_dict()
    check_job_size(plan, out["video"], options.format)
    record_outputs()
    write_json_atomic(out["plan"], plan, overwrite=True)
    loc = plan.get("localization") or {}
    if loc.get("scores"):
        write_scores_plot(out["plot"], loc["scores"], loc.get("positive") or
                          [s > 1.0 / len(loc["scores"]) for s in loc["scores"]],
                          loc.get("segment"), loc.get("peak"), options.query)
    for msg in plan.get("messages", []):
        print(f"[fourlegs] note: {msg}", flush=True)
    return HighlightJob(options, out, scene, preset, engine, plan, scene_lock)


#: bytes per pixel: of a frame while it renders (rasterizer buffers, relevancy, compositor passes), and of a
#: finished frame on disk (MP4: uncompressed PNG frames until they are encoded; PNG; EXR: half floats)
RENDER_BYTES_PER_PIXEL = 64
DISK_BYTES_PER_PIXEL = {"MP4": 3.0, "PNG": 2.0, "EXR": 6.0}


def check_job_size(plan: dict[str, Any], video: Path, fmt: str) -> None:
    """InputError with the estimate when one frame would not fit in memory or the frames not on the disk
    of ``video``'s folder (checked before the renderer starts, instead of a crash hours later)."""
    import shutil

    from .validate import check_memory, format_bytes

    width, height = (int(v) for v in plan["resolution"])
    frames = int(plan["frame_end"]) - int(plan["frame_start"]) + 1
    check_memory(RENDER_BYTES_PER_PIXEL * width * height, f"rendering one {width}x{height} frame", "resolution")
    needed = DISK_BYTES_PER_PIXEL.get(fmt, 3.0) * width * height * frames
    probe = Path(video).parent
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    try:
        free = shutil.disk_usage(probe).free
    except OSError:
        return
    if needed > free:
        raise InputError(f"{frames} frames of {width}x{height} need about {format_bytes(needed)} of disk, "
                         f"{probe} has {format_bytes(free)} free; lower the resolution, frame rate or durations",
                         field="resolution")


def finish_highlight_job(job: HighlightJob, render: dict[str, Any], timer: StageTimer, *,
                         versions: Optional[dict[str, str]] = None) -> dict[str, Any]:
    """Write report.json (the job is finished: report.json now guards its outputs) and return it.

    ``render``: the renderer's statistics (frames, seconds, threads); ``versions``: software versions
    the renderer adds to :func:`software_versions` (e.g. Blender's).
    """
    plan, options, scene, out = job.plan, job.options, job.scene, job.outputs
    report = {
        "format": "fourlegs-highlight-report", "version": 1,
        "query": options.query, "scene": {"name": scene.name, "path": str(scene.root),
                                          "num_timesteps": scene.num_timesteps,
                                          "num_gaussians": scene.num_gaussians},
        "preset": job.preset.name, "resolution": plan["resolution"], "fps": plan["fps"],
        "frames": [plan["frame_start"], plan["frame_end"]],
        "shots": [{"name": s["name"], "effect": s["effect"], "frames": [s["frame_start"], s["frame_end"]]}
                  for s in plan["shots"]],
        "localization": plan.get("localization") or {}, "passes": plan.get("passes"),
        "messages": plan.get("messages", []),
        "query_paths": {"temporal": options.query_path, "spatial": options.spatial},
        "query_stats": dict(job.engine.stats) if job.engine is not None else {},
        "render": render, "timings_s": timer.timings, "cpu_timings_s": timer.cpu_timings,
        "total_seconds": timer.total_seconds(),
        "outputs": {k: str(v) for k, v in out.items() if v.exists() or k == "report"},
        "versions": {**software_versions(), **(versions or {})},
    }
    write_json_atomic(out["report"], report, overwrite=True)
    (Path(options.output) / OUTPUTS_MARKER).unlink(missing_ok=True)
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
    """Whether a shot of ``preset`` renders per-Gaussian relevancy (so the job needs the query engine)."""
    from .highlights.effects import MASKED_EFFECTS

    return any(s.effect in MASKED_EFFECTS for s in preset.shots)


def software_versions() -> dict[str, str]:
    """Versions of Python, numpy and torch (for the report)."""
    import numpy
    import torch

    return {"python": platform.python_version(), "numpy": numpy.__version__, "torch": torch.__version__}
