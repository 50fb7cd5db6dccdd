"""What an editor does after the first Generate: pick another segment, reopen the file, move a shot's
marker, move the project folder. Real bpy, a real (hand-built) language field and the real planner."""
from __future__ import annotations

import numpy as np
import pytest

from _blender_helpers import bl, bpy_addon, language_bundle  # noqa: F401

pytestmark = pytest.mark.blender
pytest.importorskip("torch")

QUERY = "red cube"


def _two_segment_bundle(path, T=12):
    """The red cube is relevant at timesteps 1-2 and again at 7-10 (the longer segment)."""
    language_bundle(path, T=T, N=200, query_label=QUERY)
    lat = np.load(path / "language" / "latents.npy")
    lat[:, :, :] = [0.0, 1.0]
    lat[[1, 2, 7, 8, 9, 10], :100] = [1.0, 0.0]
    np.save(path / "language" / "latents.npy", lat)
    return path


def _import_and_query(bl, path, preset="broadcast"):
    assert bl.ops.fourlegs.import_scene(filepath=str(path / "scene.json")) == {"FINISHED"}
    props = bl.context.scene.fourlegs
    props.query, props.preset = QUERY, preset
    assert bl.ops.fourlegs.run_query() == {"FINISHED"}
    return props


def test_the_picked_segment_drives_generate(bl, tmp_path):
    from fourlegs_addon import render_engine

    props = _import_and_query(bl, _two_segment_bundle(tmp_path / "scene"))
    segments = [(s.start, s.end) for s in props.segments]
    assert len(segments) == 2 and (props.segment_start, props.segment_end) == segments[props.segment_index]
    other = 1 - props.segment_index
    props.segment_index = other  # the editor picks the other segment in the list
    assert bl.ops.fourlegs.generate_highlight() == {"FINISHED"}
    loc = render_engine.plan_of(bl.context.scene)["localization"]
    a, b = segments[other]
    assert tuple(loc["segment"]) == (a, b) and loc["peak"] == (a + b) // 2
    held = [k["timestep"] for shot in render_engine.plan_of(bl.context.scene)["shots"]
            if shot["effect"] == "bullet_time" for k in shot["time_keys"]]
    assert held and all(t == (a + b) // 2 for t in held)  # bullet-time freezes the picked segment's peak


def test_generate_after_reopening_reuses_the_stored_localization(bl, tmp_path, monkeypatch):
    from fourlegs_addon import query_ops, querying, render_engine
    from fourlegs_engine.query.engine import QueryEngine

    props = _import_and_query(bl, _two_segment_bundle(tmp_path / "scene"))
    assert bl.ops.fourlegs.generate_highlight() == {"FINISHED"}
    first = render_engine.plan_of(bl.context.scene)
    blend = tmp_path / "project.blend"
    bl.ops.wm.save_as_mainfile(filepath=str(blend))
    bl.ops.wm.open_mainfile(filepath=str(blend))
    query_ops._LOCALIZERS.clear()  # a new Blender session: nothing in memory
    querying._ENGINES.clear()
    calls = []
    real = QueryEngine.localize
    monkeypatch.setattr(QueryEngine, "localize", lambda self, *a, **k: calls.append(a) or real(self, *a, **k))
    assert bl.ops.fourlegs.generate_highlight() == {"FINISHED"}
    assert calls == []
    again = render_engine.plan_of(bl.context.scene)
    assert again["localization"]["segment"] == first["localization"]["segment"]
    for s1, s2 in zip(first["shots"], again["shots"]):
        np.testing.assert_allclose([k["c2w"] for k in s1["camera_keys"]], [k["c2w"] for k in s2["camera_keys"]],
                                   atol=1e-9)
    del props


def test_main_job_and_panel_plan_the_same_orbit_rig_and_marker_bindings(bl, tmp_path):
    """The main job hands the planner the query engine itself, the panel Run Query's result: the same
    framed orbit, and in both a rig whose camera follows the plan and whose marker is bound to it."""
    from fourlegs_addon import convert, highlight_ops, importer, planning, querying, render_engine, rig

    path = _two_segment_bundle(tmp_path / "scene")
    props = _import_and_query(bl, path)
    assert bl.ops.fourlegs.generate_highlight() == {"FINISHED"}
    panel = render_engine.plan_of(bl.context.scene)
    engine = querying.open_query_engine(importer.engine_scene_for(props.splat_object))
    main = planning.make_plan(importer.engine_scene_for(props.splat_object), engine, QUERY, "broadcast")
    for s1, s2 in zip(panel["shots"], main["shots"]):
        assert s1["effect"] == s2["effect"]
        np.testing.assert_allclose([k["c2w"] for k in s1["camera_keys"]], [k["c2w"] for k in s2["camera_keys"]],
                                   atol=1e-6)
    orbit = next(s for s in main["shots"] if s["effect"] == "bullet_time")
    assert orbit["params"]["rigid"] is False  # framed about the action region

    bindings = []
    for plan in (panel, main):
        bl.ops.wm.read_factory_settings(use_empty=True)
        importer.import_scene(bl.context.scene, importer.load_engine_scene(path), source=str(path))
        highlight_ops.generate_highlight(bl.context.scene, plan)
        scene = bl.context.scene
        cam = bl.data.objects[rig.CAMERA_NAME]
        bindings.append({m.name: m.camera.name if m.camera else None for m in scene.timeline_markers})
        for key in orbit["camera_keys"]:
            scene.frame_set(key["frame"])
            assert scene.camera == cam
            c2w = convert.blender_to_opencv_c2w(np.array(cam.matrix_world))
            np.testing.assert_allclose(c2w[:3, 3], np.asarray(key["c2w"])[:3, 3], atol=2e-3)
            if key["frame"] >= orbit["frame_start"] + (orbit["frame_end"] - orbit["frame_start"]) / 3:
                np.testing.assert_allclose(c2w[:3, :3], np.asarray(key["c2w"])[:3, :3], atol=2e-3)
            lens = cam.data.lens
            assert lens == pytest.approx(key["lens_mm"], rel=1e-3)
    assert bindings[0] == bindings[1] and rig.CAMERA_NAME in bindings[0].values()
