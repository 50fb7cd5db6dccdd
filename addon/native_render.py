"""Highlights rendered by EEVEE or Cycles (Blender 5.3+): the relevancy mask Blender renders itself.

Blender shades a ``GAUSSIAN_SPLAT`` point cloud without a material from its own radiance attributes
(with a material, the material's shader replaces them). So the picture is the scene's own view layer,
splats untouched next to meshes and lights, and the mask comes from a second view layer,
"4-LEGS Relevancy", whose material override reads the per-splat relevancy attribute
(``splat_relevancy``) through an Attribute node into the AOV "Relevancy". The compositor
(:mod:`.compositor`) desaturates the picture where that AOV is low. Meshes in the relevancy layer get
the override too (no relevancy attribute: 0), so a mesh in front of the action hides it in the mask as
it does in the picture.

The frame-change handler writes the relevancy of the scene timestep on frames where the highlight
desaturates (the only frames whose mask is used); where it comes from: :mod:`.relevancy_store`.
"""
from __future__ import annotations

from typing import Optional

import bpy
import numpy as np
from bpy.app.handlers import persistent

from . import compositor, importer, native_splats, relevancy_store
from .keyframes import GENERATED_KEY, frames_in_ranges
from .render_engine import plan_of

LAYER_NAME = "4-LEGS Relevancy"
MATERIAL_NAME = "4-LEGS Relevancy Mask"
AOV_NAME = compositor.RELEVANCY_PASS
NATIVE_ENGINES = ("BLENDER_EEVEE", "BLENDER_EEVEE_NEXT", "CYCLES")
SHOWN_KEY = "fourlegs_relevancy_timestep"  # object property: the timestep whose relevancy the attribute holds


def relevancy_material() -> bpy.types.Material:
    """Attribute ``splat_relevancy`` (0 where absent) -> AOV "Relevancy"; the surface emits it too."""
    mat = bpy.data.materials.get(MATERIAL_NAME)
    if mat is not None:
        return mat
    mat = bpy.data.materials.new(MATERIAL_NAME)
    mat[GENERATED_KEY] = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    nodes.clear()
    attr = nodes.new("ShaderNodeAttribute")
    attr.attribute_type, attr.attribute_name = "GEOMETRY", native_splats.RELEVANCY_ATTR
    aov = nodes.new("ShaderNodeOutputAOV")
    aov.aov_name = AOV_NAME
    emit, out = nodes.new("ShaderNodeEmission"), nodes.new("ShaderNodeOutputMaterial")
    links.new(attr.outputs["Fac"], aov.inputs["Value"])
    links.new(attr.outputs["Fac"], emit.inputs["Strength"])
    links.new(emit.outputs["Emission"], out.inputs["Surface"])
    attr.location, aov.location, emit.location, out.location = (-300, 0), (0, 150), (0, -100), (250, -100)
    return mat


def relevancy_layer(scene: bpy.types.Scene) -> Optional[bpy.types.ViewLayer]:
    return scene.view_layers.get(LAYER_NAME)


def setup(scene: bpy.types.Scene, enabled: bool) -> Optional[bpy.types.ViewLayer]:
    """Create (``enabled``) or remove the relevancy view layer; returns it."""
    layer = relevancy_layer(scene)
    if not enabled:
        if layer is not None:
            scene.view_layers.remove(layer)
        return None
    if layer is None:
        layer = scene.view_layers.new(LAYER_NAME)
    layer.material_override = relevancy_material()
    if AOV_NAME not in layer.aovs:
        aov = layer.aovs.add()
        aov.name, aov.type = AOV_NAME, "VALUE"
    for other in scene.view_layers:
        other.use_pass_z = other.use_pass_z and other != layer
    update_relevancy(scene, force=True)
    return layer


def wants_mask(scene: bpy.types.Scene, frame: int) -> bool:
    """Whether the mask of ``frame`` is used: the plan lists it, or the keyed desaturation or blur is on there."""
    plan = plan_of(scene) or {}
    return (frames_in_ranges((plan.get("passes") or {}).get("relevancy"), frame)
            or compositor.mask_at(scene, frame) > 0.0)


def update_relevancy(scene: bpy.types.Scene, force: bool = False) -> int:
    """Write the scene timestep's relevancy on every splat point cloud (on frames whose mask is used);
    returns how many objects were written."""
    if relevancy_layer(scene) is None or not (force or wants_mask(scene, scene.frame_current)):
        return 0
    query = (plan_of(scene) or {}).get("query")
    t = int(round(float(scene.fourlegs.timestep)))
    written = 0
    for obj in importer.splat_objects(scene):
        if obj.type != "POINTCLOUD" or (obj.get(SHOWN_KEY) == t and not force):
            continue
        src = importer.engine_scene_for(obj)
        if src is None:
            continue
        t_obj = min(max(t, 0), src.num_timesteps - 1)
        rel = relevancy_store.relevancy_for(scene, obj, src, t_obj, query)
        values = np.zeros(src.num_gaussians, np.float32) if rel is None else np.asarray(rel, np.float32)
        index = importer.kept_indices(obj, src.num_gaussians)
        native_splats.write_relevancy(obj, values if index is None else values[index])
        obj[SHOWN_KEY] = t
        written += 1
    return written


@persistent
def on_frame_change(scene: bpy.types.Scene, depsgraph=None) -> None:
    try:
        update_relevancy(scene)
    except Exception as exc:  # the handler runs on every frame: the render shows no mask, one line says why
        print(f"4-LEGS: the relevancy mask of frame {scene.frame_current} is missing: {exc}")


def register() -> None:
    if on_frame_change not in bpy.app.handlers.frame_change_post:
        bpy.app.handlers.frame_change_post.append(on_frame_change)


def unregister() -> None:
    if on_frame_change in bpy.app.handlers.frame_change_post:
        bpy.app.handlers.frame_change_post.remove(on_frame_change)
