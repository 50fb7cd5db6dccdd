"""Where the 4-LEGS Splats engine renders, it honours the scene: the points an editor deleted or hid,
view-dependent colour (SH degrees 1-3), and it says plainly that meshes need EEVEE/Cycles."""
from __future__ import annotations

import numpy as np
import pytest

from _blender_helpers import bl, bpy_addon, hand_plan, tiny_scene  # noqa: F401

pytestmark = pytest.mark.blender
pytest.importorskip("torch")


def _render(bl, frame: int = 2) -> np.ndarray:
    """The 4-LEGS Splats render of ``frame`` as top-down (H,W,4) scene-linear RGBA."""
    from fourlegs_addon import render_engine

    scene = bl.context.scene
    scene.frame_set(frame)
    depsgraph = bl.context.evaluated_depsgraph_get()
    r = scene.render
    return render_engine.render_arrays(scene, depsgraph, r.resolution_x, r.resolution_y, frame=frame,
                                       relevancy_pass=False, depth=False, transparent=True)["rgba"]


def _setup(bl, scene):
    from fourlegs_addon import highlight_ops, importer

    bl.context.scene.fourlegs.renderer = "FOURLEGS"
    obj = importer.import_scene(bl.context.scene, scene)
    highlight_ops.generate_highlight(bl.context.scene, hand_plan(desaturate=False))
    return obj


def test_deleted_and_hidden_points_are_not_rendered(bl):
    import bmesh

    scene = tiny_scene(N=400)
    obj = _setup(bl, scene)
    full = _render(bl)
    keep = np.asarray(scene.gaussians.means[0])[:, 0] >= 0.0  # delete the Gaussians on the -x side
    bm = bmesh.new()
    bm.from_mesh(obj.data)
    bm.verts.ensure_lookup_table()
    bmesh.ops.delete(bm, geom=[v for v, k in zip(bm.verts, keep) if not k], context="VERTS")
    bm.to_mesh(obj.data)
    bm.free()
    cut = _render(bl)
    assert np.abs(cut - full).max() > 0.1

    # the same render as a scene made of the kept Gaussians only
    g = scene.gaussians
    kept = tiny_scene(N=400)
    kept.gaussians.means, kept.gaussians.rotations = g.means[:, keep], g.rotations[:, keep]
    kept.gaussians.colors, kept.gaussians.log_scales = g.colors[:, keep], g.log_scales[keep]
    kept.gaussians.opacity_logits = g.opacity_logits[keep]
    bl.ops.wm.read_factory_settings(use_empty=True)
    _setup(bl, kept)
    np.testing.assert_allclose(cut, _render(bl), atol=1e-5)

    # hidden in edit mode: also left out of the render (and back when revealed)
    obj = bl.context.scene.fourlegs.splat_object
    hide = np.zeros(len(obj.data.vertices), bool)
    hide[: len(hide) // 2] = True
    obj.data.vertices.foreach_set("hide", hide)
    hidden = _render(bl)
    assert (hidden[..., 3] > 0.5).sum() < (cut[..., 3] > 0.5).sum()
    obj.data.vertices.foreach_set("hide", np.zeros(len(hide), bool))
    np.testing.assert_allclose(_render(bl), cut, atol=1e-5)


def _sh_scene(scale_rest: float):
    """tiny_scene coloured by SH degree 2 (no RGB): DC from the colours, random higher terms x ``scale_rest``."""
    from fourlegs_engine.scene.gaussians import rgb_to_sh_dc

    scene = tiny_scene(N=400)
    g = scene.gaussians
    sh = np.zeros((g.num_gaussians, 9, 3), np.float32)
    sh[:, 0] = rgb_to_sh_dc(g.colors[0])
    sh[:, 1:] = np.random.default_rng(1).normal(0.0, 0.3, (g.num_gaussians, 8, 3)) * scale_rest
    g.sh, g.colors = sh, None
    return scene


def test_view_dependent_colour_is_rendered(bl):
    """Zeroing or scaling the SH terms of degree >= 1 changes the render, which equals the engine's own
    rasterization with SH evaluated from the render camera."""
    import torch

    from fourlegs_addon import render_engine
    from fourlegs_engine.render import rasterize
    from fourlegs_engine.render.sh import eval_sh

    images = {}
    for scale in (0.0, 1.0, 20.0):
        bl.ops.wm.read_factory_settings(use_empty=True)
        _setup(bl, _sh_scene(scale))
        images[scale] = _render(bl, frame=1)  # scene time 0: no interpolation between timesteps
    assert np.abs(images[1.0] - images[0.0]).max() > 0.05
    assert np.abs(images[20.0] - images[1.0]).max() > 0.05

    scene = bl.context.scene
    scene.frame_set(1)
    depsgraph = bl.context.evaluated_depsgraph_get()
    camera = render_engine.scene_camera(scene, depsgraph, scene.render.resolution_x, scene.render.resolution_y)
    g = _sh_scene(20.0).gaussians
    t = int(round(float(scene.fourlegs.timestep)))
    means = torch.from_numpy(np.asarray(g.means[t], np.float32))
    colors = eval_sh(torch.from_numpy(g.sh), means, camera).clamp(0, 1)
    ref = rasterize(means, torch.from_numpy(np.asarray(g.rotations[t])), torch.from_numpy(g.log_scales),
                    torch.from_numpy(g.opacity_logits), camera, colors=colors, outputs=("rgb",))["rgb"]
    np.testing.assert_allclose(images[20.0][..., :3], render_engine.srgb_to_linear_torch(ref).numpy(), atol=1e-4)


def test_the_panel_says_meshes_need_eevee_or_cycles(bl):
    from fourlegs_addon import panels, render_engine

    _setup(bl, tiny_scene())
    scene = bl.context.scene
    assert render_engine.undrawn_line(scene) == ""
    bl.ops.mesh.primitive_cube_add(size=0.5, location=(2.0, -2.0, 1.0))  # in front of the camera
    log = []

    class Layout:
        def __getattr__(self, name):
            def call(*args, **kwargs):
                log.append((name, kwargs.get("text", "")))
                return Layout()
            return call

    panels.FOURLEGS_PT_render.draw(type("P", (), {"layout": Layout()})(), bl.context)
    lines = [text for name, text in log if name == "label"]
    assert any("Cube" in t and "EEVEE or Cycles" in t for t in lines), lines
