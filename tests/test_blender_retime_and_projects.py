"""A shot's marker retimes its shot; a project (.blend + scene + outputs) keeps working when it moves."""
from __future__ import annotations

import importlib.util
import json
import math
import shutil

import numpy as np
import pytest

from _blender_helpers import bl, bpy_addon, hand_plan, orbit_key, tiny_scene  # noqa: F401

pytestmark = pytest.mark.blender
HAS_TORCH = importlib.util.find_spec("torch") is not None


def _orbit_plan(arc_deg: float = 90.0) -> dict:
    """hand_plan with a rigid, sine-eased bullet-time orbit at frames 7-15 (the planner's, rig-able)."""
    plan = hand_plan(desaturate=True)
    f0, f1 = 7, 15
    angles = [math.radians(arc_deg) * (0.5 - 0.5 * math.cos(math.pi * (f - f0) / (f1 - f0))) for f in range(f0, f1 + 1)]
    plan["shots"][1] = {"name": "bullet", "effect": "bullet_time", "frame_start": f0, "frame_end": f1,
                        "camera_keys": [orbit_key(f, a) for f, a in zip(range(f0, f1 + 1), angles)],
                        "time_keys": [{"frame": f0, "timestep": 2.0}, {"frame": f1, "timestep": 2.0}],
                        "interpolation": "linear",
                        "params": {"arc_deg": arc_deg, "easing": "ease_in_out_sine", "radius_scale": 1.0,
                                   "height_scale": 1.0}}
    plan["frame_end"] = f1
    plan["passes"]["relevancy"] = [[7, 15]]
    plan["desaturate"] = {"ranges": [[7, 15]], "fade_in": 0, "fade_out": 0, "strength": 1.0, "weights": {}}
    return plan


def _pose(scene, frame):
    scene.frame_set(frame)
    cam = scene.camera
    return cam.name, np.array(cam.matrix_world), float(scene.fourlegs.timestep)


def test_moving_a_shot_marker_retimes_the_shot(bl):
    """Bullet-time marker 7 -> 10: the orbit (rig), its frozen scene time, the desaturation and the plan's
    relevancy frames start at 10; the shot before holds until the cut; the timeline grows by 3."""
    from fourlegs_addon import compositor, highlight_ops, importer, render_engine, rig

    importer.import_scene(bl.context.scene, tiny_scene())
    scene = bl.context.scene
    highlight_ops.generate_highlight(scene, _orbit_plan())
    before = {f: _pose(scene, f) for f in range(1, 16)}
    weights = {f: compositor.desaturation_at(scene, f) for f in range(1, 16)}
    marker = scene.timeline_markers["2 bullet"]
    marker.frame = 10  # the editor drags the marker three frames later
    scene.frame_set(1)
    assert scene.frame_end == 18
    for f in range(7, 16):  # the whole shot, three frames later
        name, matrix, t = _pose(scene, f + 3)
        assert name == before[f][0] == rig.CAMERA_NAME or f == 7 and name == before[f][0]
        np.testing.assert_allclose(matrix, before[f][1], atol=1e-5)
        assert t == pytest.approx(before[f][2])
        assert compositor.desaturation_at(scene, f + 3) == pytest.approx(weights[f])
    for f in range(1, 7):  # the shot before is untouched ...
        np.testing.assert_allclose(_pose(scene, f)[1], before[f][1], atol=1e-6)
    for f in (7, 8, 9):  # ... and holds its last frame until the cut
        np.testing.assert_allclose(_pose(scene, f)[1], before[6][1], atol=1e-6)
        assert compositor.desaturation_at(scene, f) == 0.0
    pivot = bl.data.objects[rig.PIVOT_NAME]
    assert (pivot["start_frame"], pivot["end_frame"]) == (10, 18)
    plan = render_engine.plan_of(scene)
    assert plan["shots"][1]["frame_start"] == 10 and plan["passes"]["relevancy"] == [[10, 18]]
    assert plan["frame_end"] == 18 and [k["frame"] for k in plan["shots"][1]["time_keys"]] == [10, 18]

    marker.frame = 5  # and earlier than it was made: the shot before loses its last frames
    scene.frame_set(1)
    assert scene.frame_end == 13
    for f in range(7, 16):
        np.testing.assert_allclose(_pose(scene, f - 2)[1], before[f][1], atol=1e-5)
    np.testing.assert_allclose(_pose(scene, 4)[1], before[4][1], atol=1e-6)
    assert json.loads(bl.data.texts[render_engine.PLAN_TEXT_NAME].as_string())["shots"][0]["frame_end"] == 6


