"""Run Query and Find Best Scene (background jobs), the results in the panel, Show Relevancy.

Run Query localizes everything the planner may ask for once, in a worker thread; the result is kept
per imported scene (:func:`localizer_for`) so Generate Highlight plans without localizing again.
"""
from __future__ import annotations

import json
from typing import Any, Optional

import bpy
import numpy as np
from bpy.props import BoolProperty

from . import importer, jobs, planning, plots, querying
from .messages import error_line, missing_for

ALL_NEEDS = {"temporal", "best_view", "action_centre"}
RELEVANCE_KEY = "fourlegs_scene_relevance"

#: source key of an imported scene -> the localization Run Query made there
_LOCALIZERS: dict[str, planning.CachedLocalizer] = {}


def splat_object(context) -> Optional[bpy.types.Object]:
    """The panel's imported scene object (None when there is none)."""
    obj = context.scene.fourlegs.splat_object
    return obj if obj is not None and importer.source_key(obj) else None


LOCALIZATION_KEY = "fourlegs_localization"  # object property: Run Query's localization (JSON), kept in the .blend


def localizer_for(obj: bpy.types.Object, props: Any = None) -> Optional[planning.CachedLocalizer]:
    """The localization Run Query made for ``obj``: this session's, else the one saved in the .blend (its
    query engine opened only if the planner needs more than it holds)."""
    key = importer.source_key(obj) or ""
    if key in _LOCALIZERS:
        return _LOCALIZERS[key]
    stored = obj.get(LOCALIZATION_KEY) if obj is not None else None
    if not stored:
        return None
    try:
        data = json.loads(stored)
        localization = planning.localization_from_dict(data["localization"])
    except (ValueError, KeyError, TypeError):
        return None
    encoder = querying.encoder_config(props) if props is not None else None

    def open_engine():
        return querying.open_query_engine(importer.engine_scene_for(obj), encoder=encoder)

    _LOCALIZERS[key] = planning.CachedLocalizer(open_engine, data["query"], localization, data.get("need", ALL_NEEDS))
    return _LOCALIZERS[key]


def _cancelled_error():
    from fourlegs_engine import api

    return api.Cancelled


class QueryJob(jobs.Job):
    """Localize ``query`` in ``scene`` (temporal, best view, action centre) and the peak's relevancy."""

    def __init__(self, scene: Any, query: str, encoder: Any = None):
        super().__init__()
        self.scene, self.query, self.encoder = scene, query, encoder
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
        """The engine's progress callback while it opens (text encoder, field, reference phrases, index):
        0-20% of the bar; raises :class:`Cancelled` once the user cancelled, between those steps."""
        if self.cancelled:
            raise _cancelled_error()("the query was cancelled")
        self.progress = 0.2 * fraction
        self.stage = f"opening the query engine: {stage}"

    def work(self) -> None:
        from fourlegs_engine import api

        self.stage, self.progress = "opening the query engine", 0.0
        try:
            self.engine = querying.open_query_engine(self.scene, encoder=self.encoder, progress=self.on_open_progress)
        except api.InputError:
            problem = field_problem(self.scene)
            if problem is None:
                raise
            raise RuntimeError(problem) from None
        if self.cancelled:
            return
        self.stage, self.progress = "localizing in time and space", 0.2
        self.localization = self.engine.localize(self.query, set(ALL_NEEDS), progress=self.on_progress)
        temporal = self.localization.temporal
        t = temporal.peak if temporal is not None and temporal.found else 0
        self.stage, self.progress = "relevancy of the Gaussians", 0.9
        self.peak_relevancy = np.asarray(self.engine.gaussian_relevancy(self.query, int(t)), np.float32)
        self.progress, self.stage = 1.0, "done"


