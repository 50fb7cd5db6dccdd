"""4D Gaussian scene -> one Blender point-cloud object (+ the scene's cameras).

The object is a vertex-only mesh filled with ``foreach_set`` (hundreds of thousands of points in well
under a second) whose geometry-nodes modifier turns vertices into point instances (Mesh to Points,
radius from the ``splat_radius`` attribute, Set Material). The material colours points from the
``splat_rgb`` attribute, or from ``splat_relevancy_rgb`` once a query has run. The attribute is not
named ``color``: Cycles renders an attribute of that name black. A scene that marks its foreground (a
fitted capture) also gets the boolean ``splat_foreground`` attribute (e.g. a geometry-nodes selection).

Time: the mesh shows the scene timestep ``scene.fourlegs.timestep`` (fractional values interpolate
linearly between neighbouring timesteps); a persistent frame-change handler updates positions and
colours with ``foreach_set`` whenever the timeline moves. The Gaussians themselves stay on disk
(memory-mapped) in a per-file cache, re-opened lazily from the object's ``fourlegs_source`` path after
a .blend is reloaded; timesteps the handler has read are unmapped again every 32 MB, so scrubbing a long
scene does not keep it all resident.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Optional

import bpy
import numpy as np
from bpy.app.handlers import persistent

from . import convert

SOURCE_KEY = "fourlegs_source"
RGB_ATTR = "splat_rgb"
RELEVANCY_ATTR = "splat_relevancy"
RELEVANCY_RGB_ATTR = "splat_relevancy_rgb"
RADIUS_ATTR = "splat_radius"
OPACITY_ATTR = "splat_opacity"
FOREGROUND_ATTR = "splat_foreground"  # boolean, only when the scene marks its foreground (e.g. a fitted capture)
NODE_GROUP_NAME = "4-LEGS Splats"
MODIFIER_NAME = "4-LEGS Splats"
CAMERA_COLLECTION_SUFFIX = " Cameras"
RADIUS_SIGMAS = 1.5  # instance radius = 1.5 x the geometric-mean standard deviation of the Gaussian
# Calibrated cameras have fx and fy a fraction of a percent apart; Blender cannot write a multilayer EXR with
# non-square pixels, so such cameras get square pixels and the geometric-mean focal length.
SQUARE_PIXEL_TOLERANCE = 0.01
RELEASE_EVERY_BYTES = 1 << 25  # the frame-change handler unmaps the timesteps it read every 32 MB

# source key -> Scene (engine object, arrays memory-mapped); relevancy per source: (N,) or (T,N)
_SCENES: dict[str, Any] = {}
_RELEVANCY: dict[str, np.ndarray] = {}
# source key -> the one-line message of why it cannot be opened (reported once, shown in the panel)
_MISSING: dict[str, str] = {}
# source key -> callable(t: int) -> (N,) relevancy, evaluated lazily per timestep and cached
_RELEVANCY_PROVIDERS: dict[str, Any] = {}
_RELEVANCY_CACHE: dict[tuple[str, int], np.ndarray] = {}
# source key -> bytes of memory-mapped timesteps read since they were last unmapped
_BYTES_READ: dict[Optional[str], int] = {}


# ----------------------------------------------------------------------------- engine-side data
def load_engine_scene(path: str | Path):
    """Open a scene with the engine's loaders (bundle, params.npz dir, PLY file or PLY directory)."""
    from fourlegs_engine import api

    return api.load_scene(Path(bpy.path.abspath(str(path))))


def stored_path(path: str | Path) -> str:
    """How a scene path is stored on the object: relative to the .blend (``//...``) once it is saved, so
    the project can move; absolute before (a new file has no folder yet)."""
    path = str(Path(path).resolve())
    if bpy.data.filepath:
        try:
            return bpy.path.relpath(path)
        except ValueError:  # another drive (Windows)
            return path
    return path


def relative_sources(blend_dir: str | Path) -> None:
    """Store every splat object's scene path relative to ``blend_dir`` (``//...``), for a .blend about to
    be saved there (a file that is not saved yet has no ``//``)."""
    for obj in bpy.data.objects:
        key = source_key(obj)
        if not key or key.startswith(("memory:", "//")):
            continue
        try:
            rel = bpy.path.relpath(key, start=str(blend_dir))
        except ValueError:  # another drive (Windows)
            continue
        if key in _SCENES:
            _SCENES[rel] = _SCENES[key]
        obj[SOURCE_KEY] = rel


def missing_message(obj: bpy.types.Object) -> str:
    """Why the object's scene could not be opened (empty when it could)."""
    return _MISSING.get(source_key(obj) or "", "")


