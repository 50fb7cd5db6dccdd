"""What an editor meets: shot markers, relevancy after moving the desaturated shot, the confirm before
replacing edits, the s_t plot kept in the .blend, relative scene paths, a missing scene reported once,
Render Video refused without a highlight."""
from __future__ import annotations

import numpy as np
import pytest

from _blender_helpers import bl, bpy_addon, hand_plan, tiny_scene  # noqa: F401

pytestmark = pytest.mark.blender


def _generate(bl, plan=None):
    from fourlegs_addon import importer, operators

    obj = importer.import_scene(bl.context.scene, tiny_scene())
    operators.generate_highlight(bl.context.scene, plan or hand_plan(desaturate=True))
    return obj


def test_one_marker_per_shot_replaced_not_duplicated(bl):
    from fourlegs_addon import highlight_ops, keyframes, operators

    _generate(bl)
    scene = bl.context.scene
    own = scene.timeline_markers.new("editor note", frame=3)
    assert sorted((m.name, m.frame) for m in scene.timeline_markers) == [
        ("1 context", 1), ("2 bullet", 7), ("editor note", 3)]
    assert keyframes.has_generated(scene)
    operators.generate_highlight(scene, hand_plan(desaturate=False))
    assert sorted((m.name, m.frame) for m in scene.timeline_markers) == [
        ("1 context", 1), ("2 bullet", 7), ("editor note", 3)]
    assert own.name == "editor note"


def test_relevancy_follows_the_desaturated_shot_where_the_editor_moved_it(bl):
    from fourlegs_addon import compositor, importer, keyframes, render_engine

    obj = _generate(bl)
    asked: list[int] = []
    importer.set_relevancy_provider(obj, lambda t: asked.append(t) or np.ones(64, np.float32))
    scene = bl.context.scene
    tree = compositor.compositor_tree(scene)
    fc = keyframes.find_fcurve(tree, f'nodes["{compositor.WEIGHT_NODE}"].outputs[0].default_value', 0)
    assert compositor.desaturation_at(scene, 3) == 0.0 and compositor.desaturation_at(scene, 9) == 1.0
    assert not render_engine.frames_in_ranges(render_engine.relevancy_frames(scene), 3)  # the plan says no
    out = render_engine.render_arrays(scene, None, 32, 24, frame=3, relevancy_pass=True)
    assert not bool(out["relevancy_computed"])
    for kp in fc.keyframe_points:  # the editor drags the desaturation keys 6 frames earlier
        kp.co.x -= 6
        kp.handle_left.x -= 6
        kp.handle_right.x -= 6
    fc.update()
    assert compositor.desaturation_at(scene, 3) == pytest.approx(1.0)
    out = render_engine.render_arrays(scene, None, 32, 24, frame=3, relevancy_pass=True)
    assert bool(out["relevancy_computed"]) and asked  # computed where it now is


def test_s_t_plot_is_packed_into_the_blend(bl, tmp_path):
    from fourlegs_addon import plots

    img = plots.scores_image(np.array([0.1, 0.5, 0.9, 0.2]), np.array([False, True, True, False]), (1, 2), 2)
    assert img.packed_file is not None
    path = tmp_path / "plot.blend"
    bl.ops.wm.save_as_mainfile(filepath=str(path))
    bl.ops.wm.read_factory_settings(use_empty=True)
    bl.ops.wm.open_mainfile(filepath=str(path))
    again = bl.data.images[plots.IMAGE_NAME]
    assert again.packed_file is not None and tuple(again.size) == (256, 80)
    pixels = np.array(again.pixels[:]).reshape(80, 256, 4)
    assert pixels[..., :3].std() > 0.05  # the bars, not a blank image


def test_scene_path_is_relative_once_the_blend_is_saved_and_a_missing_scene_is_reported_once(bl, tmp_path,
                                                                                            capsys):
    from fourlegs_engine.scene import write_bundle
    from fourlegs_addon import importer

    write_bundle(tiny_scene(T=3, N=32), tmp_path / "shots" / "bundle")
    bl.ops.wm.save_as_mainfile(filepath=str(tmp_path / "edit.blend"))
    assert bl.ops.fourlegs.import_scene(filepath=str(tmp_path / "shots" / "bundle" / "scene.json")) == {"FINISHED"}
    obj = bl.context.scene.fourlegs.splat_object
    assert importer.source_key(obj) == "//shots/bundle"
    bl.ops.wm.save_mainfile()
    (tmp_path / "shots").rename(tmp_path / "moved")
    importer._SCENES.clear()
    bl.ops.wm.open_mainfile(filepath=str(tmp_path / "edit.blend"))
    capsys.readouterr()
    scene = bl.context.scene
    for frame in (1, 2, 3):
        scene.fourlegs.timestep = float(frame - 1)
        scene.frame_set(frame)
    printed = capsys.readouterr().out
    assert printed.count("cannot be opened") == 1 and "Traceback" not in printed
    obj = scene.fourlegs.splat_object
    assert "//shots/bundle" in importer.missing_message(obj)


