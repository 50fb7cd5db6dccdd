"""The "4-LEGS Splats" render engine: F12 / animation renders through the engine's Gaussian rasterizer.

For the current frame it rasterizes every visible imported splat object at the scene timestep
(``scene.fourlegs.timestep``, fractional values interpolate positions and colours) seen from the
scene's active camera, and writes

- ``Combined``: RGB, scene-linear (the Gaussians' sRGB colours linearized, so a PNG/MP4 written with
  the Standard view transform reproduces the rasterizer's colours), alpha = coverage when the film
  is transparent, else 1,
- ``Depth``: expected camera depth (1e10 where nothing was hit, as Blender's other engines do), on
  every frame the view layer's Z pass is on,
- ``Relevancy``: the query's relevancy of the visible surface in [0, 1], declared through
  ``update_render_passes`` when the view layer asks for it (``view_layer.fourlegs_relevancy``),
  and computed **only on frames the highlight plan lists** in ``passes["relevancy"]`` (elsewhere
  the pass stays 0 and nothing is computed).

Relevancy is the per-Gaussian relevancy of that timestep rendered as a one-channel feature in the
same rasterization as the colours and divided by the coverage (so it is the weighted mean relevancy
of what the pixel sees). Works in background mode (no GPU module needed).
"""
from __future__ import annotations

import json
import time
import warnings
from typing import Any, Optional

import bpy
import numpy as np

from . import compositor, convert, importer, relevancy_store
from .keyframes import frames_in_ranges
from .messages import error_line

ENGINE_ID = "FOURLEGS_SPLATS"
RELEVANCY_PASS = "Relevancy"
PLAN_TEXT_NAME = "fourlegs_plan.json"
EMPTY_DEPTH = 1e10

#: per-frame statistics of the last render (the headless job reads and reports them)
stats: dict[str, Any] = {"frames": 0, "relevancy_frames": [], "depth_frames": [], "seconds": 0.0,
                         "last_error": None, "cancelled": False}


def reset_stats() -> None:
    stats.update(frames=0, relevancy_frames=[], depth_frames=[], seconds=0.0, last_error=None, cancelled=False)


#: the last parsed plan text: (source string, plan) -- parsing the plan JSON on every frame cost
#: more than the Blender side of a frame; the text is re-read (cheap) and re-parsed only when it changed
_PLAN_CACHE: list = [None, None]


def plan_of(scene: bpy.types.Scene) -> Optional[dict[str, Any]]:
    """The highlight plan stored by Generate Highlight (text datablock), or None.

    The parsed plan is shared between calls while the text is unchanged: treat it as read-only.
    """
    name = scene.get("fourlegs_plan_text", PLAN_TEXT_NAME)
    text = bpy.data.texts.get(name)
    if text is None:
        return None
    source = text.as_string()
    if _PLAN_CACHE[0] != source:
        try:
            plan = json.loads(source)
        except json.JSONDecodeError:
            plan = None
        _PLAN_CACHE[:] = [source, plan]
    return _PLAN_CACHE[1]


def relevancy_frames(scene: bpy.types.Scene, plan: Any = ...) -> list:
    plan = plan_of(scene) if plan is ... else plan
    return list(((plan or {}).get("passes") or {}).get("relevancy") or [])


def depth_wanted(scene: bpy.types.Scene, view_layer, frame: int, plan: Any = ...) -> bool:
    """Depth on every frame the view layer's Z pass is on (a Z pass is never left holding "nothing hit")."""
    return bool(view_layer.use_pass_z)


def wants_relevancy_pass(view_layer: bpy.types.ViewLayer) -> bool:
    return bool(getattr(view_layer, "fourlegs_relevancy", False))


def scene_camera(scene: bpy.types.Scene, depsgraph, width: int, height: int):
    """The active camera as an engine ``Camera`` (OpenCV) at the render resolution."""
    cam_obj = scene.camera
    if cam_obj is None:
        raise RuntimeError("the scene has no active camera")
    cam_eval = cam_obj.evaluated_get(depsgraph) if depsgraph is not None else cam_obj
    data = cam_eval.data
    if data.type != "PERSP":
        raise RuntimeError(f"camera {cam_obj.name!r} is {data.type}; the splat renderer needs a perspective camera")
    render = scene.render
    K = convert.camera_intrinsics(data.lens, data.sensor_width, data.sensor_height, data.sensor_fit, width,
                                  height, shift_x=data.shift_x, shift_y=data.shift_y,
                                  pixel_aspect_x=render.pixel_aspect_x, pixel_aspect_y=render.pixel_aspect_y)
    c2w = convert.blender_to_opencv_c2w(np.array(cam_eval.matrix_world))
    w2c = convert.rigid_inverse(c2w)
    from fourlegs_engine import api

    return api.Camera(K=K, w2c=w2c, width=width, height=height, near=max(data.clip_start, 1e-4),
                  far=max(data.clip_end, data.clip_start * 2), name=cam_obj.name)