def source_key(obj: bpy.types.Object) -> Optional[str]:
    key = obj.get(SOURCE_KEY)
    return str(key) if key else None


def engine_scene_for(obj: bpy.types.Object):
    """The engine ``Scene`` behind an imported object (re-opened from its path when not cached)."""
    key = source_key(obj)
    if key is None:
        return None
    scene = _SCENES.get(key)
    if scene is None and not key.startswith("memory:"):
        scene = load_engine_scene(key)
        _SCENES[key] = scene
    return scene


def adopt_scene(obj: bpy.types.Object, scene: Any, source: str) -> None:
    """Point ``obj`` at ``scene`` loaded from ``source`` (e.g. the bundle its PLY was converted into)."""
    key = stored_path(source)
    _SCENES[key] = scene
    _MISSING.pop(key, None)
    obj[SOURCE_KEY] = key


def splat_objects(scene: bpy.types.Scene) -> list[bpy.types.Object]:
    return [o for o in scene.objects if o.type == "MESH" and source_key(o)]


# ----------------------------------------------------------------------------- import
def import_scene(context_scene: bpy.types.Scene, scene: Any, *, source: str | None = None,
                 name: str | None = None, with_cameras: bool = True) -> bpy.types.Object:
    """Create the point-cloud object (and cameras) of an engine ``Scene`` in ``context_scene``.

    Args:
        context_scene: the Blender scene to link into.
        scene: a ``fourlegs_engine.scene.Scene``.
        source: the path it was loaded from (stored on the object so a saved .blend re-opens it);
            None for an in-memory scene (kept in this session's cache only).
        name: object name (default: the scene name).
    Returns:
        The new mesh object; it is also ``context_scene.fourlegs.splat_object``.
    """
    g = scene.gaussians
    name = name or scene.name or "4-LEGS scene"
    key = stored_path(source) if source else f"memory:{name}:{id(scene)}"
    _SCENES[key] = scene

    collection = bpy.data.collections.new(f"4-LEGS {name}")
    context_scene.collection.children.link(collection)
    mesh = bpy.data.meshes.new(name)
    n = g.num_gaussians
    mesh.vertices.add(n)
    mesh.vertices.foreach_set("co", np.ascontiguousarray(g.means[0], dtype=np.float32).ravel())
    log_scales = np.asarray(g.log_scales if g.log_scales.ndim == 2 else g.log_scales[0], dtype=np.float64)
    radius = RADIUS_SIGMAS * np.exp(np.clip(log_scales.mean(axis=1), -30.0, 10.0))
    _set_attr(mesh, RADIUS_ATTR, "FLOAT", "value", radius.astype(np.float32))
    opacity = 1.0 / (1.0 + np.exp(-np.clip(np.asarray(g.opacity_logits, dtype=np.float64), -60, 60)))
    _set_attr(mesh, OPACITY_ATTR, "FLOAT", "value", opacity.astype(np.float32))
    if g.foreground is not None:
        mesh.attributes.new(FOREGROUND_ATTR, "BOOLEAN", "POINT").data.foreach_set(
            "value", np.asarray(g.foreground, dtype=bool))
    _set_attr(mesh, RGB_ATTR, "FLOAT_COLOR", "color", _rgba(g.rgb(0)))
    _set_attr(mesh, RELEVANCY_ATTR, "FLOAT", "value", np.zeros(n, np.float32))
    _set_attr(mesh, RELEVANCY_RGB_ATTR, "FLOAT_COLOR", "color", _rgba(np.zeros((n, 3), np.float32)))
    mesh.color_attributes.active_color = mesh.color_attributes[RGB_ATTR]
    mesh.update()

    obj = bpy.data.objects.new(name, mesh)
    obj[SOURCE_KEY] = key
    obj["fourlegs_num_timesteps"] = g.num_timesteps
    obj["fourlegs_shown_timestep"] = 0.0
    collection.objects.link(obj)
    material = _splat_material(name)
    mesh.materials.append(material)
    modifier = obj.modifiers.new(MODIFIER_NAME, "NODES")
    modifier.node_group = _splat_node_group(material)

    props = context_scene.fourlegs
    props.splat_object = obj
    props.num_timesteps = g.num_timesteps
    if source:
        props.source_path = str(source)
    if with_cameras:
        import_cameras(context_scene, scene, collection)
    context_scene.frame_start = 1
    context_scene.frame_end = max(1, g.num_timesteps)
    context_scene.render.fps = max(1, int(round(scene.fps)))
    _key_capture_playback(context_scene, g.num_timesteps)
    use_standard_view(context_scene)
    update_object(obj, float(props.timestep))
    return obj


