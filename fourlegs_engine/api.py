"""The engine as the Blender add-on (and any other front end) sees it: a small, stable facade.

Everything here is re-exported from where it lives; front ends import this module instead of reaching
into the engine's internals, so the engine can reorganize without breaking them::

    from fourlegs_engine import api

    scene = api.open_scene("capture/")                 # bundle, params.npz dir, .ply file or .ply dir
    scene = api.ensure_language_field(scene)           # once per scene
    engine = api.open_query_engine(scene, options=api.QueryOptions(spatial="fast"))
    plan = api.plan_highlight(scene, engine, "a ball flying in the air", api.load_preset("broadcast"))
"""
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from .errors import (Cancelled, FourlegsError, InputError, OutputExistsError, describe_environment_error,
                     print_error)

# name -> engine module it lives in. They are imported on first use, so a front end that only opens and
# shows a scene (the Blender add-on's import and timeline playback) runs without PyTorch installed.
_LAZY = {
    "atomic_path": "fileio", "write_json_atomic": "fileio", "OUTPUTS_MARKER": "fileio", "claim_outputs": "fileio",
    "image_file_problem": "fileio", "incomplete_write_error": "fileio",
    "check_text": "validate",
    "available_presets": "highlights", "load_preset": "highlights", "plan_highlight": "highlights",
    "plan_needs": "highlights",
    "EncoderConfig": "pipeline", "FieldStep": "pipeline", "QueryOptions": "pipeline",
    "language_field_steps": "pipeline", "ensure_language_field": "pipeline",
    "has_language_field": "pipeline", "open_query_engine": "pipeline", "open_scene": "pipeline",
    "text_encoder": "pipeline",
    "rasterize": "render", "eval_sh": "render.sh",
    "rank_scenes_opening": "query.multiscene",
    "Camera": "scene", "Scene": "scene", "load_scene": "scene",
    "release_mapped_pages": "scene.gaussians",
    "torch_threads": "threads", "kernel_threads": "threads", "usable_cpu_count": "threads",
    "HighlightJobOptions": "highlight_job", "StageTimer": "highlight_job", "finish_highlight_job": "highlight_job",
    "plan_digest": "highlight_job", "prepare_highlight_job": "highlight_job",
}

if TYPE_CHECKING:
    from .fileio import (OUTPUTS_MARKER, atomic_path, claim_outputs, image_file_problem, incomplete_write_error,
                         write_json_atomic)
    from .highlight_job import (HighlightJobOptions, StageTimer, finish_highlight_job, plan_digest,
                                prepare_highlight_job)
    from .highlights import available_presets, load_preset, plan_highlight, plan_needs
    from .pipeline import (EncoderConfig, FieldStep, QueryOptions, ensure_language_field, has_language_field,
                           language_field_steps, open_query_engine, open_scene, text_encoder)
    from .query.multiscene import rank_scenes_opening
    from .render import rasterize
    from .render.sh import eval_sh
    from .scene import Camera, Scene, load_scene
    from .scene.gaussians import release_mapped_pages
    from .threads import kernel_threads, torch_threads, usable_cpu_count
    from .validate import check_text


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__package__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


__all__ = ["Cancelled", "Camera", "EncoderConfig", "FieldStep", "FourlegsError", "HighlightJobOptions", "InputError",
           "OUTPUTS_MARKER", "OutputExistsError", "QueryOptions", "Scene", "StageTimer", "atomic_path",
           "available_presets", "check_text", "claim_outputs", "describe_environment_error",
           "ensure_language_field", "eval_sh", "finish_highlight_job", "has_language_field", "image_file_problem",
           "incomplete_write_error", "kernel_threads", "language_field_steps", "load_preset", "load_scene",
           "open_query_engine", "open_scene", "plan_digest", "plan_highlight", "plan_needs",
           "prepare_highlight_job", "print_error", "rank_scenes_opening", "rasterize", "release_mapped_pages", "text_encoder",
           "torch_threads", "usable_cpu_count", "write_json_atomic"]
