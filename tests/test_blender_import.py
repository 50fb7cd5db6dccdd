"""Point-cloud import: one object, attributes, geometry nodes, timestep switching, cameras, relevancy."""
from __future__ import annotations

import numpy as np
import pytest

from _blender_helpers import bl, bpy_addon, tiny_scene  # noqa: F401

pytestmark = pytest.mark.blender


def srgb_to_linear(c):
    from fourlegs_addon.convert import srgb_to_linear as f

    return f(c)


def _positions(obj) -> np.ndarray:
    co = np.empty(len(obj.data.vertices) * 3, np.float32)
    obj.data.vertices.foreach_get("co", co)
    return co.reshape(-1, 3)


def _attr(obj, name: str, width: int) -> np.ndarray:
    attr = obj.data.attributes[name]
    out = np.empty(len(attr.data) * width, np.float32)
    attr.data.foreach_get("color" if width == 4 else "value", out)
    return out.reshape(-1, width) if width > 1 else out


def test_import_creates_one_point_cloud_object(bl):
    from fourlegs_addon import importer

    scene = tiny_scene()
    obj = importer.import_scene(bl.context.scene, scene)
    g = scene.gaussians
    assert obj.type == "MESH" and len(obj.data.vertices) == g.num_gaussians and len(obj.data.polygons) == 0
    assert bl.context.scene.fourlegs.splat_object == obj
    np.testing.assert_allclose(_positions(obj), g.means[0], atol=1e-6)
    np.testing.assert_allclose(_attr(obj, importer.RGB_ATTR, 4)[:, :3], srgb_to_linear(g.colors[0]), atol=1e-6)
    np.testing.assert_allclose(_attr(obj, importer.RADIUS_ATTR, 1), 1.5 * 0.05, rtol=1e-5)
    np.testing.assert_allclose(_attr(obj, importer.OPACITY_ATTR, 1), 1 / (1 + np.exp(-2.0)), rtol=1e-5)
    assert "color" not in obj.data.attributes  # an attribute called "color" renders black in Cycles
    # geometry nodes: Mesh to Points with the radius attribute, then Set Material
    mod = obj.modifiers[importer.MODIFIER_NAME]
    kinds = {n.bl_idname for n in mod.node_group.nodes}
    assert {"GeometryNodeMeshToPoints", "GeometryNodeSetMaterial", "GeometryNodeInputNamedAttribute"} <= kinds
    evaluated = obj.evaluated_get(bl.context.evaluated_depsgraph_get())
    points = [geom for geom in [evaluated.data] if geom is not None]
    assert points  # evaluates without error
    mat = obj.data.materials[0]
    assert mat.node_tree.nodes["Splat Colour"].attribute_name == importer.RGB_ATTR


def test_timestep_property_switches_positions_and_colours(bl):
    from fourlegs_addon import importer

    scene = tiny_scene()
    obj = importer.import_scene(bl.context.scene, scene)
    props = bl.context.scene.fourlegs
    props.timestep = 3.0
    np.testing.assert_allclose(_positions(obj), scene.gaussians.means[3], atol=1e-6)
    np.testing.assert_allclose(_attr(obj, importer.RGB_ATTR, 4)[:, :3], srgb_to_linear(scene.gaussians.colors[3]),
                               atol=1e-6)
    props.timestep = 1.25  # fractional timesteps interpolate linearly
    expect = 0.75 * scene.gaussians.means[1] + 0.25 * scene.gaussians.means[2]
    np.testing.assert_allclose(_positions(obj), expect, atol=1e-6)
    props.timestep = 99.0  # clamped to the last timestep, never an error
    np.testing.assert_allclose(_positions(obj), scene.gaussians.means[3], atol=1e-6)


def test_keyframed_timestep_follows_the_timeline(bl):
    """The frame-change handler shows the animated scene timestep (held keys = bullet-time)."""
    from fourlegs_addon import importer

    scene = tiny_scene()
    bl_scene = bl.context.scene
    obj = importer.import_scene(bl_scene, scene)
    bl_scene.frame_set(3)  # the import keyed the capture's playback: frame f shows timestep f - 1
    assert bl_scene.fourlegs.timestep == pytest.approx(2.0)
    np.testing.assert_allclose(_positions(obj), scene.gaussians.means[2], atol=1e-6)
    bl_scene.animation_data_clear()  # an editor's own keys instead
    for frame, t in ((1, 0.0), (5, 2.0), (9, 2.0)):
        bl_scene.fourlegs.timestep = t
        bl_scene.keyframe_insert("fourlegs.timestep", frame=frame)
    for frame, t in ((1, 0.0), (3, 1.0), (5, 2.0), (7, 2.0), (9, 2.0)):
        bl_scene.frame_set(frame)
        assert bl_scene.fourlegs.timestep == pytest.approx(t, abs=1e-3)
        lo, w = int(np.floor(bl_scene.fourlegs.timestep)), bl_scene.fourlegs.timestep % 1.0
        hi = min(lo + 1, 3)
        expect = (1 - w) * scene.gaussians.means[lo] + w * scene.gaussians.means[hi]
        np.testing.assert_allclose(_positions(obj), expect, atol=1e-5)