def _key_capture_playback(context_scene: bpy.types.Scene, num_timesteps: int) -> None:
    """Key the scene time so the timeline plays the capture (frame f shows timestep f - 1), unless the
    scene time is animated already (a highlight's keys, an editor's own, or an earlier import)."""
    from . import keyframes

    if num_timesteps < 2 or keyframes.find_fcurve(context_scene, keyframes.TIMESTEP_PATH) is not None:
        return
    action = keyframes.ensure_action(context_scene, "Scene Time")
    keyframes.write_fcurve(context_scene, action, keyframes.TIMESTEP_PATH, 0, [1, num_timesteps],
                           [0.0, num_timesteps - 1.0], ["LINEAR"] * 2)


def _rgba(rgb: np.ndarray) -> np.ndarray:
    """(N,3) display (sRGB) colours -> (N,4) scene-linear RGBA for Blender colour attributes."""
    rgb = convert.srgb_to_linear(rgb)
    return np.concatenate([rgb, np.ones((rgb.shape[0], 1), np.float32)], axis=1)


def _set_attr(mesh: bpy.types.Mesh, name: str, kind: str, field: str, values: np.ndarray) -> None:
    attr = mesh.attributes.get(name) or mesh.attributes.new(name, kind, "POINT")
    attr.data.foreach_set(field, np.ascontiguousarray(values, dtype=np.float32).ravel())


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


def use_standard_view(bl_scene: bpy.types.Scene) -> None:
    """Standard view transform, no look: output pixels reproduce the Gaussians' colours (no AgX tone map)."""
    bl_scene.view_settings.view_transform = "Standard"
    bl_scene.view_settings.look = "None"
    bl_scene.view_settings.exposure = 0.0
    bl_scene.view_settings.gamma = 1.0


# ----------------------------------------------------------------------------- cameras
def apply_camera(cam_obj: bpy.types.Object, c2w_opencv: np.ndarray, K: np.ndarray, width: int,
                 height: int, near: float = 0.01, far: float = 100.0) -> None:
    """Place a Blender camera object to match an OpenCV camera."""
    from mathutils import Matrix

    cam_obj.matrix_world = Matrix(convert.opencv_to_blender_c2w(c2w_opencv).tolist())
    lens = convert.intrinsics_to_blender(K, width, height)
    data = cam_obj.data
    data.sensor_fit = "HORIZONTAL"
    data.sensor_width = lens.sensor_width_mm
    data.lens = lens.lens_mm
    data.shift_x, data.shift_y = lens.shift_x, lens.shift_y
    data.clip_start, data.clip_end = near, far


def near_square_pixels(K: np.ndarray, tolerance: float = SQUARE_PIXEL_TOLERANCE) -> np.ndarray:
    """(3,3) ``K`` with fx = fy = sqrt(fx*fy) when they differ by at most ``tolerance`` (relative), else ``K``."""
    K = np.asarray(K, dtype=np.float64)
    fx, fy = K[0, 0], K[1, 1]
    if fx <= 0 or fy <= 0 or abs(fx / fy - 1.0) > tolerance:
        return K
    out = K.copy()
    out[0, 0] = out[1, 1] = math.sqrt(fx * fy)
    return out


def import_cameras(context_scene: bpy.types.Scene, scene: Any, collection: bpy.types.Collection) -> list:
    """The scene's cameras at timestep 0 (train, then test) as Blender cameras in a child collection.

    The render's pixel aspect is the first camera's (one value per Blender scene); nearly square pixels
    become square (:func:`near_square_pixels`)."""
    cams = scene.cameras.cameras(0, "all") if scene.cameras.num_timesteps else []
    if not cams:
        return []
    sub = bpy.data.collections.new(collection.name + CAMERA_COLLECTION_SUFFIX)
    collection.children.link(sub)
    out = []
    for i, cam in enumerate(cams):
        data = bpy.data.cameras.new(cam.name or f"cam{i:02d}")
        obj = bpy.data.objects.new(cam.name or f"cam{i:02d}", data)
        obj["fourlegs_camera"] = cam.name or f"cam{i:02d}"
        sub.objects.link(obj)
        apply_camera(obj, cam.c2w, near_square_pixels(cam.K), cam.width, cam.height, cam.near, min(cam.far, 1000.0))
        out.append(obj)
    render = context_scene.render
    render.resolution_x, render.resolution_y = cams[0].width, cams[0].height
    render.resolution_percentage = 100
    lens = convert.intrinsics_to_blender(near_square_pixels(cams[0].K), cams[0].width, cams[0].height)
    render.pixel_aspect_x, render.pixel_aspect_y = lens.pixel_aspect_x, lens.pixel_aspect_y
    if context_scene.camera is None:
        context_scene.camera = out[0]
    return out


