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
    from fourlegs_addon import keyframes, operators

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