def test_render_video_refuses_a_scene_without_a_highlight(bl, tmp_path):
    from fourlegs_addon import importer

    importer.import_scene(bl.context.scene, tiny_scene())
    bl.context.scene.fourlegs.output_path = str(tmp_path / "clip.mp4")
    with pytest.raises(RuntimeError, match="no highlight in this scene"):
        bl.ops.fourlegs.render_video()
    assert not (tmp_path / "clip.mp4").exists()


def test_a_saved_highlight_reopens_with_the_panel_filled_and_output_set_to_its_video(bl, tmp_path):
    """What the headless job does before saving its .blend (``operators.fill_from_plan``)."""
    from fourlegs_addon import operators, plots

    plan = hand_plan(desaturate=True)
    plan["localization"]["segments"] = [[0, 0], [1, 3]]
    plan["localization"]["scores"] = [0.2, 0.3, 0.4, 0.2]
    _generate(bl, plan)
    video = tmp_path / "highlight.mp4"
    operators.fill_from_plan(bl.context.scene, plan, output=str(video), fmt="MP4")
    bl.ops.wm.save_as_mainfile(filepath=str(tmp_path / "job.blend"))
    bl.ops.wm.read_factory_settings(use_empty=True)
    bl.ops.wm.open_mainfile(filepath=str(tmp_path / "job.blend"))
    scene = bl.context.scene
    props = scene.fourlegs
    assert props.query == "the cube" and props.found
    assert (props.segment_start, props.segment_end, props.peak, props.best_view) == (1, 3, 2, "cam00")
    assert [(s.start, s.end) for s in props.segments] == [(0, 0), (1, 3)] and props.segment_index == 1
    assert props.segments[1].peak_score == pytest.approx(0.4) and props.segments[0].peak_score == pytest.approx(0.2)
    assert props.output_path == str(video) and scene.render.filepath == str(video)
    assert scene.render.image_settings.file_format == "FFMPEG"
    assert bl.data.images[plots.IMAGE_NAME].packed_file is not None
    props.segment_index = 0  # the editor picks the other segment: it is shown
    assert (props.segment_start, props.segment_end) == (0, 0) and props.timestep == 0.0


def _orbit_plan(arc_deg: float = 90.0):
    import math

    from _blender_helpers import orbit_key

    plan = hand_plan(desaturate=False)
    f0, f1 = 7, 15
    angles = [math.radians(arc_deg) * (0.5 - 0.5 * math.cos(math.pi * (f - f0) / (f1 - f0))) for f in range(f0, f1 + 1)]
    plan["shots"][1] = {"name": "bullet", "effect": "bullet_time", "frame_start": f0, "frame_end": f1,
                        "camera_keys": [orbit_key(f, a) for f, a in zip(range(f0, f1 + 1), angles)],
                        "time_keys": [{"frame": f0, "timestep": 2.0}, {"frame": f1, "timestep": 2.0}],
                        "interpolation": "linear",
                        "params": {"arc_deg": arc_deg, "easing": "ease_in_out_sine", "radius_scale": 1.0,
                                   "height_scale": 1.0}}
    plan["frame_end"] = f1
    return plan


def test_orbit_is_a_rig_that_reproduces_the_plan_and_obeys_radius_and_speed(bl):
    import math

    from fourlegs_addon import convert, rig

    plan = _orbit_plan()
    main = _generate(bl, plan)
    scene = bl.context.scene
    pivot, cam = bl.data.objects[rig.PIVOT_NAME], bl.data.objects[rig.CAMERA_NAME]
    assert cam.parent == pivot and tuple(pivot.location) == pytest.approx((0, 0, 0))
    assert pivot["radius"] == pytest.approx(4.0) and pivot["speed"] == 1.0 and pivot["arc_deg"] == 90.0
    markers = {m.name: m for m in scene.timeline_markers}
    assert markers["2 bullet"].camera == cam and markers["1 context"].camera.name == "4-LEGS Highlight Camera"
    for key in plan["shots"][1]["camera_keys"]:
        scene.frame_set(key["frame"])
        assert scene.camera == cam
        c2w = convert.blender_to_opencv_c2w(np.array(cam.matrix_world))
        np.testing.assert_allclose(c2w, np.asarray(key["c2w"]), atol=1e-4)
    scene.frame_set(3)
    assert scene.camera.name == "4-LEGS Highlight Camera"
    pivot["radius"] = 6.0
    pivot["speed"] = 2.0
    pivot.update_tag()  # what editing the property in the sidebar does
    scene.frame_set(11)  # half-way through the shot: at speed 2 the 90 degree arc is done
    x, y, z = cam.matrix_world.translation
    assert math.hypot(x, y) == pytest.approx(6.0, abs=1e-4) and z == pytest.approx(1.0, abs=1e-4)
    assert math.degrees(math.atan2(y, x)) == pytest.approx(90.0, abs=1e-3)
    del main