# ----------------------------------------------------------------------------- time + relevancy
def blend_timestep(arr: Any, t: float) -> np.ndarray:
    """Row ``t`` of a (T,N,C) array, linearly interpolated for fractional ``t`` (clamped to the range)."""
    T = arr.shape[0]
    t = min(max(float(t), 0.0), float(T - 1))
    lo = int(math.floor(t))
    hi = min(lo + 1, T - 1)
    w = t - lo
    a = np.asarray(arr[lo], dtype=np.float32)
    if w < 1e-6 or hi == lo:
        return a
    return (1.0 - w) * a + w * np.asarray(arr[hi], dtype=np.float32)


def update_object(obj: bpy.types.Object, t: float) -> bool:
    """Show timestep ``t`` on ``obj`` (positions, colours, relevancy). Returns False if unchanged."""
    scene = engine_scene_for(obj)
    if scene is None:
        return False
    g = scene.gaussians
    t = min(max(float(t), 0.0), float(g.num_timesteps - 1))
    if abs(float(obj.get("fourlegs_shown_timestep", -1.0)) - t) < 1e-6:
        return False
    mesh = obj.data
    if len(mesh.vertices) != g.num_gaussians:
        return False
    mesh.attributes["position"].data.foreach_set("vector", blend_timestep(g.means, t).ravel())
    if g.colors is not None and g.colors.ndim == 3:
        _set_attr(mesh, RGB_ATTR, "FLOAT_COLOR", "color", _rgba(blend_timestep(g.colors, t)))
    release_after_reading(source_key(obj), (g.means, g.colors), 2 if t != int(t) else 1)
    rel = _RELEVANCY.get(source_key(obj))
    if rel is not None and rel.ndim == 2:
        _write_relevancy(mesh, blend_timestep(rel[:, :, None], t)[:, 0])
    mesh.update()
    obj["fourlegs_shown_timestep"] = t
    return True


def release_after_reading(key: Optional[str], arrays: tuple, rows: int) -> None:
    """Count the bytes of ``rows`` timesteps read from ``arrays`` (memory-mapped (T,N,k) arrays of one
    scene; others are skipped); every :data:`RELEASE_EVERY_BYTES` unmap them, so scrubbing or rendering a
    long scene does not keep every timestep resident (the pages stay in the OS file cache)."""
    from fourlegs_engine import api

    per_timestep = [a for a in arrays if a is not None and a.ndim == 3]
    _BYTES_READ[key] = _BYTES_READ.get(key, 0) + rows * sum(a[0].nbytes for a in per_timestep)
    if _BYTES_READ[key] >= RELEASE_EVERY_BYTES:
        _BYTES_READ[key] = 0
        for arr in per_timestep:
            api.release_mapped_pages(arr)


def update_scene_objects(scene: bpy.types.Scene) -> None:
    """Show the scene time on every splat object; a scene that cannot be opened is reported once (console
    line, panel) and skipped on later frames."""
    props = getattr(scene, "fourlegs", None)
    if props is None:
        return
    for obj in splat_objects(scene):
        key = source_key(obj)
        if key in _MISSING:
            continue
        try:
            update_object(obj, float(props.timestep))
        except Exception as exc:  # the handler runs on every frame: one line, once
            _MISSING[key] = f"{obj.name}: scene {key} cannot be opened: {exc}"
            print(f"4-LEGS: {_MISSING[key]}")


@persistent
def on_frame_change(scene: bpy.types.Scene, depsgraph=None) -> None:
    update_scene_objects(scene)


def heat_rgb(values: np.ndarray) -> np.ndarray:
    """(N,) relevancy in [0,1] -> (N,3) blue-to-red heat colours (turbo-like, no matplotlib)."""
    v = np.clip(np.nan_to_num(np.asarray(values, dtype=np.float32)), 0.0, 1.0)[:, None]
    stops = np.array([[0.19, 0.07, 0.23], [0.27, 0.51, 0.96], [0.16, 0.90, 0.62], [0.95, 0.80, 0.16],
                      [0.85, 0.18, 0.02]], np.float32)
    pos = v * (len(stops) - 1)
    lo = np.clip(np.floor(pos).astype(int), 0, len(stops) - 2)
    w = pos - lo
    return stops[lo[:, 0]] * (1 - w) + stops[lo[:, 0] + 1] * w


