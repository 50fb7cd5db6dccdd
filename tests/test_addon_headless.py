"""The main job: `fourlegs highlight` (CLI -> headless bpy subprocess) end to end on a tiny scene."""
from __future__ import annotations

import json
import re
import subprocess
import sys

import pytest

from _blender_helpers import bpy_addon, child_env, language_bundle  # noqa: F401

QUERY = "the red cube"


def test_cli_process_never_imports_bpy(tmp_path):
    code = ("import sys; from fourlegs_engine.commands.main import build_parser; p = build_parser(); "
            "a = p.parse_args(['highlight', '--demo', 'a ball', '-o', 'x']); "
            "from fourlegs_engine.commands.options import highlight_job_options; "
            "from fourlegs_addon.commands import headless_command; "
            f"f = {str(tmp_path / 'o.json')!r}; open(f, 'w').write(highlight_job_options(a).to_json()); "
            "cmd = headless_command(f); "
            "assert 'bpy' not in sys.modules, 'bpy imported'; print(cmd)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=child_env(), timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "'--options-json'" in proc.stdout and "'fourlegs_addon.headless'" in proc.stdout
    assert json.loads((tmp_path / "o.json").read_text())["query"] == "a ball"


#: option values that need a format (the rest get one derived from their type or choices)
SAMPLE_VALUES = {"resolution": "320x180", "masks": "a red cube=masks/cube", "device": "cpu"}
#: options that only mean something beside another one
COMPANIONS = {"demo_size": ["--demo"]}


def _highlight_parser():
    from fourlegs_engine.commands.main import build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "command")
    return sub.choices["highlight"]


def _non_default_argv(action) -> list[str]:
    """Command-line words that give ``action`` a valid value other than its default."""
    if action.nargs == 0:  # store_true
        return [action.option_strings[0]]
    if action.dest in SAMPLE_VALUES:
        value = SAMPLE_VALUES[action.dest]
    elif action.choices:
        value = next(c for c in action.choices if c != action.default)
    elif action.type in (int, float) or getattr(action.type, "__name__", "") in ("int", "float"):  # bounded()
        value = str((action.default or 0) + 3)
    else:
        value = f"x-{action.dest}"
    return [action.option_strings[0], value] if action.option_strings else [value]


def _options_of(argv: list[str]):
    from fourlegs_engine.commands.options import highlight_job_options

    return highlight_job_options(_highlight_parser().parse_args(argv))


def _options_arguments():
    return [a for a in _highlight_parser()._actions if a.option_strings and a.dest != "help"]


def test_every_option_of_fourlegs_highlight_changes_the_job_options():
    """An option the parser accepts but the job's options dataclass drops would never reach the child."""
    baseline = ["scene_dir", "q", "-o", "out"]
    for action in _options_arguments():
        extra = COMPANIONS.get(action.dest, [])
        before = _options_of(baseline + extra)
        assert _options_of(baseline + extra + _non_default_argv(action)) != before, action.dest


def test_every_option_reaches_the_headless_job_through_its_options_json(monkeypatch):
    """`fourlegs highlight` with every option at a non-default value: the child's dataclass is the parent's."""
    from fourlegs_addon import commands, headless

    positional = [w for a in _highlight_parser()._actions if not a.option_strings for w in _non_default_argv(a)]
    argv = positional + [w for a in _options_arguments() if a.dest not in ("demo", "scene")
                         for w in _non_default_argv(a)]
    parent = _options_of(argv)
    assert parent.render_threads == 4 and parent.encoder.masks == (("a red cube", "masks/cube"),)
    children = []

    def child(cmd, **kwargs):  # the headless job's own reading of its command line, while the parent's file exists
        assert cmd[:4] == [sys.executable, "-m", "fourlegs_addon.headless", "--options-json"]
        children.append(headless.job_options(cmd[3:]))
        return 0

    monkeypatch.setattr(commands, "run_child", child)
    assert commands.run_highlight(_highlight_parser().parse_args(argv)) == 0
    assert children == [parent]
    assert headless.job_options(argv) == parent  # the job's own command line builds the same dataclass


@pytest.mark.parametrize("text,problem", [
    ("{", "not valid JSON"),
    ('{"query": "q", "output": "o", "colour": "red"}', "unknown field(s) 'colour'"),
    ('{"query": "q", "output": "o", "fps": "fast"}', "fps: expected a finite number"),
    ('{"query": "q", "output": "o", "resolution": [640]}', "resolution: expected 2 values"),
    ('{"query": "q", "output": "o", "encoder": {"batch_size": 1.5}}', "encoder.batch_size: expected an integer"),
])
def test_a_malformed_options_file_is_one_line_naming_the_file_and_field(tmp_path, text, problem):
    from fourlegs_addon import headless
    from fourlegs_engine.errors import InputError

    path = tmp_path / "options.json"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(InputError, match=re.escape(problem)) as info:
        headless.job_options(["--options-json", str(path)])
    assert str(path) in str(info.value)
    with pytest.raises(InputError, match="replaces every other argument"):
        headless.job_options(["--options-json", str(path), "--overwrite"])


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