def test_orbits_the_rig_cannot_reproduce_keep_their_keys(bl):
    from fourlegs_addon import rig

    plan = _orbit_plan()
    plan["shots"][1]["params"]["radius_scale"] = 1.5
    _generate(bl, plan)
    assert rig.PIVOT_NAME not in bl.data.objects
    assert all(m.camera is None for m in bl.context.scene.timeline_markers)


def test_dense_eased_dolly_becomes_a_few_bezier_keys_on_the_planned_path(bl):
    """60 per-frame keys of a sine-eased dolly (as the planner writes them) -> a handful of eased keys,
    every frame within the thinning tolerance of the plan."""
    import math

    from _blender_helpers import orbit_key
    from fourlegs_addon import convert, keyframes

    plan = hand_plan(desaturate=False)
    n = 60
    radii = [6.0 - 3.0 * (0.5 - 0.5 * math.cos(math.pi * i / (n - 1))) for i in range(n)]
    plan["shots"] = [{"name": "dolly", "effect": "zoom_in", "frame_start": 1, "frame_end": n,
                      "camera_keys": [orbit_key(i + 1, 0.3, radius=r) for i, r in enumerate(radii)],
                      "time_keys": [], "interpolation": "linear", "params": {}}]
    plan["frame_end"] = n
    cam = _generate(bl, plan) and bl.context.scene.camera
    keyed = keyframes.keyed_frames(cam, "location", 0)
    assert keyed[0] == 1 and keyed[-1] == n and len(keyed) <= 12, keyed
    fc = keyframes.find_fcurve(cam, "location", 0)
    assert {kp.interpolation for kp in fc.keyframe_points[:-1]} == {"BEZIER"}
    assert {kp.handle_left_type for kp in fc.keyframe_points} == {"AUTO_CLAMPED"}
    scene = bl.context.scene
    worst = 0.0
    for key in plan["shots"][0]["camera_keys"]:
        scene.frame_set(key["frame"])
        position = convert.blender_to_opencv_c2w(np.array(cam.matrix_world))[:3, 3]
        worst = max(worst, float(np.abs(position - np.asarray(key["c2w"])[:3, 3]).max()))
    assert worst <= 1.5e-3


def test_generate_asks_before_replacing_a_generated_highlight(bl, tmp_path):
    """Generate Highlight's invoke: on a scene without a highlight it generates at once; on one with a
    generated highlight it asks first (Blender's confirm popup; nothing is replaced until confirmed)."""
    import json
    import types

    from fourlegs_addon import highlight_ops, keyframes, operators

    plan_file = tmp_path / "plan.json"
    plan_file.write_text(json.dumps(hand_plan(desaturate=True)))
    _generate(bl)
    # the real operator through Blender's own invoke: the confirm's arguments are ones this Blender takes
    # (without a window Blender confirms by itself)
    assert bl.ops.fourlegs.generate_highlight("INVOKE_DEFAULT", plan_file=str(plan_file)) == {"FINISHED"}

    asked, executed = [], []
    window_manager = types.SimpleNamespace(
        invoke_confirm=lambda op, event, **kw: asked.append(kw) or {"RUNNING_MODAL"})
    context = types.SimpleNamespace(scene=bl.context.scene, window_manager=window_manager)
    op = types.SimpleNamespace(execute=lambda ctx: executed.append(1) or {"FINISHED"})
    assert keyframes.has_generated(bl.context.scene)
    assert highlight_ops.FOURLEGS_OT_generate_highlight.invoke(op, context, None) == {"RUNNING_MODAL"}
    assert executed == [] and asked[0]["title"] == "Replace the highlight?" and "edits" in asked[0]["message"]
    bl.ops.wm.read_factory_settings(use_empty=True)
    context.scene = bl.context.scene
    assert not keyframes.has_generated(bl.context.scene)
    assert highlight_ops.FOURLEGS_OT_generate_highlight.invoke(op, context, None) == {"FINISHED"}
    assert executed == [1] and len(asked) == 1