HEAT_TABLE_SIZE = 4096  # heat colours looked up at 1/4095 steps of relevancy: below one 8-bit level apart
_HEAT_TABLE: list[np.ndarray] = []


def heat_rgba(values: np.ndarray) -> np.ndarray:
    """(N,) relevancy -> (N,4) scene-linear RGBA heat colours, i.e. ``_rgba(heat_rgb(values))`` read from a
    table of :data:`HEAT_TABLE_SIZE` entries (one lookup per point: it runs on every frame change)."""
    if not _HEAT_TABLE:
        _HEAT_TABLE.append(_rgba(heat_rgb(np.linspace(0.0, 1.0, HEAT_TABLE_SIZE))))
    v = np.clip(np.nan_to_num(np.asarray(values, dtype=np.float32)), 0.0, 1.0)
    index = (v * np.float32(HEAT_TABLE_SIZE - 1) + np.float32(0.5)).astype(np.intp)
    return _HEAT_TABLE[0][index]


def _write_relevancy(mesh: bpy.types.Mesh, values: np.ndarray) -> None:
    values = np.clip(np.nan_to_num(np.asarray(values, dtype=np.float32)), 0.0, 1.0)
    _set_attr(mesh, RELEVANCY_ATTR, "FLOAT", "value", values)
    _set_attr(mesh, RELEVANCY_RGB_ATTR, "FLOAT_COLOR", "color", heat_rgba(values))


def set_relevancy(obj: bpy.types.Object, relevancy: np.ndarray, *, show: bool = True) -> None:
    """Store per-Gaussian relevancy ((N,) or (T,N) in [0,1]) and colour the viewport with it."""
    rel = np.asarray(relevancy, dtype=np.float32)
    n = len(obj.data.vertices)
    if rel.shape[-1] != n or rel.ndim not in (1, 2):
        raise ValueError(f"relevancy has shape {rel.shape}, expected ({n},) or (T,{n})")
    _RELEVANCY[source_key(obj)] = rel
    shown = float(obj.get("fourlegs_shown_timestep", 0.0))
    _write_relevancy(obj.data, rel if rel.ndim == 1 else blend_timestep(rel[:, :, None], shown)[:, 0])
    show_relevancy(obj, show)
    obj.data.update()


def set_relevancy_provider(obj: bpy.types.Object, provider: Any) -> None:
    """Register ``provider(t: int) -> (N,)`` computing per-Gaussian relevancy of timestep t on demand.

    The render engine asks only for timesteps of frames the plan lists; results are cached.
    """
    key = source_key(obj)
    _RELEVANCY_PROVIDERS[key] = provider
    for k in [k for k in _RELEVANCY_CACHE if k[0] == key]:
        del _RELEVANCY_CACHE[k]


def gaussian_relevancy(obj: bpy.types.Object, t: int) -> Optional[np.ndarray]:
    """(N,) relevancy of timestep ``t``: from the provider, else the stored (T,N)/(N,) array, else None."""
    key = source_key(obj)
    provider = _RELEVANCY_PROVIDERS.get(key)
    if provider is not None:
        if (key, t) not in _RELEVANCY_CACHE:
            values = np.asarray(provider(int(t)), dtype=np.float32).reshape(-1)
            _RELEVANCY_CACHE[(key, t)] = np.clip(np.nan_to_num(values), 0.0, 1.0)
        return _RELEVANCY_CACHE[(key, t)]
    rel = _RELEVANCY.get(key)
    if rel is None:
        return None
    return rel[min(max(int(t), 0), rel.shape[0] - 1)] if rel.ndim == 2 else rel


def show_relevancy(obj: bpy.types.Object, show: bool) -> None:
    """Switch the viewport/material colouring between the splat colours and the relevancy heat map."""
    name = RELEVANCY_RGB_ATTR if show else RGB_ATTR
    mesh = obj.data
    mesh.color_attributes.active_color = mesh.color_attributes[name]
    for mat in mesh.materials:
        if mat and mat.node_tree and "Splat Colour" in mat.node_tree.nodes:
            mat.node_tree.nodes["Splat Colour"].attribute_name = name


def register() -> None:
    if on_frame_change not in bpy.app.handlers.frame_change_post:
        bpy.app.handlers.frame_change_post.append(on_frame_change)


def unregister() -> None:
    if on_frame_change in bpy.app.handlers.frame_change_post:
        bpy.app.handlers.frame_change_post.remove(on_frame_change)
