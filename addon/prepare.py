"""Prepare language field: extract features -> train the autoencoder -> lift, in the background.

A worker thread walks :func:`fourlegs_engine.api.language_field_steps` (one timestep or epoch per
step, each saved before it is reported); a modal operator polls it on a timer, shows the stage and its
progress in the panel and stops it on Esc or Cancel between two steps. The work done is kept in the
scene's bundle, so running the operator again resumes. A scene that is not a bundle (PLY,
``params.npz``) is converted once into a bundle in the engine's cache, which the object then points to.
"""
from __future__ import annotations

import threading
import traceback
from typing import Any, Optional

import bpy

from . import importer, querying

#: stage name prefix -> index, for one progress bar over the three stages
STAGES = ("extract features", "train autoencoder", "distil")


class PrepareJob:
    """State shared between the worker thread and the modal operator (plain attributes, no bpy)."""

    def __init__(self, source: str, encoder: Any = None):
        self.source, self.encoder = source, encoder
        self.progress, self.stage = 0.0, "opening the scene"
        self.cancelled = self.done = False
        self.error: Optional[str] = None
        self.scene: Any = None
        self.steps: list[tuple[str, int, int]] = []

    def run(self) -> None:
        from fourlegs_engine import api

        try:
            scene = api.open_scene(self.source)
            for step in api.language_field_steps(scene, encoder_config=self.encoder or api.EncoderConfig()):
                index = next(i for i, name in enumerate(STAGES) if step.stage.startswith(name))
                self.steps.append((step.stage, step.done, step.total))
                self.stage = f"{step.stage} {step.done}/{step.total}"
                self.progress = (index + step.done / max(step.total, 1)) / len(STAGES)
                if self.cancelled:
                    return
            self.scene = api.open_scene(self.source)
            self.progress, self.stage = 1.0, "done"
        except Exception as exc:  # reported on the main thread
            from .operators import _err

            self.error = _err(exc)
            traceback.print_exc()
        finally:
            self.done = True


_JOBS: list[PrepareJob] = []


def cancel_all() -> None:
    for job in _JOBS:
        job.cancelled = True


def has_field(obj) -> bool:
    """Whether the imported object's scene has a language field (False when it cannot be opened)."""
    from fourlegs_engine import api

    try:
        scene = importer.engine_scene_for(obj)
    except Exception:
        return False
    return scene is not None and api.has_language_field(scene)


class FOURLEGS_OT_prepare_field(bpy.types.Operator):
    """Build the scene's language field (extract features, train the autoencoder, lift) in the background;
    Esc cancels, running it again resumes"""

    bl_idname = "fourlegs.prepare_field"
    bl_label = "Prepare Language Field"
    bl_options = {"REGISTER"}

    _timer = None
    _job: Optional[PrepareJob] = None

    @classmethod
    def poll(cls, context):
        obj = context.scene.fourlegs.splat_object
        return obj is not None and bool(importer.source_key(obj)) and not context.scene.fourlegs.running

    def execute(self, context):
        return self.invoke(context, None)

    def invoke(self, context, event):
        props = context.scene.fourlegs
        key = importer.source_key(props.splat_object)
        if key.startswith("memory:"):
            self.report({"ERROR"}, "4-LEGS: the scene was not imported from a file; it cannot hold a language field")
            return {"CANCELLED"}
        self._job = PrepareJob(key, querying.encoder_config(props))
        _JOBS.append(self._job)
        threading.Thread(target=self._job.run, name="fourlegs-prepare", daemon=True).start()
        props.running, props.progress, props.status = True, 0.0, "preparing the language field"
        wm = context.window_manager
        if context.window is not None and not bpy.app.background:
            self._timer = wm.event_timer_add(0.2, window=context.window)
            wm.modal_handler_add(self)
            return {"RUNNING_MODAL"}
        while not self._job.done:  # background mode has no event loop: wait here
            threading.Event().wait(0.05)
        return self._finish(context)

    def modal(self, context, event):
        props = context.scene.fourlegs
        job = self._job
        if event.type == "ESC":
            job.cancelled = True
        if event.type == "TIMER":
            props.progress, props.status = job.progress, job.stage
            for area in context.screen.areas if context.screen else []:
                if area.type == "VIEW_3D":
                    area.tag_redraw()
            if job.done:
                return self._finish(context)
        return {"PASS_THROUGH"}

    def _finish(self, context):
        if self._timer is not None:
            context.window_manager.event_timer_remove(self._timer)
            self._timer = None
        if self._job in _JOBS:
            _JOBS.remove(self._job)
        props = context.scene.fourlegs
        job = self._job
        props.running = False
        if job.error is not None:
            props.status = f"error: {job.error}"
            self.report({"ERROR"}, f"4-LEGS Prepare Language Field: {job.error}")
            return {"CANCELLED"}
        if job.scene is None:
            props.status = f"cancelled at {job.stage} (run it again to resume)"
            self.report({"WARNING"}, f"4-LEGS: language field {props.status}")
            return {"CANCELLED"}
        obj = props.splat_object
        root = str(job.scene.root)
        importer.adopt_scene(obj, job.scene, root)
        props.progress, props.status = 1.0, "language field ready"
        self.report({"INFO"}, f"4-LEGS: language field ready ({root})")
        return {"FINISHED"}


class FOURLEGS_OT_cancel_prepare(bpy.types.Operator):
    """Stop preparing the language field (finished timesteps are kept)"""

    bl_idname = "fourlegs.cancel_prepare"
    bl_label = "Cancel"

    def execute(self, context):
        cancel_all()
        return {"FINISHED"}


classes = (FOURLEGS_OT_prepare_field, FOURLEGS_OT_cancel_prepare)
