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

from typing import TYPE_CHECKING, Any

from .errors import (Cancelled, FourlegsError, InputError, OutputExistsError, describe_environment_error,
                     exit_code_of, print_error)
from .lazy import lazy_exports

# name -> engine module it lives in. They are imported on first use, so a front end that only opens and
# shows a scene (the Blender add-on's import and timeline playback) runs without PyTorch installed.
_LAZY = {
    **{name: "errors" for name in ("Cancelled", "FourlegsError", "InputError", "OutputExistsError",
                                   "describe_environment_error", "exit_code_of", "print_error")},
    "atomic_path": "fileio", "write_json_atomic": "fileio", "OUTPUTS_MARKER": "fileio", "claim_outputs": "fileio",
    "image_file_problem": "fileio", "incomplete_write_error": "fileio",
    "check_text": "validate",
    "PARENT_PID_ENV": "lifetime", "die_with_parent": "lifetime",
    "LockedError": "runlock", "run_lock": "runlock",
    "available_presets": "highlights", "load_preset": "highlights", "plan_highlight": "highlights",
    "plan_needs": "highlights",
    "EncoderOptions": "pipeline", "FieldStep": "pipeline", "QueryOptions": "pipeline",
    "language_field_steps": "pipeline", "ensure_language_field": "pipeline",
    "has_language_field": "pipeline", "open_query_engine": "pipeline", "open_scene": "pipeline",
    "plan_language_field": "pipeline", "text_encoder": "pipeline",
    "rasterize": "render", "eval_sh": "render.sh",
    "rank_scenes_opening": "query.multiscene",
    "Camera": "scene", "Scene": "scene", "load_scene": "scene",
    "release_mapped_pages": "scene.gaussians",
    "torch_threads": "threads", "kernel_threads": "threads", "usable_cpu_count": "threads",
    "HighlightJobOptions": "highlight_job", "StageTimer": "highlight_job",
    "STAGE_FILE_ENV": "highlight_job", "finish_highlight_job": "highlight_job",
    "plan_digest": "highlight_job", "prepare_highlight_job": "highlight_job",
}

if TYPE_CHECKING:
    from .fileio import (OUTPUTS_MARKER, atomic_path, claim_outputs, image_file_problem, incomplete_write_error,
                         write_json_atomic)
    from .highlight_job import (STAGE_FILE_ENV, HighlightJobOptions, StageTimer, finish_highlight_job, plan_digest,
                                prepare_highlight_job)
    from .lifetime import PARENT_PID_ENV, die_with_parent
    from .runlock import LockedError, run_lock
    from .highlights import available_presets, load_preset, plan_highlight, plan_needs
    from .pipeline import (EncoderOptions, FieldStep, QueryOptions, ensure_language_field, has_language_field,
                           language_field_steps, open_query_engine, open_scene, plan_language_field,
                           text_encoder)
    from .query.multiscene import rank_scenes_opening
    from .render import rasterize
    from .render.sh import eval_sh
    from .scene import Camera, Scene, load_scene
    from .scene.gaussians import release_mapped_pages
    from .threads import kernel_threads, torch_threads, usable_cpu_count
    from .validate import check_text

__getattr__, __dir__, __all__ = lazy_exports(__name__, _LAZY, base=__package__)