def gather_gaussians(scene: bpy.types.Scene, t: float, with_relevancy: bool, plan: Any = ...,
                     camera: Any = None) -> Optional[dict[str, np.ndarray]]:
    """Concatenate the visible splat objects' Gaussians at timestep ``t`` (world space): the points an
    editor deleted or hid are left out, SH colours are evaluated for ``camera`` (an engine ``Camera``;
    None: their DC term)."""
    parts = []
    for obj in importer.splat_objects(scene):
        if obj.hide_render:
            continue
        src = importer.engine_scene_for(obj)
        if src is None:
            continue
        part = _object_gaussians(obj, src.gaussians, t, camera)
        timestep, index = part.pop("timestep"), part.pop("index")
        if with_relevancy:
            query = ((plan_of(scene) if plan is ... else plan) or {}).get("query")
            rel = relevancy_store.relevancy_for(scene, obj, src, timestep, query)
            rel = np.zeros(src.num_gaussians, np.float32) if rel is None else np.asarray(rel, np.float32)
            part["relevancy"] = rel if index is None else rel[index]
        parts.append(part)
    if not parts:
        return None
    if len(parts) == 1:  # the usual case: no copy
        return parts[0]
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def _object_gaussians(obj: bpy.types.Object, g: Any, t: float, camera: Any) -> dict[str, Any]:
    """One object's Gaussians at scene time ``t``: means, rotations, log_scales, opacity_logits, colors
    (arrays over the shown Gaussians), plus their ``index`` (None: all) and the nearest ``timestep``."""
    tt = min(max(float(t), 0.0), float(g.num_timesteps - 1))
    ti = int(round(tt))
    index = importer.visible_indices(obj, g.num_gaussians)
    pick = (lambda a: a) if index is None else (lambda a: a[index])
    means = pick(importer.blend_timestep(g.means, tt))
    mw = np.array(obj.matrix_world, dtype=np.float64)
    if not np.allclose(mw, np.eye(4)):
        means = (means @ mw[:3, :3].T + mw[:3, 3]).astype(np.float32)
    log_scales = pick(np.asarray(g.log_scales[ti] if g.log_scales.ndim == 3 else g.log_scales, np.float32))
    if g.colors is not None:
        colors = importer.blend_timestep(g.colors, tt) if g.colors.ndim == 3 else np.asarray(g.colors, np.float32)
        colors = pick(colors)
    elif camera is not None and g.sh.shape[-2] > 1:
        colors = _sh_colours(pick(np.asarray(g.sh[ti] if g.sh.ndim == 4 else g.sh, np.float32)), means, camera)
    else:
        colors = pick(g.rgb(ti).astype(np.float32))
    importer.release_after_reading(importer.source_key(obj), (g.means, g.colors, g.rotations, g.log_scales),
                                   2 if tt != int(tt) else 1)
    return {"means": means, "rotations": pick(np.asarray(g.rotations[ti], np.float32)), "log_scales": log_scales,
            "opacity_logits": pick(np.asarray(g.opacity_logits, np.float32)), "colors": colors,
            "index": index, "timestep": ti}


def _sh_colours(sh: np.ndarray, means: np.ndarray, camera: Any) -> np.ndarray:
    """(M,3) RGB in [0,1] of SH coefficients (M,K,3) seen from ``camera`` (the engine's SH evaluation)."""
    import torch

    from fourlegs_engine import api

    with torch.no_grad():
        rgb = api.eval_sh(torch.from_numpy(np.ascontiguousarray(sh)), torch.from_numpy(np.ascontiguousarray(means)),
                          camera)
    return rgb.clamp(0.0, 1.0).numpy().astype(np.float32)


GEOMETRY_TYPES = ("MESH", "CURVE", "CURVES", "SURFACE", "META", "FONT", "VOLUME", "GREASEPENCIL")


def undrawn_objects(scene: bpy.types.Scene) -> list[str]:
    """Visible objects this engine does not draw (everything but the splats: meshes, text, curves, ...)."""
    splats = set(importer.splat_objects(scene))
    return sorted(o.name for o in scene.objects if o.type in GEOMETRY_TYPES and o not in splats and not o.hide_render)


