"""The main job: `fourlegs highlight` (CLI -> headless bpy subprocess) end to end on a tiny scene."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from _blender_helpers import bpy_addon, child_env, language_bundle  # noqa: F401

QUERY = "the red cube"


def test_cli_process_never_imports_bpy():
    code = ("import sys; from fourlegs_engine.commands.main import build_parser; p = build_parser(); "
            "a = p.parse_args(['highlight', '--demo', 'a ball', '-o', 'x']); "
            "from fourlegs_addon.commands import headless_argv; argv = headless_argv(a); "
            "assert 'bpy' not in sys.modules, 'bpy imported'; print(argv)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=child_env(), timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "'--demo'" in proc.stdout and "'a ball'" in proc.stdout


def test_headless_argv_round_trips_every_option():
    from fourlegs_addon import headless
    from fourlegs_addon.commands import headless_argv

    parser = headless.build_parser()
    args = parser.parse_args(["scene_dir", "q", "--preset", "subtle_desaturate", "-o", "o", "--overwrite",
                              "--resolution", "320x180", "--fps", "12", "--no-effect", "zoom_in",
                              "--encoder", "simulated", "--format", "PNG"])
    again = parser.parse_args(headless_argv(args))
    assert vars(again) == vars(args)


@pytest.mark.parametrize("text", ["640", "640x", "0x360", "641x360", "axb"])
def test_bad_resolution_is_an_input_error(text):
    from fourlegs_addon import headless
    from fourlegs_engine.commands.options import highlight_job_options
    from fourlegs_engine.errors import InputError

    args = headless.build_parser().parse_args(["scene_dir", "q", "-o", "o", "--resolution", text])
    with pytest.raises(InputError, match="--resolution"):
        highlight_job_options(args)


@pytest.mark.blender
@pytest.mark.slow
def test_highlight_end_to_end(tmp_path, request, capsys):
    pytest.importorskip("bpy")
    bundle = language_bundle(tmp_path / "scene")
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "fourlegs_engine.commands.main", "highlight", str(bundle), QUERY, "--preset", "broadcast",
           "-o", str(out), "--resolution", "64x36", "--fps", "3"]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=child_env(), timeout=500)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    names = {p.name for p in out.iterdir()}
    assert {"highlight.mp4", "highlight.blend", "plan.json", "report.json", "scores.png"} <= names
    assert not [n for n in names if n.startswith(".")]  # no temporary files left
    report = json.loads((out / "report.json").read_text())
    plan = json.loads((out / "plan.json").read_text())
    assert report["query"] == QUERY and report["localization"]["found"]
    assert report["resolution"] == [64, 36]
    n_frames = plan["frame_end"] - plan["frame_start"] + 1
    assert report["render"]["frames_rendered"] == n_frames
    relevancy_frames = {f for a, b in plan["passes"]["relevancy"] for f in range(a, b + 1)}
    assert relevancy_frames and set(report["render"]["relevancy_frames"]) == relevancy_frames
    assert len(relevancy_frames) < n_frames  # relevancy is not computed where no effect needs it
    assert {"render", "localize + plan", "blender import"} <= set(report["timings_s"])
    # the video and the .blend, checked with Blender itself (in this process: the add-on is registered)
    bl = request.getfixturevalue("bpy_addon")
    from fourlegs_addon import headless, video

    assert video.movie_frame_count(out / "highlight.mp4") == n_frames
    bl.ops.wm.open_mainfile(filepath=str(out / "highlight.blend"))
    s = bl.context.scene
    cam = bl.data.objects["4-LEGS Highlight Camera"]
    assert len(bl.data.objects["tiny"].data.vertices) == 200
    assert cam.animation_data is not None and cam.animation_data.action is not None
    assert s.camera == cam and s.render.engine == "FOURLEGS_SPLATS"
    assert [s.frame_start, s.frame_end] == [plan["frame_start"], plan["frame_end"]]
    from fourlegs_addon import compositor

    tree = compositor.compositor_tree(s)  # 5.0: a node group on the scene; 4.x: the scene's own tree
    assert tree is not None and compositor.has_desaturation(s)
    assert tree.name == "4-LEGS Compositor" or not compositor.IS_50
    assert "fourlegs_plan.json" in bl.data.texts
    # the panel as the job left it: query, segments, peak, the s_t plot; the output is the video it made
    props = s.fourlegs
    assert props.query == QUERY and props.found
    assert [props.segment_start, props.segment_end] == plan["localization"]["segment"]
    assert props.peak == plan["localization"]["peak"]
    assert [[g.start, g.end] for g in props.segments] == plan["localization"]["segments"]
    # relative to the .blend, so the project folder can move (issue #31)
    assert props.output_path == "//highlight.mp4" and s.render.image_settings.file_format == "FFMPEG"
    assert bl.path.abspath(props.output_path) == str(out / "highlight.mp4")
    assert bl.data.images["fourlegs_scores"].packed_file is not None
    # the saved file re-opens its scene from disk: the timeline drives the point cloud again
    import numpy as np

    from fourlegs_addon import importer

    obj = bl.data.objects["tiny"]
    assert importer.source_key(obj) == "//../scene"  # relative to the .blend: the project can move
    mid = (plan["frame_start"] + plan["frame_end"]) // 2
    s.frame_set(mid)
    co = np.empty(len(obj.data.vertices) * 3, np.float32)
    obj.data.vertices.foreach_get("co", co)
    means = importer.engine_scene_for(obj).gaussians.means
    np.testing.assert_allclose(co.reshape(-1, 3), importer.blend_timestep(means, s.fourlegs.timestep), atol=1e-5)
    bl.ops.wm.read_factory_settings(use_empty=True)
    # existing outputs are refused (one clear line, no traceback) before any work, and left untouched
    mtime = (out / "highlight.mp4").stat().st_mtime_ns
    assert headless.main(cmd[4:]) == 2
    assert "already exists" in capsys.readouterr().err
    assert (out / "highlight.mp4").stat().st_mtime_ns == mtime


def test_plan_digest_ignores_float_noise_but_not_changes():
    from _blender_helpers import hand_plan
    from fourlegs_engine.api import plan_digest

    plan = hand_plan()
    noisy = hand_plan()
    noisy["localization"]["action_centre"] = [1e-13, -1e-13, 2e-14]
    noisy["shots"][1]["camera_keys"][2]["c2w"][0][3] += 1e-12
    noisy["messages"] = ["a note"]
    assert plan_digest(noisy) == plan_digest(plan)
    changed = hand_plan()
    changed["shots"][1]["camera_keys"][2]["c2w"][0][3] += 0.01
    assert plan_digest(changed) != plan_digest(plan)
