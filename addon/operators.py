"""Operators of the 4-LEGS panel: import, run query (non-blocking), generate highlight, render video.

Run Query works in a background thread (the engine is pure Python + torch, no bpy) while a modal
operator polls it on a timer, shows progress in the panel and the status bar, and stops on Esc or
the Cancel button. Blender data is only touched on the main thread, when the result is collected.
Errors are reported in one line (``self.report``); Generate Highlight and Import support undo.
"""
from __future__ import annotations

import json
import threading
import traceback
from pathlib import Path
from typing import Any, Optional

import bpy
import numpy as np
from bpy.props import BoolProperty, StringProperty
from bpy_extras.io_utils import ImportHelper

from . import (compositor, importer, keyframes, planning, plots, prepare, querying, render_engine, torch_install,
               video)

ALL_NEEDS = {"temporal", "best_view", "action_centre"}


def _err(exc: BaseException) -> str:
    """One line for the user (no traceback)."""
    if isinstance(exc, ModuleNotFoundError) and exc.name in torch_install.REQUIREMENTS:
        return (f"{torch_install.missing_message([exc.name])}; install it in Edit > Preferences > Add-ons > "
                "4-LEGS Highlights")
    return str(exc) if isinstance(exc, (ValueError, FileExistsError, RuntimeError)) else f"{type(exc).__name__}: {exc}"


def interactive() -> bool:
    """Whether Blender runs with a UI (operators must not block it); False for ``blender -b`` and bpy."""
    return not bpy.app.background


def _splat_object(context) -> Optional[bpy.types.Object]:
    obj = context.scene.fourlegs.splat_object
    return obj if obj is not None and importer.source_key(obj) else None


# ----------------------------------------------------------------------------- import
class FOURLEGS_OT_import_scene(bpy.types.Operator, ImportHelper):
    """Import a 4D Gaussian scene (bundle directory, params.npz directory, PLY file or PLY directory)"""

    bl_idname = "fourlegs.import_scene"
    bl_label = "Import 4D Scene"
    bl_options = {"REGISTER", "UNDO"}

    filter_glob: StringProperty(default="*.json;*.npz;*.ply", options={"HIDDEN"})
    with_cameras: BoolProperty(name="Cameras", default=True, description="Also import the scene's cameras")

    def execute(self, context):
        path = Path(bpy.path.abspath(self.filepath))
        if path.is_file() and path.name in ("scene.json", "params.npz"):
            path = path.parent  # a bundle / params.npz directory was picked through one of its files
        try:
            scene = importer.load_engine_scene(path)
            importer.import_scene(context.scene, scene, source=str(path), with_cameras=self.with_cameras)
        except Exception as exc:
            self.report({"ERROR"}, f"4-LEGS import: {_err(exc)}")
            return {"CANCELLED"}
        self.report({"INFO"}, f"imported {scene.name}: {scene.num_gaussians} Gaussians x {scene.num_timesteps} timesteps")
        return {"FINISHED"}


# ----------------------------------------------------------------------------- query
class _QueryJob:
    """State shared between the worker thread and the modal operator."""

    def __init__(self, scene: Any, query: str, encoder: Any = None):
        self.scene, self.query, self.encoder = scene, query, encoder
        self.progress, self.stage = 0.0, "starting"
        self.cancelled = False
        self.done = False
        self.error: Optional[str] = None
        self.engine = self.localization = None
        self.peak_relevancy: Optional[np.ndarray] = None

    def on_progress(self, fraction: float, stage: str) -> None:
        """The engine's progress callback during localization: 20-90% of the bar; raises
        :class:`Cancelled` once the user cancelled, which stops the engine between timesteps."""
        if self.cancelled:
            raise _cancelled_error()("the query was cancelled")
        self.progress = 0.2 + 0.7 * fraction
        if stage:
            self.stage = f"localizing: {stage}"

    def on_open_progress(self, fraction: float, stage: str) -> None:
        """The engine's progress callback while it opens (text encoder, field, reference phrases, codebook):
        0-20% of the bar; raises :class:`Cancelled` once the user cancelled, between those steps."""
        if self.cancelled:
            raise _cancelled_error()("the query was cancelled")
        self.progress = 0.2 * fraction
        self.stage = f"opening the query engine: {stage}"

    def run(self) -> None:
        try:
            self.stage, self.progress = "opening the query engine", 0.0
            self.engine = querying.open_query_engine(self.scene, encoder=self.encoder, progress=self.on_open_progress)
            if self.cancelled:
                return
            self.stage, self.progress = "localizing in time and space", 0.2
            self.localization = self.engine.localize(self.query, set(ALL_NEEDS), progress=self.on_progress)
            temporal = self.localization.temporal
            t = temporal.peak if temporal is not None and temporal.found else 0
            self.stage, self.progress = "relevancy of the Gaussians", 0.9
            self.peak_relevancy = np.asarray(self.engine.gaussian_relevancy(self.query, int(t)), np.float32)
            self.progress, self.stage = 1.0, "done"
        except Exception as exc:  # reported on the main thread
            if self.cancelled:
                return
            self.error = _err(exc)
            traceback.print_exc()
        finally:
            self.done = True