def undrawn_line(scene: bpy.types.Scene) -> str:
    """The panel's one line when the scene holds objects this engine leaves out (empty when none)."""
    names = undrawn_objects(scene)
    if not names:
        return ""
    where = "EEVEE or Cycles" if bpy.app.version >= (5, 3, 0) else "EEVEE or Cycles on Blender 5.3+"
    return (f"the 4-LEGS Splats engine draws only the splats; {len(names)} object(s) ({', '.join(names[:3])}) "
            f"need {where}")


def srgb_to_linear_torch(c, out=None):
    """Torch twin of ``convert.srgb_to_linear`` for the rasterized image (one pass fewer copies).

    Args:
        c: (...,3) sRGB-encoded values (any float dtype; NaN -> 0, clamped to [0,1]).
        out: optional float32 tensor (may be a strided view) receiving the result.
    Returns:
        (...,3) float32 scene-linear values (``out`` when given).
    """
    import torch

    c = torch.nan_to_num(c.to(torch.float32), nan=0.0).clamp_(0.0, 1.0)
    high = c.add(0.055).div_(1.055).pow_(2.4)
    result = torch.where(c <= 0.04045, c / 12.92, high)
    if out is None:
        return result
    out.copy_(result)
    return out


def render_arrays(scene: bpy.types.Scene, depsgraph, width: int, height: int, *, frame: int,
                  relevancy_pass: bool, depth: bool = True, plan: Any = ..., camera: Any = None,
                  transparent: Optional[bool] = None) -> dict[str, np.ndarray]:
    """Rasterize the current state: returns top-down (H,W,·) float32 arrays rgba, depth, [relevancy].

    ``depth=False`` skips the depth output (the pass is filled with "nothing hit"); relevancy is
    computed only when ``relevancy_pass`` and ``frame`` is in the plan's relevancy ranges or the keyed
    desaturation or blur is on there (an editor may have moved the masked shot).
    ``plan``: the scene's plan when the caller already has it (default: read it).
    ``camera``: an engine ``Camera`` of ``width`` x ``height`` (default: the scene's active camera).
    ``transparent``: alpha = coverage (default: the scene's ``film_transparent``).
    """
    import torch

    plan = plan_of(scene) if plan is ... else plan
    t = float(scene.fourlegs.timestep)
    compute_rel = relevancy_pass and (frames_in_ranges(relevancy_frames(scene, plan), frame)
                                      or compositor.mask_at(scene, frame) > 0.0)
    camera = scene_camera(scene, depsgraph, width, height) if camera is None else camera
    data = gather_gaussians(scene, t, compute_rel, plan, camera)
    out: dict[str, np.ndarray] = {}
    if data is None:
        out["rgba"] = np.zeros((height, width, 4), np.float32)
        out["depth"] = np.full((height, width, 1), EMPTY_DEPTH, np.float32)
        if relevancy_pass:
            out["relevancy"] = np.zeros((height, width, 1), np.float32)
        return out
    from fourlegs_engine.api import rasterize
    with warnings.catch_warnings():  # read-only memmap rows are shared, not copied: the rasterizer never writes them
        warnings.filterwarnings("ignore", message="The given NumPy array is not writable")
        tens = {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in data.items()}
    outputs = ["rgb", "alpha"] + (["depth"] if depth else []) + (["features"] if compute_rel else [])
    with torch.no_grad():
        res = rasterize(tens["means"], tens["rotations"], tens["log_scales"], tens["opacity_logits"], camera,
                        colors=tens["colors"], features=tens["relevancy"][:, None] if compute_rel else None,
                        outputs=tuple(outputs))
        alpha = res["alpha"].to(torch.float32)
        rgba = torch.empty((height, width, 4), dtype=torch.float32)
        srgb_to_linear_torch(res["rgb"], out=rgba[..., :3])  # Blender's Combined is scene-linear
        if scene.render.film_transparent if transparent is None else transparent:
            rgba[..., 3:].copy_(alpha)
        else:
            rgba[..., 3].fill_(1.0)
        out["rgba"] = rgba.numpy()
        hit = alpha > 1e-3
        if depth:
            out["depth"] = torch.where(hit, res["depth"].to(torch.float32), EMPTY_DEPTH).numpy()
        else:
            out["depth"] = np.full((height, width, 1), EMPTY_DEPTH, np.float32)
        if relevancy_pass:
            if compute_rel:
                feat = res["features"].to(torch.float32)
                rel = torch.where(hit, feat / alpha.clamp(min=1e-3), 0.0)
                out["relevancy"] = torch.nan_to_num(rel, nan=0.0).clamp_(0.0, 1.0).numpy()
            else:
                out["relevancy"] = np.zeros((height, width, 1), np.float32)
    out["relevancy_computed"] = np.array(compute_rel)
    return out


