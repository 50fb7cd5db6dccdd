"""The splat object of Blender before 5.3: a vertex-only mesh that geometry nodes turn into points.

The mesh is filled with ``foreach_set`` (hundreds of thousands of points in well under a second); its
geometry-nodes modifier turns vertices into point instances (Mesh to Points, radius from the
``splat_radius`` attribute, Set Material). The material colours points from the ``splat_rgb``
attribute, or from ``splat_relevancy_rgb`` once a query has run. The attribute is not named ``color``:
Cycles renders an attribute of that name black. A scene that marks its foreground (a fitted capture)
also gets the boolean ``splat_foreground`` attribute (e.g. a geometry-nodes selection). Pictures only:
the 4-LEGS Splats render engine rasterizes the Gaussians themselves.
"""
from __future__ import annotations

import bpy
import numpy as np

from . import convert

RGB_ATTR = "splat_rgb"
RELEVANCY_ATTR = "splat_relevancy"
RELEVANCY_RGB_ATTR = "splat_relevancy_rgb"
RADIUS_ATTR = "splat_radius"
OPACITY_ATTR = "splat_opacity"
FOREGROUND_ATTR = "splat_foreground"  # boolean, only when the scene marks its foreground (e.g. a fitted capture)
NODE_GROUP_NAME = "4-LEGS Splats"
MODIFIER_NAME = "4-LEGS Splats"
RADIUS_SIGMAS = 1.5  # instance radius = 1.5 x the geometric-mean standard deviation of the Gaussian
HEAT_TABLE_SIZE = 4096  # heat colours looked up at 1/4095 steps of relevancy: below one 8-bit level apart
_HEAT_TABLE: list[np.ndarray] = []


def rgba(rgb: np.ndarray) -> np.ndarray:
    """(N,3) display (sRGB) colours -> (N,4) scene-linear RGBA for Blender colour attributes."""
    rgb = convert.srgb_to_linear(rgb)
    return np.concatenate([rgb, np.ones((rgb.shape[0], 1), np.float32)], axis=1)


def set_attr(data, name: str, kind: str, field: str, values: np.ndarray) -> None:
    """Write a per-point attribute of a mesh or point cloud, creating it when missing."""
    attr = data.attributes.get(name) or data.attributes.new(name, kind, "POINT")
    attr.data.foreach_set(field, np.ascontiguousarray(values, dtype=np.float32).ravel())


def create_mesh(name: str, gaussians, rgb: np.ndarray) -> bpy.types.Mesh:
    """The vertex-only mesh of ``gaussians`` (a ``GaussianSequence``) at timestep 0, colours ``rgb`` (N,3)."""
    g = gaussians
    mesh = bpy.data.meshes.new(name)
    n = g.num_gaussians
    mesh.vertices.add(n)
    mesh.vertices.foreach_set("co", np.ascontiguousarray(g.means[0], dtype=np.float32).ravel())
    log_scales = np.asarray(g.log_scales if g.log_scales.ndim == 2 else g.log_scales[0], dtype=np.float64)
    radius = RADIUS_SIGMAS * np.exp(np.clip(log_scales.mean(axis=1), -30.0, 10.0))
    set_attr(mesh, RADIUS_ATTR, "FLOAT", "value", radius.astype(np.float32))
    opacity = 1.0 / (1.0 + np.exp(-np.clip(np.asarray(g.opacity_logits, dtype=np.float64), -60, 60)))
    set_attr(mesh, OPACITY_ATTR, "FLOAT", "value", opacity.astype(np.float32))
    if g.foreground is not None:
        mesh.attributes.new(FOREGROUND_ATTR, "BOOLEAN", "POINT").data.foreach_set(
            "value", np.asarray(g.foreground, dtype=bool))
    set_attr(mesh, RGB_ATTR, "FLOAT_COLOR", "color", rgba(rgb))
    set_attr(mesh, RELEVANCY_ATTR, "FLOAT", "value", np.zeros(n, np.float32))
    set_attr(mesh, RELEVANCY_RGB_ATTR, "FLOAT_COLOR", "color", rgba(np.zeros((n, 3), np.float32)))
    mesh.color_attributes.active_color = mesh.color_attributes[RGB_ATTR]
    mesh.update()
    return mesh


def finish_object(obj: bpy.types.Object, name: str) -> None:
    """Give the mesh object its emission material and the Mesh to Points modifier."""
    material = _splat_material(name)
    obj.data.materials.append(material)
    modifier = obj.modifiers.new(MODIFIER_NAME, "NODES")
    modifier.node_group = _splat_node_group(material)


def show_timestep(mesh: bpy.types.Mesh, means: np.ndarray, rgb) -> None:
    """Positions (M,3) and, when given, colours (M,3) of the kept vertices."""
    mesh.attributes["position"].data.foreach_set("vector", np.ascontiguousarray(means, np.float32).ravel())
    if rgb is not None:
        set_attr(mesh, RGB_ATTR, "FLOAT_COLOR", "color", rgba(rgb))