def _cancelled_error():
    from fourlegs_engine import api

    return api.Cancelled


_JOBS: list[_QueryJob] = []
_LOCALIZERS: dict[str, planning.CachedLocalizer] = {}


def cancel_all() -> None:
    for job in _JOBS:
        job.cancelled = True


class _JobModal:
    """Timer-driven modal part shared by the operators running a :class:`_QueryJob` in a worker thread."""

    _timer = None
    _job: Optional[_QueryJob] = None

    def modal(self, context, event):
        props = context.scene.fourlegs
        job = self._job
        if event.type == "ESC" or job.cancelled:
            job.cancelled = True
            self._stop(context)
            props.running, props.status = False, "cancelled"
            self.report({"WARNING"}, "4-LEGS query cancelled")
            return {"CANCELLED"}
        if event.type == "TIMER":
            props.progress, props.status = job.progress, job.stage
            for area in context.screen.areas if context.screen else []:
                if area.type == "VIEW_3D":
                    area.tag_redraw()
            if job.done:
                self._stop(context)
                return self._finish(context)
        return {"PASS_THROUGH"}

    def _start(self, context, job, thread_name: str, status: str):
        """Run ``job`` in a worker thread: modal with a timer in the UI, waited for in background mode."""
        self._job = job
        _JOBS.append(job)
        threading.Thread(target=job.run, name=thread_name, daemon=True).start()
        props = context.scene.fourlegs
        props.running, props.progress, props.status = True, 0.0, status
        wm = context.window_manager
        if context.window is not None and not bpy.app.background:
            self._timer = wm.event_timer_add(0.2, window=context.window)
            wm.modal_handler_add(self)
            return {"RUNNING_MODAL"}
        while not job.done:  # background mode has no event loop
            threading.Event().wait(0.05)
        self._stop(context)
        if job.cancelled:
            props.running, props.status = False, "cancelled"
            self.report({"WARNING"}, "4-LEGS query cancelled")
            return {"CANCELLED"}
        return self._finish(context)

    def _failed(self, context, label: str) -> bool:
        """Mark the job over; if it raised, show its error (status line and report) and say so."""
        props = context.scene.fourlegs
        props.running = False
        if self._job.error is None:
            return False
        props.status = f"error: {self._job.error}"
        self.report({"ERROR"}, f"4-LEGS {label}: {self._job.error}")
        return True

    def _stop(self, context) -> None:
        if self._timer is not None:
            context.window_manager.event_timer_remove(self._timer)
            self._timer = None
        if self._job in _JOBS:
            _JOBS.remove(self._job)


class FOURLEGS_OT_run_query(_JobModal, bpy.types.Operator):
    """Find when and where the query happens (runs in the background; Esc cancels)"""

    bl_idname = "fourlegs.run_query"
    bl_label = "Run Query"
    bl_options = {"REGISTER"}

    @classmethod
    def poll(cls, context):
        props = context.scene.fourlegs
        return _splat_object(context) is not None and bool(props.query.strip()) and not props.running

    def execute(self, context):
        return self.invoke(context, None)

    def invoke(self, context, event):
        props = context.scene.fourlegs
        obj = _splat_object(context)
        try:
            scene = importer.engine_scene_for(obj)
        except Exception as exc:
            self.report({"ERROR"}, f"4-LEGS query: {_err(exc)}")
            return {"CANCELLED"}
        return self._start(context, _QueryJob(scene, props.query.strip(), querying.encoder_config(props)),
                           "fourlegs-query", "starting")

    def _finish(self, context):
        props = context.scene.fourlegs
        job = self._job
        if self._failed(context, "query"):
            return {"CANCELLED"}
        obj = _splat_object(context)
        store_results(context.scene, obj, job.engine, job.query, job.localization, job.peak_relevancy)
        props.progress, props.status = 1.0, "done" if props.found else "not found"
        self.report({"INFO"} if props.found else {"WARNING"},
                    f"4-LEGS: {job.query!r} " + (f"found at timesteps {props.segment_start}-{props.segment_end}"
                                                 if props.found else "was not found"))
        return {"FINISHED"}


