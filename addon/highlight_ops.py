"""Generate Highlight: plan the shots for the query and turn the plan into Blender data; the panel of a
scene made from a plan."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Optional

import bpy
import numpy as np
from bpy.props import StringProperty

from . import (compositor, importer, jobs, keyframes, native_render, native_splats, planning, plots, querying,
               relevancy_store, render_engine, video)
from .messages import error_line
from .query_ops import fill_segments, localizer_for, splat_object


def disabled_effects(props) -> list[str]:
    off = []
    if not props.use_zoom_in:
        off.append("zoom_in")
    if not props.use_bullet_time:
        off.append("bullet_time")
    if not props.use_desaturate:
        off.append("desaturate_background")
    if not props.use_blur:
        off.append("blur_background")
    return off


def generate_highlight(bl_scene, plan: dict[str, Any]) -> bpy.types.Object:
    """Turn a plan dict into Blender data (camera keys, scene-time keys, timeline, passes, compositor).

    The renderer is the panel's choice (``scene.fourlegs.renderer``): EEVEE or Cycles with their own
    relevancy mask on Blender 5.3+ (:mod:`.native_render`), else the 4-LEGS Splats engine.
    """
    cam = keyframes.apply_plan(bl_scene, plan)
    fill_subjects(bl_scene.fourlegs, plan)
    text = bpy.data.texts.get(render_engine.PLAN_TEXT_NAME) or bpy.data.texts.new(render_engine.PLAN_TEXT_NAME)
    text.clear()
    text.write(json.dumps(plan, indent=1))
    text[keyframes.GENERATED_KEY] = True
    importer.use_standard_view(bl_scene)
    passes = plan.get("passes") or {}
    rel, depth = bool(passes.get("relevancy")), bool(passes.get("depth"))
    store_relevancy(bl_scene, plan)
    if native_renderer(bl_scene):
        if bl_scene.render.engine not in native_render.NATIVE_ENGINES:
            bl_scene.render.engine = "BLENDER_EEVEE"
        for obj in importer.splat_objects(bl_scene):  # the splats' own radiance, not the heat map
            importer.show_relevancy(obj, False)
        layer = native_render.setup(bl_scene, rel and bool(plan.get("desaturate") or plan.get("blur")))
        for view_layer in bl_scene.view_layers:
            view_layer.use_pass_z = depth and view_layer != layer
        compositor.build_compositor(bl_scene, plan, mask_layer=layer.name if layer is not None else None)
        return cam
    bl_scene.render.engine = render_engine.ENGINE_ID
    native_render.setup(bl_scene, False)
    for view_layer in bl_scene.view_layers:
        view_layer.use_pass_z = depth
        view_layer.fourlegs_relevancy = rel
    compositor.build_compositor(bl_scene, plan)
    return cam


def fill_subjects(props, plan: dict[str, Any]) -> None:
    """List the plan's instances (``localization.instances``, best first) in the panel; the first
    ``framed_instances`` of them have their own shots."""
    loc = plan.get("localization") or {}
    framed = int(loc.get("framed_instances") or 0)
    props.subjects.clear()
    for i, inst in enumerate(loc.get("instances") or []):
        item = props.subjects.add()
        item.gaussians, item.height = int(inst.get("gaussians", 0)), float(inst.get("height", 0.0))
        item.mass, item.framed = float(inst.get("mass", 0.0)), i < framed
    props.subject_index = 0 if len(props.subjects) else -1


def native_renderer(bl_scene) -> bool:
    """Whether the highlight renders with EEVEE/Cycles (Blender 5.3+ and the panel's choice)."""
    return native_splats.available() and bl_scene.fourlegs.renderer == "NATIVE"


def desaturated_timesteps(bl_scene, plan: dict[str, Any]) -> list[int]:
    """The scene timesteps (rounded) shown on frames whose relevancy the highlight uses."""
    frames = {f for f, w in compositor.mask_weights(plan).items() if w > 0.0}
    for a, b in (plan.get("passes") or {}).get("relevancy") or []:
        frames.update(range(int(a), int(b) + 1))
    curve = keyframes.find_fcurve(bl_scene, keyframes.TIMESTEP_PATH)
    if curve is None:
        return sorted({int(round(float(bl_scene.fourlegs.timestep)))} if frames else set())
    return sorted({int(round(curve.evaluate(f))) for f in frames})


def store_relevancy(bl_scene, plan: dict[str, Any]) -> int:
    """Store the relevancy of the desaturated timesteps beside the scene's field (:mod:`.relevancy_store`)
    when this Blender can evaluate it (a query engine is the splat object's provider), so EEVEE and
    Cycles render the mask later without PyTorch. Returns how many timesteps were written."""
    obj = bl_scene.fourlegs.splat_object
    query = plan.get("query")
    if obj is None or not query or importer.relevancy_provider(obj) is None:
        return 0
    scene = importer.engine_scene_for(obj)
    if relevancy_store.store_dir(scene, query) is None:
        return 0
    last = scene.num_timesteps - 1
    steps = [min(max(t, 0), last) for t in desaturated_timesteps(bl_scene, plan)]
    # through the object's cache: the 4-LEGS render of these timesteps reuses what is computed here
    return relevancy_store.store_timesteps(scene, query, lambda t: importer.gaussian_relevancy(obj, t), steps)


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


def picked_segment(props) -> Optional[tuple[int, int]]:
    """The segment picked in the panel's list (None when none is picked)."""
    if 0 <= props.segment_index < len(props.segments):
        item = props.segments[props.segment_index]
        return int(item.start), int(item.end)
    return None


class FOURLEGS_OT_generate_highlight(bpy.types.Operator):
    """Plan the highlight shots for the query and create the camera animation, scene-time keys and compositor setup"""

    bl_idname = "fourlegs.generate_highlight"
    bl_label = "Generate Highlight"
    bl_options = {"REGISTER", "UNDO"}

    plan_file: StringProperty(name="Plan", subtype="FILE_PATH", default="",
                              description="Use this plan JSON instead of planning from the query")

    @classmethod
    def poll(cls, context):
        return splat_object(context) is not None and not context.scene.fourlegs.running

    def invoke(self, context, event):
        if keyframes.has_generated(context.scene):  # edits to the generated camera/keys would be lost
            return context.window_manager.invoke_confirm(
                self, event, title="Replace the highlight?",
                message="Generate again replaces the highlight camera, its keys, the shot markers and the "
                        "compositor setup, with any edits made to them.", confirm_text="Replace")
        return self.execute(context)

    def execute(self, context):
        try:
            plan = self._plan(context)
            if plan is None:
                return {"CANCELLED"}
            generate_highlight(context.scene, plan)
        except Exception as exc:
            self.report({"ERROR"}, f"4-LEGS Generate Highlight: {error_line(exc)}")
            return {"CANCELLED"}
        for msg in plan.get("messages", []):
            self.report({"WARNING"}, str(msg))
        self.report({"INFO"}, f"highlight: {len(plan['shots'])} shots, frames {plan['frame_start']}-{plan['frame_end']}")
        return {"FINISHED"}

    def _plan(self, context) -> Optional[dict[str, Any]]:
        """The plan file's plan, or one planned from the query (None: the query runs first, in the UI)."""
        props = context.scene.fourlegs
        if self.plan_file:
            return json.loads(Path(bpy.path.abspath(self.plan_file)).read_text(encoding="utf-8"))
        obj = splat_object(context)
        scene = importer.engine_scene_for(obj)
        localizer = localizer_for(obj, props)
        query = props.query.strip()
        if (localizer is None or localizer.query != query) and jobs.interactive():
            # localizing takes tens of seconds: run it in the background instead of freezing the UI
            if query and bpy.ops.fourlegs.run_query.poll():
                bpy.ops.fourlegs.run_query("INVOKE_DEFAULT")
                self.report({"INFO"}, "4-LEGS: running the query first (in the background); press "
                                      "Generate Highlight again when it is done")
            else:
                self.report({"WARNING"}, "4-LEGS: type a query and Run Query first")
            return None
        if localizer is None or localizer.query != query:
            localizer = planning.CachedLocalizer(
                querying.open_query_engine(scene, encoder=querying.encoder_config(props)), query)
        picked = picked_segment(props)
        if picked is not None:
            localizer = planning.PickedSegmentLocalizer(localizer, picked)
        return planning.make_plan(scene, localizer, query, props.preset, disabled_effects=disabled_effects(props))


classes = (FOURLEGS_OT_generate_highlight,)