def test_outputs_and_scene_paths_are_relative_to_the_blend(bl, tmp_path):
    """What the main job does before saving its .blend: the scene and the video output become `//`
    paths, so a copied project folder renders into itself."""
    from fourlegs_addon import highlight_ops, importer
    from fourlegs_engine.scene import write_bundle

    project = tmp_path / "project"
    write_bundle(tiny_scene(T=4, N=64), project / "scene")
    importer.import_scene(bl.context.scene, importer.load_engine_scene(project / "scene"), source=str(project / "scene"))
    highlight_ops.fill_from_plan(bl.context.scene, hand_plan(), output=str(project / "highlight.mp4"), fmt="MP4")
    importer.relative_sources(project)
    scene = bl.context.scene
    assert scene.fourlegs.output_path == "//highlight.mp4" and scene.render.filepath == "//highlight.mp4"
    assert importer.source_key(scene.fourlegs.splat_object) == "//scene"


def test_an_unsaved_file_does_not_render_into_the_working_directory(bl, tmp_path, monkeypatch):
    from fourlegs_addon import highlight_ops, importer

    monkeypatch.chdir(tmp_path)
    importer.import_scene(bl.context.scene, tiny_scene())
    highlight_ops.generate_highlight(bl.context.scene, hand_plan(desaturate=False))
    assert bl.context.scene.fourlegs.output_path == "//highlight.mp4" and not bl.data.filepath
    with pytest.raises(RuntimeError, match="not saved yet"):
        bl.ops.fourlegs.render_video()
    assert list(tmp_path.iterdir()) == []
    assert bl.context.scene.fourlegs.status.startswith("error: the output //highlight.mp4")


def _project(bl, root):
    """A project folder: scene bundle, a .blend with a generated highlight, output `//out/clip.png`."""
    from fourlegs_addon import highlight_ops
    from fourlegs_engine.scene import write_bundle

    write_bundle(tiny_scene(T=4, N=200), root / "scene")
    bl.ops.wm.save_as_mainfile(filepath=str(root / "edit.blend"))
    assert bl.ops.fourlegs.import_scene(filepath=str(root / "scene" / "scene.json")) == {"FINISHED"}
    scene = bl.context.scene
    scene.fourlegs.renderer = "FOURLEGS"
    highlight_ops.generate_highlight(scene, hand_plan(desaturate=False))
    scene.frame_end = 2
    scene.fourlegs.output_path, scene.fourlegs.output_format = "//out", "PNG"
    bl.ops.wm.save_mainfile()


@pytest.mark.skipif(not HAS_TORCH, reason="the 4-LEGS Splats engine renders with PyTorch")
def test_a_moved_project_renders_and_a_copied_blend_relinks_its_scene(bl, tmp_path):
    from fourlegs_addon import importer

    _project(bl, tmp_path / "project")
    moved = tmp_path / "deeper" / "project"
    moved.parent.mkdir()
    shutil.move(str(tmp_path / "project"), str(moved))
    importer._SCENES.clear()
    bl.ops.wm.open_mainfile(filepath=str(moved / "edit.blend"))
    assert bl.ops.fourlegs.render_video() == {"FINISHED"}
    assert sorted(p.name for p in (moved / "out").iterdir()) == ["frame_0001.png", "frame_0002.png"]

    # the .blend alone, one folder deeper: its scene is missing until relinked
    (moved / "copy").mkdir()
    shutil.copy(moved / "edit.blend", moved / "copy" / "edit.blend")
    importer._SCENES.clear()
    bl.ops.wm.open_mainfile(filepath=str(moved / "copy" / "edit.blend"))
    scene = bl.context.scene
    scene.frame_set(2)
    obj = scene.fourlegs.splat_object
    assert importer.missing_message(obj)
    assert bl.ops.fourlegs.relink_scene(filepath=str(moved / "scene" / "scene.json")) == {"FINISHED"}
    assert importer.source_key(obj) == "//../scene" and not importer.missing_message(obj)
    assert bl.ops.fourlegs.render_video() == {"FINISHED"}
    assert len(list((moved / "copy" / "out").iterdir())) == 2


def test_relink_refuses_a_scene_of_another_size(bl, tmp_path):
    from fourlegs_engine.scene import write_bundle

    write_bundle(tiny_scene(T=2, N=32), tmp_path / "a")
    write_bundle(tiny_scene(T=2, N=48), tmp_path / "b")
    assert bl.ops.fourlegs.import_scene(filepath=str(tmp_path / "a" / "scene.json")) == {"FINISHED"}
    with pytest.raises(RuntimeError, match="holds 48 Gaussians, the object was made from 32"):
        bl.ops.fourlegs.relink_scene(filepath=str(tmp_path / "b" / "scene.json"))
