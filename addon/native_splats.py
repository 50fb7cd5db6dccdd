"""The splat object of Blender 5.3+: a ``GAUSSIAN_SPLAT`` point cloud that EEVEE and Cycles render.

Its attributes follow Blender's own conventions (:mod:`.splat_attributes`); the frame-change handler
rewrites the ones that change over time with ``foreach_set`` from the memory-mapped scene, as the mesh
path does. Every point carries ``fourlegs_index`` (its Gaussian), so points an editor deletes stay
deleted on every frame and in the 4-LEGS render. A static PLY file is imported by Blender's own PLY
importer (its extra properties become attributes, as Blender keeps them).

The per-point relevancy of the highlight (``splat_relevancy``) is written on frames where a relevancy
source exists; the highlight's relevancy view layer reads it through a material (:mod:`.native_render`).
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import bpy
import numpy as np

from . import splat_attributes as sa

MIN_VERSION = (5, 3, 0)
INDEX_ATTR = "fourlegs_index"
RELEVANCY_ATTR = "splat_relevancy"
HEAT_MATERIAL = "4-LEGS Relevancy Heat"
#: attribute data type -> the ``foreach_set`` field Blender names its values
FIELDS = {"FLOAT": "value", "FLOAT_VECTOR": "vector", "FLOAT4": "vector", "QUATERNION": "value", "INT": "value"}


def available() -> bool:
    """Whether this Blender renders Gaussian splats natively (``PointCloud.type == 'GAUSSIAN_SPLAT'``)."""
    return bpy.app.version >= MIN_VERSION


def write_attribute(data, name: str, kind: str, values: np.ndarray) -> None:
    """Write a per-point attribute (created when missing) with ``foreach_set``."""
    attr = data.attributes.get(name)
    if attr is None or attr.data_type != kind:
        if attr is not None:
            data.attributes.remove(attr)
        attr = data.attributes.new(name, kind, "POINT")
    dtype = np.int32 if kind == "INT" else np.float32
    attr.data.foreach_set(FIELDS[kind], np.ascontiguousarray(values, dtype=dtype).ravel())


def read_attribute(data, name: str) -> Optional[np.ndarray]:
    """(M, values per point) of a float/int attribute, or None when there is none."""
    attr = data.attributes.get(name)
    if attr is None or attr.data_type not in FIELDS:
        return None
    width = {"FLOAT": 1, "INT": 1, "FLOAT_VECTOR": 3, "FLOAT4": 4, "QUATERNION": 4}[attr.data_type]
    out = np.empty(len(attr.data) * width, np.int32 if attr.data_type == "INT" else np.float32)
    attr.data.foreach_get(FIELDS[attr.data_type], out)
    return out.reshape(len(attr.data), width)


def frame_attributes(gaussians, t: float, index: Optional[np.ndarray] = None, *,
                     only_changing: bool = False) -> dict[str, np.ndarray]:
    """Blender's splat attributes of ``gaussians`` at scene time ``t`` (fractional: positions and colours
    interpolate linearly, rotations and scales are those of the nearest timestep), for the Gaussians
    ``index`` (None: all). ``only_changing``: leave out what does not change over time."""
    g = gaussians
    T = g.num_timesteps
    t = min(max(float(t), 0.0), float(T - 1))
    ti = int(round(t))
    pick = (lambda a: a) if index is None else (lambda a: a[index])
    means = pick(sa.blend_timestep(g.means, t))
    rotations = pick(np.asarray(g.rotations[ti], np.float32))
    log_scales = pick(np.asarray(g.log_scales[ti] if g.log_scales.ndim == 3 else g.log_scales, np.float32))
    opacity = pick(np.asarray(g.opacity_logits, np.float32))
    if g.sh is not None:
        sh = pick(np.asarray(g.sh[ti] if g.sh.ndim == 4 else g.sh, np.float32))
        attrs = sa.splat_attributes(means, rotations, log_scales, opacity, sh=sh)
        colours_change = g.sh.ndim == 4
    else:
        colors = sa.blend_timestep(g.colors, t) if g.colors.ndim == 3 else np.asarray(g.colors, np.float32)
        attrs = sa.splat_attributes(means, rotations, log_scales, opacity, colors=pick(colors))
        colours_change = g.colors.ndim == 3
    if only_changing:
        keep = {sa.POSITION, sa.ROTATION}
        if g.log_scales.ndim == 3:
            keep.add(sa.SCALE)
        if colours_change:
            keep |= {n for n in attrs if n == sa.BASE or n.startswith(sa.SH_PREFIX)}
        attrs = {n: v for n, v in attrs.items() if n in keep}
    return attrs


def create_object(name: str, gaussians) -> bpy.types.Object:
    """A new ``GAUSSIAN_SPLAT`` point-cloud object showing ``gaussians`` at timestep 0 (not linked)."""
    pc = bpy.data.pointclouds.new(name)
    pc.type = "GAUSSIAN_SPLAT"
    pc.resize(gaussians.num_gaussians)
    for attr_name, values in frame_attributes(gaussians, 0.0).items():
        write_attribute(pc, attr_name, sa.kind_of(attr_name)[0], values)
    write_attribute(pc, INDEX_ATTR, "INT", np.arange(gaussians.num_gaussians, dtype=np.int32))
    return bpy.data.objects.new(name, pc)


def import_ply_file(path: Path, name: str) -> bpy.types.Object:
    """A static Inria PLY through Blender's own importer (extra properties kept as attributes); the object
    is unlinked from wherever the importer put it, for the caller to link."""
    before = set(bpy.data.objects)
    result = bpy.ops.wm.ply_import(filepath=str(path))
    made = [o for o in bpy.data.objects if o not in before and o.type == "POINTCLOUD"]
    if "FINISHED" not in result or len(made) != 1:
        raise RuntimeError(f"{path}: Blender's PLY importer did not make one point cloud ({result})")
    obj = made[0]
    for collection in list(obj.users_collection):
        collection.objects.unlink(obj)
    obj.name = obj.data.name = name
    if obj.data.type != "GAUSSIAN_SPLAT":
        raise RuntimeError(f"{path}: Blender did not read it as Gaussian splats (no opacity/scale/rot properties?)")
    write_attribute(obj.data, INDEX_ATTR, "INT", np.arange(len(obj.data.points), dtype=np.int32))
    return obj


def kept_indices(obj: bpy.types.Object, num_gaussians: int) -> Optional[np.ndarray]:
    """(M,) the Gaussians the object's points still show (after deletions), or None when all, in order."""
    values = read_attribute(obj.data, INDEX_ATTR)
    if values is None:
        return None if len(obj.data.points) == num_gaussians else np.arange(len(obj.data.points))
    index = values[:, 0].astype(np.int64)
    if len(index) == num_gaussians and np.array_equal(index, np.arange(num_gaussians)):
        return None
    return np.clip(index, 0, num_gaussians - 1)