class FOURLEGS_OT_run_query(jobs.JobOperator, bpy.types.Operator):
    """Find when and where the query happens (runs in the background; Esc cancels)"""

    bl_idname = "fourlegs.run_query"
    bl_label = "Run Query"
    bl_options = {"REGISTER"}
    job_label = "query"

    @classmethod
    def poll(cls, context):
        props = context.scene.fourlegs
        return splat_object(context) is not None and bool(props.query.strip()) and not props.running

    def execute(self, context):
        return self.invoke(context, None)

    def invoke(self, context, event):
        props = context.scene.fourlegs
        try:
            problem = missing_for(("torch",))
            if problem is None:
                scene = importer.engine_scene_for(splat_object(context))
        except Exception as exc:
            problem = error_line(exc)
        if problem is not None:
            return self.refuse(context, problem)
        return self.start_job(context, QueryJob(scene, props.query.strip(), querying.encoder_config(props)),
                              "fourlegs-query", "starting")

    def finish_job(self, context):
        props = context.scene.fourlegs
        job = self._job
        store_results(context.scene, splat_object(context), job.engine, job.query, job.localization,
                      job.peak_relevancy)
        props.progress, props.status = 1.0, "done" if props.found else "not found"
        self.report({"INFO"} if props.found else {"WARNING"},
                    f"4-LEGS: {job.query!r} " + (f"found at timesteps {props.segment_start}-{props.segment_end}"
                                                 if props.found else "was not found"))
        return {"FINISHED"}


def field_problem(scene: Any) -> Optional[str]:
    """Why ``scene`` cannot be queried yet (no language field: press Prepare), or None."""
    from fourlegs_engine import api

    if scene is not None and not api.has_language_field(scene):
        return ("the scene has no distilled language field yet: press Prepare Language Field (4-LEGS panel, "
                "Query) first; it runs in the background and resumes where it stopped")
    return None


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
    _LOCALIZERS[importer.source_key(obj)] = planning.CachedLocalizer(engine, query, localization, ALL_NEEDS)
    obj[LOCALIZATION_KEY] = json.dumps({"query": query, "need": sorted(ALL_NEEDS),
                                        "localization": localization.to_dict()})
    importer.set_relevancy_provider(obj, lambda t, e=engine, q=query: e.gaussian_relevancy(q, t).numpy())
    if peak_relevancy is not None:
        importer.set_relevancy(obj, peak_relevancy, show=True)


# ----------------------------------------------------------------------------- several scenes
def imported_splat_objects() -> list[bpy.types.Object]:
    """Every 4-LEGS point-cloud object in the file (one per imported scene), in name order."""
    return sorted((o for o in bpy.data.objects if importer.source_key(o)), key=lambda o: o.name)


class RankJob(jobs.Job):
    """Ranks several scenes by max_t s_t (the engine's multi-scene selection)."""

    def __init__(self, scenes: dict[str, Any], query: str, encoder: Any = None):
        super().__init__()
        self.scenes, self.query, self.encoder = scenes, query, encoder
        self.ranking = None

    def work(self) -> None:
        from fourlegs_engine import api

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


class FOURLEGS_OT_find_best_scene(jobs.JobOperator, bpy.types.Operator):
    """Rank the imported 4-LEGS scenes by how strongly the query happens in them (max over time of s_t, on
    every 10th timestep) and make the best one the panel's scene (runs in the background; Esc cancels)"""

    bl_idname = "fourlegs.find_best_scene"
    bl_label = "Find Best Scene"
    bl_options = {"REGISTER", "UNDO"}
    job_label = "Find Best Scene"

    def execute(self, context):
        return self.invoke(context, None)

    @classmethod
    def poll(cls, context):
        props = context.scene.fourlegs
        return len(imported_splat_objects()) > 1 and bool(props.query.strip()) and not props.running

    def invoke(self, context, event):
        props = context.scene.fourlegs
        problem = missing_for(("torch",))
        if problem is not None:
            return self.refuse(context, problem)
        try:
            scenes = {obj.name: importer.engine_scene_for(obj) for obj in imported_splat_objects()}
        except Exception as exc:
            return self.refuse(context, error_line(exc))
        return self.start_job(context, RankJob(scenes, props.query.strip(), querying.encoder_config(props)),
                              "fourlegs-rank", "ranking scenes")

    def finish_job(self, context):
        props = context.scene.fourlegs
        job = self._job
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


class FOURLEGS_OT_show_relevancy(bpy.types.Operator):
    """Colour the point cloud by the query's relevancy, or by its own colours"""

    bl_idname = "fourlegs.show_relevancy"
    bl_label = "Show Relevancy"
    bl_options = {"REGISTER", "UNDO"}

    show: BoolProperty(default=True)

    @classmethod
    def poll(cls, context):
        return splat_object(context) is not None

    def execute(self, context):
        importer.show_relevancy(splat_object(context), self.show)
        return {"FINISHED"}


classes = (FOURLEGS_OT_run_query, FOURLEGS_OT_find_best_scene, FOURLEGS_OT_show_relevancy)