def fill_segments(props, segments, scores, chosen) -> None:
    """List every segment (start, end, peak s_t) in the panel; the chosen one is selected."""
    scores = np.nan_to_num(np.asarray(scores, np.float64))
    props.segments.clear()
    index = -1
    for i, (a, b) in enumerate(segments):
        item = props.segments.add()
        item.start, item.end = int(a), int(b)
        item.peak_score = float(scores[int(a):int(b) + 1].max()) if len(scores) > int(b) else 0.0
        if chosen is not None and (int(a), int(b)) == (int(chosen[0]), int(chosen[1])):
            index = i
    props["segment_index"] = index  # no update callback: the chosen segment is already shown


def fill_from_plan(bl_scene, plan: dict[str, Any], output: Optional[str] = None, fmt: Optional[str] = None) -> None:
    """The panel of a scene made from a plan (the headless job's .blend): query, found, segments, peak,
    best view, the s_t plot, and the output the video was written to."""
    props = bl_scene.fourlegs
    loc = plan.get("localization") or {}
    props.query = str(plan.get("query") or "")
    props.found = bool(loc.get("found"))
    seg = loc.get("segment") if props.found else None
    props.segment_start, props.segment_end = (int(seg[0]), int(seg[1])) if seg else (-1, -1)
    props.peak = int(loc["peak"]) if props.found and loc.get("peak") is not None else -1
    props.best_view = str(loc.get("best_view") or "")
    scores = loc.get("scores") or []
    fill_segments(props, loc.get("segments") or ([seg] if seg else []), scores, seg)
    if scores:
        positive = np.zeros(len(scores), bool)
        for a, b in loc.get("segments") or []:
            positive[int(a):int(b) + 1] = True
        plots.scores_image(np.asarray(scores, np.float64), positive, seg, props.peak if props.found else None)
    if output is not None:
        props.output_path = str(output)
        bl_scene.render.filepath = str(output)
    if fmt is not None:
        props.output_format = fmt
        video.configure_output(bl_scene, fmt)


def store_results(bl_scene, obj, engine: Any, query: str, localization: Any,
                  peak_relevancy: Optional[np.ndarray]) -> None:
    """Copy a localization into the scene properties, the s_t image and the viewport relevancy colours."""
    props = bl_scene.fourlegs
    temporal = localization.temporal
    props.found = bool(temporal is not None and temporal.found)
    seg = temporal.segment if props.found else None
    props.segment_start, props.segment_end = (int(seg[0]), int(seg[1])) if seg else (-1, -1)
    props.peak = int(temporal.peak) if props.found and temporal.peak is not None else -1
    props.best_view = localization.best_view or ""
    fill_segments(props, temporal.segments if temporal is not None else [],
                  temporal.scores if temporal is not None else [], seg)
    if temporal is not None:
        plots.scores_image(np.asarray(temporal.scores, np.float64), np.asarray(temporal.positive, bool),
                           seg, props.peak if props.found else None)
    key = importer.source_key(obj)
    _LOCALIZERS[key] = planning.CachedLocalizer(engine, query, localization, ALL_NEEDS)
    importer.set_relevancy_provider(obj, lambda t, e=engine, q=query: e.gaussian_relevancy(q, t).numpy())
    if peak_relevancy is not None:
        importer.set_relevancy(obj, peak_relevancy, show=True)


# ----------------------------------------------------------------------------- multi-scene
RELEVANCE_KEY = "fourlegs_scene_relevance"


def imported_splat_objects() -> list[bpy.types.Object]:
    """Every 4-LEGS point-cloud object in the file (one per imported scene), in name order."""
    return sorted((o for o in bpy.data.objects if importer.source_key(o)), key=lambda o: o.name)