def test_cameras_are_imported_with_matching_pose_and_lens(bl):
    from fourlegs_addon import convert, importer

    scene = tiny_scene()
    importer.import_scene(bl.context.scene, scene)
    for cam in scene.cameras.cameras(0, "all"):
        obj = bl.data.objects[cam.name]
        assert obj.type == "CAMERA"
        np.testing.assert_allclose(convert.blender_to_opencv_c2w(np.array(obj.matrix_world)), cam.c2w, atol=1e-5)
        assert obj.data.lens == pytest.approx(cam.fx * obj.data.sensor_width / cam.width, rel=1e-6)
    r = bl.context.scene.render
    assert (r.resolution_x, r.resolution_y) == (32, 24)


def test_relevancy_attribute_colours_the_viewport(bl):
    from fourlegs_addon import importer

    scene = tiny_scene()
    obj = importer.import_scene(bl.context.scene, scene)
    rel = np.linspace(0.0, 1.0, scene.num_gaussians, dtype=np.float32)
    importer.set_relevancy(obj, rel)
    np.testing.assert_allclose(_attr(obj, importer.RELEVANCY_ATTR, 1), rel, atol=1e-6)
    heat = _attr(obj, importer.RELEVANCY_RGB_ATTR, 4)[:, :3]
    assert heat[-1, 0] > heat[0, 0] and heat[0, 2] > heat[-1, 2]  # high relevancy = red, low = blue
    assert obj.data.color_attributes.active_color.name == importer.RELEVANCY_RGB_ATTR
    assert obj.data.materials[0].node_tree.nodes["Splat Colour"].attribute_name == importer.RELEVANCY_RGB_ATTR
    importer.show_relevancy(obj, False)
    assert obj.data.color_attributes.active_color.name == importer.RGB_ATTR
    with pytest.raises(ValueError):
        importer.set_relevancy(obj, np.zeros(3))
    # a (T,N) relevancy follows the timestep
    per_t = np.stack([np.full(scene.num_gaussians, t / 3.0, np.float32) for t in range(4)])
    importer.set_relevancy(obj, per_t)
    bl.context.scene.fourlegs.timestep = 3.0
    np.testing.assert_allclose(_attr(obj, importer.RELEVANCY_ATTR, 1), 1.0, atol=1e-6)


def test_nan_colours_never_reach_blender(bl):
    from fourlegs_addon import importer

    scene = tiny_scene()
    scene.gaussians.colors[0, :3] = np.nan
    obj = importer.import_scene(bl.context.scene, scene)
    assert np.all(np.isfinite(_attr(obj, importer.RGB_ATTR, 4)))


def test_import_300k_gaussians_in_seconds(bl):
    """300k Gaussians (the Panoptic scale): import stays well under the seconds budget."""
    import math
    import time

    from fourlegs_addon import importer
    from fourlegs_engine.scene import CameraRig, GaussianSequence, Scene

    N, T = 300_000, 2
    rng = np.random.default_rng(0)
    means = rng.normal(size=(T, N, 3)).astype(np.float32)
    rot = np.zeros((T, N, 4), np.float32)
    rot[..., 0] = 1
    g = GaussianSequence(means=means, rotations=rot, log_scales=np.full((N, 3), math.log(0.01), np.float32),
                         opacity_logits=np.zeros(N, np.float32), colors=rng.uniform(size=(T, N, 3)).astype(np.float32))
    scene = Scene(gaussians=g, cameras=CameraRig(), name="big")
    t0 = time.perf_counter()
    obj = importer.import_scene(bl.context.scene, scene, with_cameras=False)
    t_import = time.perf_counter() - t0
    t0 = time.perf_counter()
    bl.context.scene.fourlegs.timestep = 1.0
    t_switch = time.perf_counter() - t0
    assert len(obj.data.vertices) == N
    np.testing.assert_allclose(_positions(obj)[-5:], means[1, -5:], atol=1e-6)
    print(f"300k import {t_import:.2f} s, timestep switch {t_switch:.2f} s")
    assert t_import < 10.0 and t_switch < 5.0


def test_import_operator_reads_a_ply_sequence_and_reports_bad_input(bl, tmp_path):
    from fourlegs_addon import importer
    from fourlegs_engine.scene.ply import write_ply_scene

    scene = tiny_scene()
    write_ply_scene(scene, tmp_path / "frames")
    assert bl.ops.fourlegs.import_scene(filepath=str(tmp_path / "frames")) == {"FINISHED"}
    obj = bl.context.scene.fourlegs.splat_object
    assert len(obj.data.vertices) == scene.num_gaussians and bl.context.scene.fourlegs.num_timesteps == 4
    bl.context.scene.fourlegs.timestep = 2.0
    np.testing.assert_allclose(_positions(obj), scene.gaussians.means[2], atol=1e-5)
    (tmp_path / "broken.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nend_header\n")
    with pytest.raises(RuntimeError, match="4-LEGS import: .*broken.ply"):
        bl.ops.fourlegs.import_scene(filepath=str(tmp_path / "broken.ply"))