def _to_rect(img: np.ndarray) -> np.ndarray:
    """Top-down (H,W,C) image -> Blender's bottom-up (H*W, C) pixel rows."""
    return np.ascontiguousarray(img[::-1].reshape(-1, img.shape[2]), dtype=np.float32)


def write_pass(render_pass, img: np.ndarray) -> None:
    """Copy a top-down (H,W,C) image into a render pass (``foreach_set``: far faster than ``rect = ...``)."""
    rect = _to_rect(img)
    try:
        render_pass.rect.foreach_set(rect.ravel())
    except (AttributeError, TypeError):  # older Blender without foreach_set on the pass buffer
        render_pass.rect = rect


#: longest side, in pixels, of the viewport image the CPU rasterizer draws (scaled up to the region)
VIEWPORT_MAX_SIDE = 320


def viewport_camera(view_matrix, window_matrix, width: int, height: int, near: float = 0.01, far: float = 1000.0):
    """An engine ``Camera`` (OpenCV) of ``width`` x ``height`` pixels seeing what a 3D viewport sees.

    Args:
        view_matrix: (4,4) world -> OpenGL view (``region_data.view_matrix``).
        window_matrix: (4,4) OpenGL perspective projection (``region_data.window_matrix``).
    Raises RuntimeError for an orthographic view (the rasterizer is perspective only).
    """
    P = np.array(window_matrix, dtype=np.float64)
    if abs(P[3, 3]) > 1e-9 or abs(P[3, 2] + 1.0) > 1e-6:
        raise RuntimeError("orthographic view: the splat viewport needs a perspective view (numpad 5)")
    # OpenGL NDC -> top-down pixels, with OpenCV camera axes (y down, z forward) = GL axes (1, -1, -1)
    K = np.array([[P[0, 0] * width / 2.0, 0.0, width / 2.0 * (1.0 - P[0, 2])],
                  [0.0, P[1, 1] * height / 2.0, height / 2.0 * (1.0 + P[1, 2])],
                  [0.0, 0.0, 1.0]])
    w2c = np.diag([1.0, -1.0, -1.0, 1.0]) @ np.array(view_matrix, dtype=np.float64)
    from fourlegs_engine import api

    return api.Camera(K=K, w2c=w2c, width=int(width), height=int(height), near=max(float(near), 1e-4),
                      far=max(float(far), 2.0 * max(float(near), 1e-4)), name="viewport")


def viewport_size(region_width: int, region_height: int, max_side: int = VIEWPORT_MAX_SIDE) -> tuple[int, int]:
    """(width, height) of the image rasterized for a region: its aspect, the longest side at most ``max_side``."""
    scale = min(1.0, max_side / max(region_width, region_height, 1))
    return max(1, round(region_width * scale)), max(1, round(region_height * scale))


def viewport_image(scene: bpy.types.Scene, view_matrix, window_matrix, region_width: int, region_height: int, *,
                   near: float = 0.01, far: float = 1000.0, max_side: int = VIEWPORT_MAX_SIDE) -> np.ndarray:
    """Top-down (h,w,4) scene-linear RGBA of the splats at the scene timestep seen from the viewport, at
    :func:`viewport_size` (alpha = coverage, so the viewport's background shows where nothing is)."""
    width, height = viewport_size(region_width, region_height, max_side)
    camera = viewport_camera(view_matrix, window_matrix, width, height, near, far)
    arrays = render_arrays(scene, None, width, height, frame=scene.frame_current, relevancy_pass=False,
                           depth=False, plan=None, camera=camera, transparent=True)
    return arrays["rgba"]


def _draw_image(engine: "FourlegsRenderEngine", scene, rgba: np.ndarray, region_width: int, region_height: int) -> None:
    """Draw a top-down (h,w,4) linear image over the whole region through Blender's display transform."""
    import gpu
    from gpu_extras.presets import draw_texture_2d

    h, w = rgba.shape[:2]
    pixels = gpu.types.Buffer("FLOAT", w * h * 4, _to_rect(rgba).ravel())  # buffer protocol: one copy
    texture = gpu.types.GPUTexture((w, h), format="RGBA16F", data=pixels)
    gpu.state.blend_set("ALPHA_PREMULT")
    engine.bind_display_space_shader(scene)
    draw_texture_2d(texture, (0, 0), region_width, region_height)
    engine.unbind_display_space_shader()
    gpu.state.blend_set("NONE")