class _RankJob(_QueryJob):
    """Ranks several scenes by max_t s_t (the engine's multi-scene selection) in the worker thread."""

    def __init__(self, scenes: dict[str, Any], query: str, encoder: Any = None):
        super().__init__(None, query, encoder)
        self.scenes = scenes
        self.ranking = None

    def run(self) -> None:
        from fourlegs_engine import api

        try:
            def cancel_point(fraction: float, stage: str) -> None:
                if self.cancelled:
                    raise api.Cancelled("cancelled")

            def opener(scene):
                def open_engine():
                    cancel_point(0.0, "")  # also where the engine is already open
                    return querying.open_query_engine(scene, encoder=self.encoder, progress=cancel_point)
                return open_engine

            scored = [0]

            def on_scene(name, relevance):
                scored[0] += 1
                self.progress = 0.9 * scored[0] / len(self.scenes)
                self.stage = f"scored {scored[0]}/{len(self.scenes)} scenes"

            self.stage, self.progress = f"scoring {len(self.scenes)} scenes", 0.02
            self.ranking = api.rank_scenes_opening({n: opener(s) for n, s in self.scenes.items()}, self.query,
                                                   on_scene=on_scene)
            self.progress, self.stage = 1.0, "done"
        except Exception as exc:
            if not self.cancelled:
                self.error = _err(exc)
                traceback.print_exc()
        finally:
            self.done = True


class FOURLEGS_OT_find_best_scene(_JobModal, bpy.types.Operator):
    """Rank the imported 4-LEGS scenes by how strongly the query happens in them (max over time of s_t, on
    every 10th timestep) and make the best one the panel's scene (runs in the background; Esc cancels)"""

    bl_idname = "fourlegs.find_best_scene"
    bl_label = "Find Best Scene"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        return self.invoke(context, None)

    @classmethod
    def poll(cls, context):
        props = context.scene.fourlegs
        return len(imported_splat_objects()) > 1 and bool(props.query.strip()) and not props.running

    def invoke(self, context, event):
        props = context.scene.fourlegs
        try:
            scenes = {obj.name: importer.engine_scene_for(obj) for obj in imported_splat_objects()}
        except Exception as exc:
            self.report({"ERROR"}, f"4-LEGS Find Best Scene: {_err(exc)}")
            return {"CANCELLED"}
        return self._start(context, _RankJob(scenes, props.query.strip(), querying.encoder_config(props)),
                           "fourlegs-rank", "ranking scenes")

    def _finish(self, context):
        props = context.scene.fourlegs
        job = self._job
        if self._failed(context, "Find Best Scene"):
            return {"CANCELLED"}
        ranking = job.ranking
        for name, relevance in ranking.ranking:
            bpy.data.objects[name][RELEVANCE_KEY] = float(relevance)
        table = ", ".join(f"{n} {r:.3f}" for n, r in ranking.ranking)
        if ranking.best is None:
            props.status = "not found in any scene"
            self.report({"WARNING"}, f"4-LEGS: {job.query!r} was not found in any scene ({table})")
            return {"FINISHED"}
        best = bpy.data.objects[ranking.best]
        props.splat_object = best
        props.num_timesteps = int(job.scenes[ranking.best].num_timesteps)
        for obj in context.view_layer.objects:
            obj.select_set(obj == best)
        context.view_layer.objects.active = best
        props.progress, props.status = 1.0, f"best scene: {best.name}"
        self.report({"INFO"}, f"4-LEGS: {job.query!r} best in {best.name} (max_t s_t: {table})")
        return {"FINISHED"}


class FOURLEGS_OT_cancel_query(bpy.types.Operator):
    """Stop the running query"""

    bl_idname = "fourlegs.cancel_query"
    bl_label = "Cancel"

    def execute(self, context):
        cancel_all()
        prepare.cancel_all()
        _RENDERS.clear()  # each running Render Video stops at its next timer tick
        context.scene.fourlegs.running = False
        return {"FINISHED"}


class FOURLEGS_OT_show_relevancy(bpy.types.Operator):
    """Colour the point cloud by the query's relevancy, or by its own colours"""

    bl_idname = "fourlegs.show_relevancy"
    bl_label = "Show Relevancy"
    bl_options = {"REGISTER", "UNDO"}

    show: BoolProperty(default=True)

    @classmethod
    def poll(cls, context):
        return _splat_object(context) is not None

    def execute(self, context):
        importer.show_relevancy(_splat_object(context), self.show)
        return {"FINISHED"}


