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

from .errors import FourlegsError, InputError, OutputExistsError, describe_environment_error, print_error
from .fileio import (OUTPUTS_MARKER, atomic_path, claim_outputs, image_file_problem, incomplete_write_error,
                     write_json_atomic)
from .highlights import available_presets, load_preset, plan_highlight, plan_needs
from .pipeline import (EncoderConfig, QueryOptions, ensure_language_field, has_language_field, open_query_engine,
                       open_scene, text_encoder)
from .render import rasterize
from .scene import Camera, Scene, load_scene
from .threads import torch_threads
from .validate import check_text

__all__ = ["Camera", "EncoderConfig", "FourlegsError", "InputError", "OUTPUTS_MARKER", "OutputExistsError",
           "QueryOptions", "Scene", "atomic_path", "available_presets", "check_text", "claim_outputs",
           "describe_environment_error", "ensure_language_field", "has_language_field", "image_file_problem",
           "incomplete_write_error", "load_preset", "load_scene", "open_query_engine", "open_scene",
           "plan_highlight", "plan_needs", "print_error", "rasterize", "text_encoder", "torch_threads",
           "write_json_atomic"]
