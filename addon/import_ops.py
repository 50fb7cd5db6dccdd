"""Import 4D Scene: a bundle, params.npz directory, PLY file or PLY directory as a splat object."""
from __future__ import annotations

from pathlib import Path

import bpy
from bpy.props import BoolProperty, StringProperty
from bpy_extras.io_utils import ImportHelper

from . import importer
from .messages import error_line


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
            self.report({"ERROR"}, f"4-LEGS import: {error_line(exc)}")
            return {"CANCELLED"}
        self.report({"INFO"}, f"imported {scene.name}: {scene.num_gaussians} Gaussians x {scene.num_timesteps} timesteps")
        return {"FINISHED"}


classes = (FOURLEGS_OT_import_scene,)