def _splat_material(name: str) -> bpy.types.Material:
    mat = bpy.data.materials.new(f"{name} Splats")
    if mat.node_tree is None:  # Blender < 5.0: node materials are opt-in
        mat.use_nodes = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    nodes.clear()
    attr = nodes.new("ShaderNodeAttribute")
    attr.name = "Splat Colour"
    attr.attribute_type = "GEOMETRY"
    attr.attribute_name = RGB_ATTR
    emit = nodes.new("ShaderNodeEmission")
    out = nodes.new("ShaderNodeOutputMaterial")
    links.new(attr.outputs["Color"], emit.inputs["Color"])
    links.new(emit.outputs["Emission"], out.inputs["Surface"])
    attr.location, emit.location, out.location = (-400, 0), (-150, 0), (100, 0)
    return mat


def _splat_node_group(material: bpy.types.Material) -> bpy.types.NodeTree:
    group = bpy.data.node_groups.new(NODE_GROUP_NAME, "GeometryNodeTree")
    group.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    group.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    nodes, links = group.nodes, group.links
    gin, gout = nodes.new("NodeGroupInput"), nodes.new("NodeGroupOutput")
    radius = nodes.new("GeometryNodeInputNamedAttribute")
    radius.data_type = "FLOAT"
    radius.inputs["Name"].default_value = RADIUS_ATTR
    to_points = nodes.new("GeometryNodeMeshToPoints")
    set_mat = nodes.new("GeometryNodeSetMaterial")
    set_mat.inputs["Material"].default_value = material
    links.new(gin.outputs[0], to_points.inputs["Mesh"])
    links.new(radius.outputs["Attribute"], to_points.inputs["Radius"])
    links.new(to_points.outputs["Points"], set_mat.inputs["Geometry"])
    links.new(set_mat.outputs["Geometry"], gout.inputs[0])
    for i, node in enumerate((gin, radius, to_points, set_mat, gout)):
        node.location = (i * 200 - 400, 0)
    return group


def heat_rgb(values: np.ndarray) -> np.ndarray:
    """(N,) relevancy in [0,1] -> (N,3) blue-to-red heat colours (turbo-like, no matplotlib)."""
    v = np.clip(np.nan_to_num(np.asarray(values, dtype=np.float32)), 0.0, 1.0)[:, None]
    stops = np.array([[0.19, 0.07, 0.23], [0.27, 0.51, 0.96], [0.16, 0.90, 0.62], [0.95, 0.80, 0.16],
                      [0.85, 0.18, 0.02]], np.float32)
    pos = v * (len(stops) - 1)
    lo = np.clip(np.floor(pos).astype(int), 0, len(stops) - 2)
    w = pos - lo
    return stops[lo[:, 0]] * (1 - w) + stops[lo[:, 0] + 1] * w


def heat_rgba(values: np.ndarray) -> np.ndarray:
    """(N,) relevancy -> (N,4) scene-linear RGBA heat colours, i.e. ``rgba(heat_rgb(values))`` read from a
    table of :data:`HEAT_TABLE_SIZE` entries (one lookup per point: it runs on every frame change)."""
    if not _HEAT_TABLE:
        _HEAT_TABLE.append(rgba(heat_rgb(np.linspace(0.0, 1.0, HEAT_TABLE_SIZE))))
    v = np.clip(np.nan_to_num(np.asarray(values, dtype=np.float32)), 0.0, 1.0)
    index = (v * np.float32(HEAT_TABLE_SIZE - 1) + np.float32(0.5)).astype(np.intp)
    return _HEAT_TABLE[0][index]


def write_relevancy(mesh: bpy.types.Mesh, values: np.ndarray) -> None:
    """Per-vertex relevancy (M,) in [0,1] and its heat colours."""
    values = np.clip(np.nan_to_num(np.asarray(values, dtype=np.float32)), 0.0, 1.0)
    set_attr(mesh, RELEVANCY_ATTR, "FLOAT", "value", values)
    set_attr(mesh, RELEVANCY_RGB_ATTR, "FLOAT_COLOR", "color", heat_rgba(values))


def show_relevancy(obj: bpy.types.Object, show: bool) -> None:
    """Switch the viewport/material colouring between the splat colours and the relevancy heat map."""
    name = RELEVANCY_RGB_ATTR if show else RGB_ATTR
    mesh = obj.data
    mesh.color_attributes.active_color = mesh.color_attributes[name]
    for mat in mesh.materials:
        if mat and mat.node_tree and "Splat Colour" in mat.node_tree.nodes:
            mat.node_tree.nodes["Splat Colour"].attribute_name = name
