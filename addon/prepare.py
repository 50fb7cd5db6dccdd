"""Prepare language field: extract features -> train the autoencoder -> lift, in the background.

A worker job walks :func:`fourlegs_engine.api.language_field_steps` (one timestep or epoch per step,
each saved before it is reported); the add-on's job runner (:mod:`.jobs`) shows the stage and its
progress in the panel and stops it on Esc or Cancel between two steps. The work done is kept in the
scene's bundle, so running the operator again resumes. A scene that is not a bundle (PLY,
``params.npz``) is converted once into a bundle in the engine's cache, which the object then points to.
"""
from __future__ import annotations

import contextlib
from typing import Any

import bpy

from . import importer, jobs, querying
from .messages import missing_for

#: stage name prefix -> index, for one progress bar over the three stages
STAGES = ("extract features", "train autoencoder", "distil")


class _ExtractionDone(Exception):
    """Raised by the stage reporter when the main job's chain reaches the autoencoder."""


class PrepareJob(jobs.Job):
    """Build the language field of the scene at ``source``; ``scene`` is the re-opened scene once done."""

    def __init__(self, source: str, encoder: Any = None):
        super().__init__()
        self.source, self.encoder = source, encoder
        self.stage = "opening the scene"
        self.scene: Any = None
        self.steps: list[tuple[str, int, int]] = []

    def work(self) -> None:
        from fourlegs_engine import api

        scene = api.open_scene(self.source)
        encoder_config = self.encoder or api.EncoderOptions()
        if not api.has_language_field(scene):
            self.extract_as_the_main_job(scene, encoder_config)
        if self.cancelled:
            return
        for step in api.language_field_steps(scene, encoder_config=encoder_config):
            index = next(i for i, name in enumerate(STAGES) if step.stage.startswith(name))
            self.steps.append((step.stage, step.done, step.total))
            self.stage = f"{step.stage} {step.done}/{step.total}"
            self.progress = (index + step.done / max(step.total, 1)) / len(STAGES)
            if self.cancelled:
                return
        self.scene = api.open_scene(self.source)
        self.progress, self.stage = 1.0, "done"

    def extract_as_the_main_job(self, scene: Any, encoder_config: Any) -> None:
        """Extract the features of every timestep as the main job's chain does (``ensure_language_field``:
        one call, so neighbouring timesteps share their rendered frames and the encoder's warm-up), stopping
        the chain when it reaches the autoencoder; the per-unit steps (cancellable, resumable) do the rest."""
        from fourlegs_engine import api

        @contextlib.contextmanager
        def stage(name: str):
            if not name.startswith(STAGES[0]):
                raise _ExtractionDone
            self.stage = name
            yield

        try:
            api.ensure_language_field(scene, encoder_config=encoder_config, stage=stage)
        except _ExtractionDone:
            pass


def has_field(obj) -> bool:
    """Whether the imported object's scene has a language field (False when it cannot be opened)."""
    from fourlegs_engine import api

    try:
        scene = importer.engine_scene_for(obj)
        return scene is not None and api.has_language_field(scene)
    except Exception:  # cannot be opened, or PyTorch is missing (the panel says so on its own line)
        return False


class FOURLEGS_OT_prepare_field(jobs.JobOperator, bpy.types.Operator):
    """Build the scene's language field (extract features, train the autoencoder, lift) in the background;
    Esc cancels, running it again resumes"""

    bl_idname = "fourlegs.prepare_field"
    bl_label = "Prepare Language Field"
    bl_options = {"REGISTER"}
    job_label = "Prepare Language Field"

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
            return self.refuse(context, "the scene was not imported from a file; it cannot hold a language field")
        problem = missing_for(("torch",))
        if problem is not None:
            return self.refuse(context, problem)
        return self.start_job(context, PrepareJob(key, querying.encoder_config(props)), "fourlegs-prepare",
                              "preparing the language field")

    def job_cancelled(self, context):
        if self._job.scene is not None:  # cancelled after the last step: the field is complete
            return self.finish_job(context)
        props = context.scene.fourlegs
        props.status = f"cancelled at {self._job.stage} (run it again to resume)"
        self.report({"WARNING"}, f"4-LEGS: language field {props.status}")
        return {"CANCELLED"}

    def finish_job(self, context):
        props = context.scene.fourlegs
        root = str(self._job.scene.root)
        importer.adopt_scene(props.splat_object, self._job.scene, root)
        props.progress, props.status = 1.0, "language field ready"
        self.report({"INFO"}, f"4-LEGS: language field ready ({root})")
        return {"FINISHED"}


classes = (FOURLEGS_OT_prepare_field,)
