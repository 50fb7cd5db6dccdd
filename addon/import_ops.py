"""Import 4D Scene: a bundle, params.npz directory, PLY file or PLY sequence as a splat object."""
from __future__ import annotations

from pathlib import Path

import bpy
from bpy.props import BoolProperty, StringProperty
from bpy_extras.io_utils import ImportHelper

from . import importer, native_splats, ply_files, render_engine
from .messages import error_line


class FOURLEGS_OT_import_scene(bpy.types.Operator, ImportHelper):
    """Import a 4D Gaussian scene (bundle directory, params.npz directory, PLY file or PLY sequence)"""

    bl_idname = "fourlegs.import_scene"
    bl_label = "Import 4D Scene"
    bl_options = {"REGISTER", "UNDO"}

    filter_glob: StringProperty(default="*.json;*.npz;*.ply", options={"HIDDEN"})
    with_cameras: BoolProperty(name="Cameras", default=True, description="Also import the scene's cameras")
    sequence: BoolProperty(name="Whole Sequence", default=True,
                           description="A PLY file numbered like its neighbours (frame_0001.ply, ...) imports "
                                       "the whole sequence, one file per timestep")

    def execute(self, context):
        path = Path(bpy.path.abspath(self.filepath))
        if path.is_file() and path.name in ("scene.json", "params.npz"):
            path = path.parent  # a bundle / params.npz directory was picked through one of its files
        if path.is_file() and path.suffix.lower() == ".ply" and self.sequence:
            path = ply_files.sequence_of(path) or path
        try:
            scene = importer.load_engine_scene(path)
            one_ply = path if path.is_file() and path.suffix.lower() == ".ply" else None
            obj = importer.import_scene(context.scene, scene, source=str(path), with_cameras=self.with_cameras,
                                        ply_file=one_ply)
            kept = self._keep_extra_properties(obj, path, one_ply)
        except Exception as exc:
            self.report({"ERROR"}, f"4-LEGS import: {error_line(exc)}")
            return {"CANCELLED"}
        if not native_splats.available():
            context.scene.render.engine = render_engine.ENGINE_ID  # the one engine that draws splats here
        if kept:
            self.report({"INFO"}, f"extra PLY properties kept as point attributes: {', '.join(kept)}")
        self.report({"INFO"}, f"imported {scene.name}: {scene.num_gaussians} Gaussians x {scene.num_timesteps} timesteps")
        return {"FINISHED"}

    @staticmethod
    def _keep_extra_properties(obj, path: Path, one_ply) -> list[str]:
        """Extra vertex properties of the (first) PLY file as float point attributes; Blender's own importer
        keeps them already. Returns their names."""
        files = [path] if path.suffix.lower() == ".ply" else sorted(path.glob("*.ply"), key=ply_files.natural_key)
        if not files:
            return []
        extra = ply_files.extra_properties(files[0])
        if one_ply is None or not native_splats.available():
            for name, values in extra.items():
                native_splats.write_attribute(obj.data, name, "FLOAT", values)
        return sorted(extra)


class FOURLEGS_OT_relink_scene(bpy.types.Operator, ImportHelper):
    """Point the panel's splat object at its scene's new place (a moved or copied project)"""

    bl_idname = "fourlegs.relink_scene"
    bl_label = "Relink Scene"
    bl_options = {"REGISTER", "UNDO"}

    filter_glob: StringProperty(default="*.json;*.npz;*.ply", options={"HIDDEN"})

    @classmethod
    def poll(cls, context):
        obj = context.scene.fourlegs.splat_object
        return obj is not None and bool(importer.source_key(obj))

    def execute(self, context):
        path = Path(bpy.path.abspath(self.filepath))
        if path.is_file() and path.name in ("scene.json", "params.npz"):
            path = path.parent
        obj = context.scene.fourlegs.splat_object
        try:
            importer.relink(obj, path)
        except Exception as exc:
            self.report({"ERROR"}, f"4-LEGS Relink Scene: {error_line(exc)}")
            return {"CANCELLED"}
        context.scene.fourlegs.source_path = importer.source_key(obj)
        importer.update_scene_objects(context.scene)
        self.report({"INFO"}, f"4-LEGS: {obj.name} now shows {importer.source_key(obj)}")
        return {"FINISHED"}


classes = (FOURLEGS_OT_import_scene, FOURLEGS_OT_relink_scene)