class FourlegsRenderEngine(bpy.types.RenderEngine):
    bl_idname = ENGINE_ID
    bl_label = "4-LEGS Splats"
    bl_use_preview = False
    bl_use_postprocess = True
    bl_use_shading_nodes_custom = False

    def view_update(self, context, depsgraph):
        self._view_key = None  # the scene changed (timestep, objects): draw again

    def view_draw(self, context, depsgraph):
        """Viewport (Rendered shading): the splats through the CPU rasterizer at interactive resolution,
        drawn again only when the view, the timestep or the scene changed."""
        region, rv3d, space = context.region, context.region_data, context.space_data
        scene = depsgraph.scene
        key = (tuple(map(tuple, rv3d.view_matrix)), tuple(map(tuple, rv3d.window_matrix)), region.width,
               region.height, float(scene.fourlegs.timestep))
        try:
            if key != getattr(self, "_view_key", None) or getattr(self, "_view_image", None) is None:
                self._view_image = viewport_image(scene, rv3d.view_matrix, rv3d.window_matrix, region.width,
                                                  region.height, near=space.clip_start, far=space.clip_end)
                self._view_key = key
            _draw_image(self, scene, self._view_image, region.width, region.height)
        except Exception as exc:  # an orthographic view, a missing scene: say it once, draw nothing
            message = f"4-LEGS Splats viewport: {exc}"
            if getattr(self, "_view_error", None) != message:
                self._view_error = message
                print(message)

    def update_render_passes(self, scene=None, renderlayer=None):
        self.register_pass(scene, renderlayer, "Combined", 4, "RGBA", "COLOR")
        if renderlayer.use_pass_z:
            self.register_pass(scene, renderlayer, "Depth", 1, "Z", "VALUE")
        if wants_relevancy_pass(renderlayer):
            self.register_pass(scene, renderlayer, RELEVANCY_PASS, 1, "X", "VALUE")

    def render(self, depsgraph):
        scene = depsgraph.scene
        scale = scene.render.resolution_percentage / 100.0
        width = max(1, int(scene.render.resolution_x * scale))
        height = max(1, int(scene.render.resolution_y * scale))
        view_layer = depsgraph.view_layer
        want_rel = wants_relevancy_pass(view_layer)
        if want_rel:
            self.add_pass(RELEVANCY_PASS, 1, "X", layer=view_layer.name)
        start = time.perf_counter()
        plan = plan_of(scene)
        want_depth = depth_wanted(scene, view_layer, scene.frame_current, plan)
        result = self.begin_result(0, 0, width, height, layer=view_layer.name)
        try:
            arrays = render_arrays(scene, depsgraph, width, height, frame=scene.frame_current,
                                   relevancy_pass=want_rel, depth=want_depth, plan=plan)
        except KeyboardInterrupt:  # Ctrl-C inside the rasterizer: no traceback, the frame is dropped
            stats["cancelled"] = True
            self.end_result(result, cancel=True)
            return
        except Exception as exc:  # report, leave an empty (black) frame, let the caller see the error
            stats["last_error"] = error_line(exc)
            self.report({"ERROR"}, f"4-LEGS Splats: {stats['last_error']}")
            self.end_result(result, cancel=False)
            return
        layer = result.layers[0]
        write_pass(layer.passes["Combined"], arrays["rgba"])
        undrawn = undrawn_line(scene)
        if undrawn:
            self.report({"WARNING"}, undrawn)
        depth_pass = layer.passes.get("Depth")
        if depth_pass is not None:
            write_pass(depth_pass, arrays["depth"])
        if want_rel:
            rel_pass = layer.passes.get(RELEVANCY_PASS)
            if rel_pass is not None:
                write_pass(rel_pass, arrays["relevancy"])
        self.end_result(result)
        stats["frames"] += 1
        if want_depth:
            stats["depth_frames"].append(scene.frame_current)
        if bool(arrays.get("relevancy_computed", False)):
            stats["relevancy_frames"].append(scene.frame_current)
        stats["seconds"] += time.perf_counter() - start


def register() -> None:
    bpy.types.ViewLayer.fourlegs_relevancy = bpy.props.BoolProperty(
        name="4-LEGS Relevancy", default=False,
        description="Write the query's Relevancy pass (computed only on frames the highlight plan lists)")


def unregister() -> None:
    del bpy.types.ViewLayer.fourlegs_relevancy


classes = (FourlegsRenderEngine,)
