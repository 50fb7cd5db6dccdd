"""Generate Highlight: camera keys, scene-time keys, timeline, compositor (only with desaturation), undo."""
from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest

from _blender_helpers import bl, bpy_addon, hand_plan, orbit_key, tiny_scene  # noqa: F401

pytestmark = pytest.mark.blender


def _setup(bl, plan):
    from fourlegs_addon import importer, operators

    bl.context.scene.fourlegs.renderer = "FOURLEGS"  # the 4-LEGS Splats engine's compositor (EEVEE/Cycles: test_blender_native_splats)
    importer.import_scene(bl.context.scene, tiny_scene())
    cam = operators.generate_highlight(bl.context.scene, plan)
    return cam


def test_camera_keys_reproduce_the_plan_at_every_frame(bl):
    from fourlegs_addon import convert, keyframes

    plan = hand_plan()
    cam = _setup(bl, plan)
    scene = bl.context.scene
    assert (scene.frame_start, scene.frame_end, scene.render.fps) == (1, 12, 12)
    assert (scene.render.resolution_x, scene.render.resolution_y) == (32, 24)
    assert scene.camera == cam
    # the static 'context' shot is thinned to its two ends; the orbit keeps a key per frame on its arc
    assert keyframes.keyed_frames(cam, "location", 0) == [1, 6, 7, 8, 9, 10, 11, 12]
    for shot in plan["shots"]:
        for key in shot["camera_keys"]:
            c2w, lens = keyframes.camera_pose_at(cam, scene, key["frame"])
            np.testing.assert_allclose(c2w, np.asarray(key["c2w"]), atol=2e-3)
            assert lens == pytest.approx(key["lens_mm"], rel=1e-3)
    # shots are joined by cuts: the last key of a shot holds (CONSTANT); thinned keys ease, orbit keys are LINEAR
    fc = keyframes.find_fcurve(cam, "location", 0)
    interp = {int(kp.co[0]): kp.interpolation for kp in fc.keyframe_points}
    assert interp[1] == "BEZIER" and interp[6] == "CONSTANT" and interp[12] == "CONSTANT" and interp[9] == "LINEAR"


def test_scene_time_keys_hold_for_bullet_time(bl):
    from fourlegs_addon import keyframes

    _setup(bl, hand_plan())
    scene = bl.context.scene
    assert keyframes.keyed_frames(scene, keyframes.TIMESTEP_PATH) == [1, 6, 7, 12]
    expected = {1: 0.0, 6: 2.5, 7: 2.0, 9: 2.0, 12: 2.0}
    expected[3] = 2.5 * 2 / 5  # linear between (1, 0) and (6, 2.5)
    for frame, t in expected.items():
        scene.frame_set(frame)
        assert scene.fourlegs.timestep == pytest.approx(t, abs=1e-5)


def test_sparse_orbit_keys_are_densified_along_the_arc(bl):
    """Two keys 90 degrees apart on an orbit: in-between frames stay on the circle (no chord)."""
    from fourlegs_addon import keyframes

    plan = hand_plan(desaturate=False)
    plan["shots"] = [{"name": "orbit", "effect": "bullet_time", "frame_start": 1, "frame_end": 9,
                      "camera_keys": [orbit_key(1, 0.0), orbit_key(9, math.pi / 2)],
                      "time_keys": [{"frame": 1, "timestep": 1.0}], "interpolation": "bezier", "params": {}}]
    plan["frame_end"] = 9
    cam = _setup(bl, plan)
    scene = bl.context.scene
    for frame in range(1, 10):
        scene.frame_set(frame)
        x, y, z = cam.matrix_world.translation
        assert math.hypot(x, y) == pytest.approx(4.0, abs=1e-3)  # the chord would dip to 2.83
        assert z == pytest.approx(1.0, abs=1e-4)
        angle = math.atan2(y, x)
        assert angle == pytest.approx((frame - 1) / 8 * math.pi / 2, abs=1e-3)
        # still looking at the action centre (the origin)
        forward = -np.array(cam.matrix_world.to_3x3().col[2])
        to_centre = -np.array([x, y, z]) / np.linalg.norm([x, y, z])
        assert float(forward @ to_centre) > 0.999


def test_sparse_keys_elsewhere_ease_with_bezier(bl):
    from fourlegs_addon import keyframes

    plan = hand_plan(desaturate=False)
    plan["shots"] = [{"name": "dolly", "effect": "zoom_in", "frame_start": 1, "frame_end": 11,
                      "camera_keys": [orbit_key(1, 0.0, radius=6.0), orbit_key(11, 0.0, radius=3.0)],
                      "time_keys": [], "interpolation": "bezier", "params": {}}]
    plan["frame_end"] = 11
    cam = _setup(bl, plan)
    fc = keyframes.find_fcurve(cam, "location", 0)
    assert [kp.interpolation for kp in fc.keyframe_points] == ["BEZIER", "CONSTANT"]
    scene = bl.context.scene
    xs = []
    for f in range(1, 12):
        scene.frame_set(f)
        xs.append(cam.location.x)
    steps = np.abs(np.diff(xs))
    assert steps[0] < steps[5] and steps[-1] < steps[5]  # slow in, slow out