# ----------------------------------------------------------------------------- highlight
def disabled_effects(props) -> list[str]:
    off = []
    if not props.use_zoom_in:
        off.append("zoom_in")
    if not props.use_bullet_time:
        off.append("bullet_time")
    if not props.use_desaturate:
        off.append("desaturate_background")
    return off


def generate_highlight(bl_scene, plan: dict[str, Any]) -> bpy.types.Object:
    """Turn a plan dict into Blender data (camera keys, scene-time keys, timeline, passes, compositor)."""
    cam = keyframes.apply_plan(bl_scene, plan)
    text = bpy.data.texts.get(render_engine.PLAN_TEXT_NAME) or bpy.data.texts.new(render_engine.PLAN_TEXT_NAME)
    text.clear()
    text.write(json.dumps(plan, indent=1))
    text[keyframes.GENERATED_KEY] = True
    bl_scene.render.engine = render_engine.ENGINE_ID
    importer.use_standard_view(bl_scene)
    rel = bool((plan.get("passes") or {}).get("relevancy"))
    for view_layer in bl_scene.view_layers:
        view_layer.use_pass_z = bool((plan.get("passes") or {}).get("depth"))
        view_layer.fourlegs_relevancy = rel
    compositor.build_compositor(bl_scene, plan)
    return cam


class FOURLEGS_OT_generate_highlight(bpy.types.Operator):
    """Plan the highlight shots for the query and create the camera animation, scene-time keys and compositor setup"""

    bl_idname = "fourlegs.generate_highlight"
    bl_label = "Generate Highlight"
    bl_options = {"REGISTER", "UNDO"}

    plan_file: StringProperty(name="Plan", subtype="FILE_PATH", default="",
                              description="Use this plan JSON instead of planning from the query")

    @classmethod
    def poll(cls, context):
        return _splat_object(context) is not None and not context.scene.fourlegs.running

    def invoke(self, context, event):
        if keyframes.has_generated(context.scene):  # edits to the generated camera/keys would be lost
            return context.window_manager.invoke_confirm(
                self, event, title="Replace the highlight?",
                message="Generate again replaces the highlight camera, its keys, the shot markers and the "
                        "compositor setup, with any edits made to them.", confirm_text="Replace")
        return self.execute(context)

    def execute(self, context):
        props = context.scene.fourlegs
        try:
            if self.plan_file:
                plan = json.loads(Path(bpy.path.abspath(self.plan_file)).read_text(encoding="utf-8"))
            else:
                obj = _splat_object(context)
                scene = importer.engine_scene_for(obj)
                localizer = _LOCALIZERS.get(importer.source_key(obj))
                query = props.query.strip()
                if (localizer is None or localizer.query != query) and interactive():
                    # localizing takes tens of seconds: run it in the background instead of freezing the UI
                    if query and bpy.ops.fourlegs.run_query.poll():
                        bpy.ops.fourlegs.run_query("INVOKE_DEFAULT")
                        self.report({"INFO"}, "4-LEGS: running the query first (in the background); press "
                                              "Generate Highlight again when it is done")
                    else:
                        self.report({"WARNING"}, "4-LEGS: type a query and Run Query first")
                    return {"CANCELLED"}
                if localizer is None or localizer.query != query:
                    localizer = planning.CachedLocalizer(
                        querying.open_query_engine(scene, encoder=querying.encoder_config(props)), query)
                plan = planning.make_plan(scene, localizer, query, props.preset,
                                          disabled_effects=disabled_effects(props))
            generate_highlight(context.scene, plan)
        except Exception as exc:
            self.report({"ERROR"}, f"4-LEGS Generate Highlight: {_err(exc)}")
            return {"CANCELLED"}
        for msg in plan.get("messages", []):
            self.report({"WARNING"}, str(msg))
        self.report({"INFO"}, f"highlight: {len(plan['shots'])} shots, frames {plan['frame_start']}-{plan['frame_end']}")
        return {"FINISHED"}


_RENDERS: list[video.RenderJob] = []


