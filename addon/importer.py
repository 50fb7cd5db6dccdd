"""4D Gaussian scene -> one Blender splat object (+ the scene's cameras), shown at the scene time.

Blender 5.3+ renders Gaussian splats itself: the object is a ``GAUSSIAN_SPLAT`` point cloud with Blender's
own attributes (:mod:`.native_splats`). Older Blender gets a vertex-only mesh drawn as points
(:mod:`.mesh_splats`), which the 4-LEGS Splats render engine rasterizes. Every point carries
``fourlegs_index``, the Gaussian it shows, so points an editor deletes stay deleted on every frame.

Time: the object shows the scene timestep ``scene.fourlegs.timestep`` (fractional values interpolate
linearly between neighbouring timesteps); a persistent frame-change handler updates positions and
colours with ``foreach_set`` whenever the timeline moves. The Gaussians themselves stay on disk
(memory-mapped) in a per-file cache, re-opened lazily from the object's ``fourlegs_source`` path after
a .blend is reloaded; timesteps the handler has read are unmapped again every 32 MB, so scrubbing a long
scene does not keep it all resident.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import bpy
import numpy as np
from bpy.app.handlers import persistent

from . import mesh_splats, native_splats
from .mesh_splats import (FOREGROUND_ATTR, MODIFIER_NAME, OPACITY_ATTR, RADIUS_ATTR, RELEVANCY_ATTR,  # noqa: F401
                          RELEVANCY_RGB_ATTR, RGB_ATTR, heat_rgb, heat_rgba)
from .scene_cameras import add_view_camera, apply_camera, import_cameras  # noqa: F401
from .splat_attributes import blend_timestep

SOURCE_KEY = "fourlegs_source"
INDEX_ATTR = native_splats.INDEX_ATTR
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
    """Store every path the file holds relative to ``blend_dir`` (``//...``), for a .blend about to be saved
    there: the splat objects' scenes and each scene's video output, so the project folder can move (a
    file that is not saved yet has no ``//``)."""
    for obj in bpy.data.objects:
        key = source_key(obj)
        if not key or key.startswith(("memory:", "//")):
            continue
        rel = _relative(key, blend_dir)
        if rel != key and key in _SCENES:
            _SCENES[rel] = _SCENES[key]
        obj[SOURCE_KEY] = rel
    for bl_scene in bpy.data.scenes:
        props = getattr(bl_scene, "fourlegs", None)
        if props is not None and props.output_path:
            props.output_path = _relative(props.output_path, blend_dir)
        if bl_scene.render.filepath:
            bl_scene.render.filepath = _relative(bl_scene.render.filepath, blend_dir)


def _relative(path: str, blend_dir: str | Path) -> str:
    """``path`` as ``//...`` relative to ``blend_dir`` (already relative or on another drive: unchanged)."""
    if path.startswith("//"):
        return path
    try:
        return bpy.path.relpath(str(Path(path).resolve()), start=str(blend_dir))
    except ValueError:  # another drive (Windows)
        return path


def relink(obj: bpy.types.Object, path: str | Path) -> Any:
    """Point ``obj`` at the scene at ``path`` (a moved bundle or PLY), checking it holds as many Gaussians
    as the object was made from; returns the engine scene."""
    scene = load_engine_scene(path)
    expected = int(obj.get("fourlegs_num_gaussians", scene.num_gaussians))
    if scene.num_gaussians != expected:
        raise ValueError(f"{path}: holds {scene.num_gaussians} Gaussians, the object was made from {expected}")
    old = source_key(obj)
    adopt_scene(obj, scene, str(Path(bpy.path.abspath(str(path))).resolve()))
    _MISSING.pop(old or "", None)
    obj["fourlegs_shown_timestep"] = -1.0  # show the scene time again from the relinked scene
    return scene


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
    """The scene's imported splat objects (meshes before Blender 5.3, Gaussian-splat point clouds after)."""
    return [o for o in scene.objects if o.type in ("MESH", "POINTCLOUD") and source_key(o)]


# ----------------------------------------------------------------------------- import
def import_scene(context_scene: bpy.types.Scene, scene: Any, *, source: str | None = None,
                 name: str | None = None, with_cameras: bool = True,
                 ply_file: Optional[Path] = None) -> bpy.types.Object:
    """Create the splat object (and cameras) of an engine ``Scene`` in ``context_scene``.

    Args:
        context_scene: the Blender scene to link into.
        scene: a ``fourlegs_engine.scene.Scene``.
        source: the path it was loaded from (stored on the object so a saved .blend re-opens it);
            None for an in-memory scene (kept in this session's cache only).
        name: object name (default: the scene name).
        ply_file: the one static PLY file the scene was read from: on Blender 5.3+ Blender's own PLY
            importer reads it.
    Returns:
        The new object; it is also ``context_scene.fourlegs.splat_object``. A scene without cameras
        gets a view camera.
    """
    g = scene.gaussians
    name = name or scene.name or "4-LEGS scene"
    key = stored_path(source) if source else f"memory:{name}:{id(scene)}"
    _SCENES[key] = scene

    collection = bpy.data.collections.new(f"4-LEGS {name}")
    context_scene.collection.children.link(collection)
    if native_splats.available():
        obj = (native_splats.import_ply_file(ply_file, name) if ply_file is not None
               else native_splats.create_object(name, g))
    else:
        obj = bpy.data.objects.new(name, mesh_splats.create_mesh(name, g, g.rgb(0)))
        native_splats.write_attribute(obj.data, INDEX_ATTR, "INT", np.arange(g.num_gaussians, dtype=np.int32))
        mesh_splats.finish_object(obj, name)
    obj[SOURCE_KEY] = key
    obj["fourlegs_num_timesteps"] = g.num_timesteps
    obj["fourlegs_num_gaussians"] = g.num_gaussians
    obj["fourlegs_shown_timestep"] = 0.0
    collection.objects.link(obj)

    props = context_scene.fourlegs
    props.splat_object = obj
    props.num_timesteps = g.num_timesteps
    if source:
        props.source_path = stored_path(source)
    cameras = import_cameras(context_scene, scene, collection) if with_cameras else []
    if not cameras and context_scene.camera is None:
        add_view_camera(context_scene, g.means[0], collection)
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


def use_standard_view(bl_scene: bpy.types.Scene) -> None:
    """Standard view transform, no look: output pixels reproduce the Gaussians' colours (no AgX tone map)."""
    bl_scene.view_settings.view_transform = "Standard"
    bl_scene.view_settings.look = "None"
    bl_scene.view_settings.exposure = 0.0
    bl_scene.view_settings.gamma = 1.0


# ----------------------------------------------------------------------------- time + relevancy
def kept_indices(obj: bpy.types.Object, num_gaussians: int) -> Optional[np.ndarray]:
    """(M,) the Gaussians the object's points still show after deletions, in point order; None when
    every Gaussian is there in order."""
    if obj.type == "POINTCLOUD":
        return native_splats.kept_indices(obj, num_gaussians)
    values = native_splats.read_attribute(obj.data, INDEX_ATTR)
    if values is None:
        return None if len(obj.data.vertices) == num_gaussians else np.arange(len(obj.data.vertices))
    index = values[:, 0].astype(np.int64)
    if len(index) == num_gaussians and np.array_equal(index, np.arange(num_gaussians)):
        return None
    return np.clip(index, 0, num_gaussians - 1)


def visible_indices(obj: bpy.types.Object, num_gaussians: int) -> Optional[np.ndarray]:
    """(M,) the Gaussians a render shows: the kept ones less the vertices hidden in edit mode (meshes);
    None when that is every Gaussian in order."""
    index = kept_indices(obj, num_gaussians)
    if obj.type != "MESH" or not len(obj.data.vertices):
        return index
    hidden = np.zeros(len(obj.data.vertices), bool)
    obj.data.vertices.foreach_get("hide", hidden)
    if not hidden.any():
        return index
    base = np.arange(num_gaussians) if index is None else index
    return base[~hidden]


def update_object(obj: bpy.types.Object, t: float) -> bool:
    """Show timestep ``t`` on ``obj`` (positions, colours, relevancy). Returns False if unchanged."""
    scene = engine_scene_for(obj)
    if scene is None:
        return False
    g = scene.gaussians
    t = min(max(float(t), 0.0), float(g.num_timesteps - 1))
    if abs(float(obj.get("fourlegs_shown_timestep", -1.0)) - t) < 1e-6:
        return False
    index = kept_indices(obj, g.num_gaussians)
    if obj.type == "POINTCLOUD":
        native_splats.show_timestep(obj, g, t, index)
        release_after_reading(source_key(obj), (g.means, g.colors, g.rotations, g.log_scales, g.sh),
                              2 if t != int(t) else 1)
    else:
        pick = (lambda a: a) if index is None else (lambda a: a[index])
        rgb = pick(blend_timestep(g.colors, t)) if g.colors is not None and g.colors.ndim == 3 else None
        mesh_splats.show_timestep(obj.data, pick(blend_timestep(g.means, t)), rgb)
        release_after_reading(source_key(obj), (g.means, g.colors), 2 if t != int(t) else 1)
    rel = _RELEVANCY.get(source_key(obj))
    if rel is not None and rel.ndim == 2:
        _write_relevancy(obj, blend_timestep(rel[:, :, None], t)[:, 0], index)
    _changed(obj)
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


def _write_relevancy(obj: bpy.types.Object, values: np.ndarray, index: Optional[np.ndarray]) -> None:
    values = values if index is None else np.asarray(values)[index]
    if obj.type == "POINTCLOUD":
        native_splats.write_relevancy(obj, values)
    else:
        mesh_splats.write_relevancy(obj.data, values)


def set_relevancy(obj: bpy.types.Object, relevancy: np.ndarray, *, show: bool = True) -> None:
    """Store per-Gaussian relevancy ((N,) or (T,N) in [0,1]) and colour the viewport with it."""
    rel = np.asarray(relevancy, dtype=np.float32)
    scene = engine_scene_for(obj)
    n = scene.num_gaussians if scene is not None else len(obj.data.vertices)
    if rel.shape[-1] != n or rel.ndim not in (1, 2):
        raise ValueError(f"relevancy has shape {rel.shape}, expected ({n},) or (T,{n})")
    _RELEVANCY[source_key(obj)] = rel
    shown = float(obj.get("fourlegs_shown_timestep", 0.0))
    _write_relevancy(obj, rel if rel.ndim == 1 else blend_timestep(rel[:, :, None], shown)[:, 0],
                     kept_indices(obj, n))
    show_relevancy(obj, show)
    _changed(obj)


def _changed(obj: bpy.types.Object) -> None:
    """Tell Blender the object's data changed (a mesh recomputes, a point cloud is tagged)."""
    if obj.type == "MESH":
        obj.data.update()
    else:
        obj.data.update_tag()


def set_relevancy_provider(obj: bpy.types.Object, provider: Any) -> None:
    """Register ``provider(t: int) -> (N,)`` computing per-Gaussian relevancy of timestep t on demand.

    The render engine asks only for timesteps of frames the plan lists; results are cached.
    """
    key = source_key(obj)
    _RELEVANCY_PROVIDERS[key] = provider
    for k in [k for k in _RELEVANCY_CACHE if k[0] == key]:
        del _RELEVANCY_CACHE[k]


def relevancy_provider(obj: bpy.types.Object) -> Optional[Any]:
    """The object's relevancy provider (a query engine's ``gaussian_relevancy``), or None."""
    return _RELEVANCY_PROVIDERS.get(source_key(obj) or "")


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
    """Switch the viewport colouring between the splat colours and the relevancy heat map."""
    if obj.type == "POINTCLOUD":
        native_splats.show_relevancy(obj, show)
    else:
        mesh_splats.show_relevancy(obj, show)


def register() -> None:
    if on_frame_change not in bpy.app.handlers.frame_change_post:
        bpy.app.handlers.frame_change_post.append(on_frame_change)


def unregister() -> None:
    if on_frame_change in bpy.app.handlers.frame_change_post:
        bpy.app.handlers.frame_change_post.remove(on_frame_change)