def test_compositor_present_with_desaturation(bl):
    from fourlegs_addon import compositor

    _setup(bl, hand_plan(desaturate=True))
    scene = bl.context.scene
    tree = compositor.compositor_tree(scene)
    assert tree is not None and compositor.has_desaturation(scene)
    kinds = {n.bl_idname for n in tree.nodes}
    version_specific = ({"ShaderNodeMix", "NodeGroupOutput"} if bl.app.version >= (5, 0, 0)   # node-group compositor
                        else {"CompositorNodeMixRGB", "CompositorNodeComposite"})            # 4.2 - 4.5
    assert {"CompositorNodeRLayers", "CompositorNodeHueSat"} | version_specific <= kinds
    layers = next(n for n in tree.nodes if n.bl_idname == "CompositorNodeRLayers")
    rel_links = [l for l in tree.links if l.from_node == layers and l.from_socket.name == "Relevancy"]
    assert rel_links, "the Relevancy pass drives the mask"
    assert scene.view_layers[0].fourlegs_relevancy
    weights = compositor.frame_weights(hand_plan(desaturate=True))
    assert weights[1] == 0.0 and weights[6] == 0.0 and weights[9] == 1.0
    assert 0.0 < weights[7] < weights[8] < 1.0  # fade in over 2 frames
    node = tree.nodes[compositor.WEIGHT_NODE]
    for frame in (1, 7, 9, 12):
        scene.frame_set(frame)
        assert node.outputs[0].default_value == pytest.approx(weights[frame], abs=1e-5)


def test_compositor_absent_without_desaturation(bl):
    from fourlegs_addon import compositor

    _setup(bl, hand_plan(desaturate=False))
    scene = bl.context.scene
    assert compositor.compositor_tree(scene) is None
    assert not [g for g in bl.data.node_groups if g.bl_idname == "CompositorNodeTree"]
    assert not scene.view_layers[0].fourlegs_relevancy


def test_regenerating_replaces_only_what_it_created(bl):
    from fourlegs_addon import compositor, keyframes, operators

    _setup(bl, hand_plan(desaturate=True))
    user_cam = bl.data.objects.new("MyCamera", bl.data.cameras.new("MyCamera"))
    bl.context.scene.collection.objects.link(user_cam)
    user_cam.keyframe_insert("location", frame=3)
    plan = hand_plan(desaturate=False)
    for shot in plan["shots"]:
        for key in shot["camera_keys"]:
            key["lens_mm"] = 70.0
    operators.generate_highlight(bl.context.scene, plan)
    generated = [o for o in bl.data.objects if o.get(keyframes.GENERATED_KEY)]
    assert len(generated) == 1
    assert sum(1 for c in bl.data.cameras if c.get(keyframes.GENERATED_KEY)) == 1
    assert "MyCamera" in bl.data.objects and keyframes.keyed_frames(user_cam, "location", 0) == [3]
    assert compositor.compositor_tree(bl.context.scene) is None
    _, lens = keyframes.camera_pose_at(generated[0], bl.context.scene, 4)
    assert lens == pytest.approx(70.0)


def test_bad_plan_is_reported_not_crashed(bl, tmp_path):
    from fourlegs_addon import importer

    importer.import_scene(bl.context.scene, tiny_scene())
    plan = hand_plan()
    plan["shots"][0]["camera_keys"][0]["c2w"] = [[1, 2], [3, 4]]
    path = tmp_path / "plan.json"
    path.write_text(json.dumps(plan))
    with pytest.raises(RuntimeError, match=r"camera_keys\[0\]\.c2w"):
        bl.ops.fourlegs.generate_highlight(plan_file=str(path))
    assert not [o for o in bl.data.objects if o.get("fourlegs_generated")]


def test_undo_after_generate_highlight_restores_the_previous_state(bl, tmp_path):
    """In background mode Blender pushes no undo steps by itself: push them as the UI would
    (the operator has the UNDO flag) inside a window/screen context, then undo and redo."""
    from fourlegs_addon import compositor, highlight_ops, importer

    assert "UNDO" in highlight_ops.FOURLEGS_OT_generate_highlight.bl_options
    importer.import_scene(bl.context.scene, tiny_scene())
    path = tmp_path / "plan.json"
    path.write_text(json.dumps(hand_plan(desaturate=True)))
    window = bl.context.window_manager.windows[0]
    before = {o.name for o in bl.data.objects}
    with bl.context.temp_override(window=window, screen=window.screen):
        bl.ops.ed.undo_push(message="before Generate Highlight")
        assert bl.ops.fourlegs.generate_highlight(plan_file=str(path)) == {"FINISHED"}
        bl.ops.ed.undo_push(message="Generate Highlight")
        scene = bl.context.scene
        assert "4-LEGS Highlight Camera" in bl.data.objects and scene.frame_end == 12
        assert bl.ops.ed.undo() == {"FINISHED"}
    scene = bl.context.scene
    assert {o.name for o in bl.data.objects} == before
    assert scene.frame_end == 4 and scene.render.engine != "FOURLEGS_SPLATS"
    assert compositor.compositor_tree(scene) is None and "fourlegs_plan.json" not in bl.data.texts
    assert scene.fourlegs.splat_object is not None  # the import (before) survives
    with bl.context.temp_override(window=window, screen=window.screen):
        assert bl.ops.ed.redo() == {"FINISHED"}
    assert "4-LEGS Highlight Camera" in bl.data.objects and bl.context.scene.frame_end == 12