class FOURLEGS_OT_render_video(bpy.types.Operator):
    """Render the timeline through the 4-LEGS Splats engine and the compositor to a video or image sequence
    (one frame per timer tick, the MP4 encoded in a background process, so the UI stays responsive; Esc
    or Cancel stops it)"""

    bl_idname = "fourlegs.render_video"
    bl_label = "Render Video"
    bl_options = {"REGISTER"}

    _timer = None
    _job: Optional[video.RenderJob] = None
    _cancel = False

    @classmethod
    def poll(cls, context):
        return not context.scene.fourlegs.running

    def execute(self, context):
        return self.invoke(context, None)

    def invoke(self, context, event):
        props = context.scene.fourlegs
        if render_engine.plan_of(context.scene) is None:
            self.report({"ERROR"}, "4-LEGS Render Video: no highlight in this scene; run Generate Highlight first")
            return {"CANCELLED"}
        try:
            self._job = video.RenderJob(context.scene, props.output_path, fmt=props.output_format,
                                        overwrite=props.overwrite)
        except Exception as exc:
            self.report({"ERROR"}, f"4-LEGS Render Video: {_err(exc)}")
            return {"CANCELLED"}
        _RENDERS.append(self._job)
        props.running, props.progress, props.status = True, 0.0, f"rendering frame 1/{self._job.total}"
        if context.window is not None and interactive():
            wm = context.window_manager
            wm.progress_begin(0, self._job.total)
            self._timer = wm.event_timer_add(0.01, window=context.window)
            wm.modal_handler_add(self)
            return {"RUNNING_MODAL"}
        # background mode has no event loop: render every frame here
        while self._advance(context):
            if self._job.encoding:
                threading.Event().wait(0.05)
        return self._end(context)

    def _advance(self, context) -> bool:
        """Render one frame; False when the job is over (done, failed or cancelled)."""
        props = context.scene.fourlegs
        job = self._job
        if job not in _RENDERS:  # the Cancel button
            self._cancel = True
            return False
        try:
            more = job.step()
        except BaseException as exc:
            self._error = "cancelled" if isinstance(exc, KeyboardInterrupt) else _err(exc)
            return False
        if job.encoder is None:
            props.progress = job.done / job.total
            props.status = f"rendering frame {min(job.done + 1, job.total)}/{job.total}" if more else "writing"
        else:  # the MP4 encodes in a child process: the last tenth of the bar
            props.progress = 0.9 + 0.1 * job.encoder.encoded / job.total
            props.status = f"encoding the MP4: frame {job.encoder.encoded}/{job.total}"
        if self._timer is not None:
            context.window_manager.progress_update(job.done)
        return more

    def modal(self, context, event):
        if event.type == "ESC":
            self._cancel = True
            return self._end(context)
        if event.type == "TIMER":
            if not self._advance(context):
                return self._end(context)
            for area in context.screen.areas if context.screen else []:
                if area.type in ("VIEW_3D", "PROPERTIES"):
                    area.tag_redraw()
        return {"PASS_THROUGH"}

    _error: Optional[str] = None

    def _end(self, context):
        props = context.scene.fourlegs
        job = self._job
        if self._timer is not None:
            context.window_manager.event_timer_remove(self._timer)
            context.window_manager.progress_end()
            self._timer = None
        if job in _RENDERS:
            _RENDERS.remove(job)
        props.running = False
        if self._cancel or self._error == "cancelled":
            job.cancel()
            props.status = "render cancelled"
            self.report({"WARNING"}, f"4-LEGS Render Video cancelled after {job.done} of {job.total} frames")
            return {"CANCELLED"}
        if self._error is not None:
            props.status = f"error: {self._error}"
            self.report({"ERROR"}, f"4-LEGS Render Video: {self._error}")
            return {"CANCELLED"}
        try:
            out = job.finish()
        except Exception as exc:
            props.status = f"error: {_err(exc)}"
            self.report({"ERROR"}, f"4-LEGS Render Video: {_err(exc)}")
            return {"CANCELLED"}
        props.progress, props.status = 1.0, "video written"
        self.report({"INFO"}, f"wrote {out}")
        return {"FINISHED"}


classes = (FOURLEGS_OT_import_scene, FOURLEGS_OT_run_query, FOURLEGS_OT_find_best_scene, FOURLEGS_OT_cancel_query,
           FOURLEGS_OT_show_relevancy,
           FOURLEGS_OT_generate_highlight, FOURLEGS_OT_render_video)