def show_timestep(obj: bpy.types.Object, gaussians, t: float, index: Optional[np.ndarray]) -> None:
    """Rewrite the attributes that change over time for scene time ``t``."""
    pc = obj.data
    for attr_name, values in frame_attributes(gaussians, t, index, only_changing=True).items():
        write_attribute(pc, attr_name, sa.kind_of(attr_name)[0], values)
    pc.update_tag()


def write_relevancy(obj: bpy.types.Object, values: np.ndarray) -> None:
    """Per-point relevancy (M,) in [0,1] (the kept points' Gaussians)."""
    values = np.clip(np.nan_to_num(np.asarray(values, dtype=np.float32)), 0.0, 1.0)
    write_attribute(obj.data, RELEVANCY_ATTR, "FLOAT", values)
    obj.data.update_tag()


def _heat_material() -> bpy.types.Material:
    """Emission from the relevancy attribute through a blue-to-red ramp (the viewport's Show Relevancy)."""
    mat = bpy.data.materials.get(HEAT_MATERIAL)
    if mat is not None:
        return mat
    mat = bpy.data.materials.new(HEAT_MATERIAL)
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    nodes.clear()
    attr = nodes.new("ShaderNodeAttribute")
    attr.attribute_type, attr.attribute_name = "GEOMETRY", RELEVANCY_ATTR
    ramp = nodes.new("ShaderNodeValToRGB")
    ramp.color_ramp.elements[0].color = (0.03, 0.01, 0.05, 1.0)
    ramp.color_ramp.elements[1].color = (0.7, 0.03, 0.0, 1.0)
    emit, out = nodes.new("ShaderNodeEmission"), nodes.new("ShaderNodeOutputMaterial")
    links.new(attr.outputs["Fac"], ramp.inputs["Fac"])
    links.new(ramp.outputs["Color"], emit.inputs["Color"])
    links.new(emit.outputs["Emission"], out.inputs["Surface"])
    return mat


def show_relevancy(obj: bpy.types.Object, show: bool) -> None:
    """Colour the splats by relevancy (a heat material), or by their own radiance (no material)."""
    materials = obj.data.materials
    materials.clear()
    if show:
        materials.append(_heat_material())
