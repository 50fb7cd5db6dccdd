"""The main job's engine half (``fourlegs_engine.highlight_job``) without Blender: the stage timer, the
plan and plot it writes, the report that finishes it, and the command line's translation into its options."""
from __future__ import annotations

import json
import time

import pytest

from _blender_helpers import language_bundle
from fourlegs_engine import api
from fourlegs_engine.commands.options import add_highlight_arguments, highlight_job_options
from fourlegs_engine.fileio import OUTPUTS_MARKER
from fourlegs_engine.highlight_job import DEMO_RESOLUTION, job_outputs

QUERY = "the red cube"


def test_stage_timer_records_wall_and_cpu_seconds_per_stage():
    timer = api.StageTimer()
    with timer("busy"):
        end = time.thread_time() + 0.05  # this thread's CPU: other threads of the process may add theirs
        while time.thread_time() < end:
            pass
    with timer("sleep"):
        time.sleep(0.05)
    with pytest.raises(KeyError), timer("failed"):
        raise KeyError("x")
    assert list(timer.timings) == list(timer.cpu_timings) == ["busy", "sleep", "failed"]
    assert timer.cpu_timings["busy"] >= 0.04 and timer.timings["busy"] >= 0.04
    assert timer.timings["sleep"] >= 0.04 and timer.cpu_timings["sleep"] < timer.timings["sleep"]
    # every figure is rounded to the millisecond, so the sum of two may exceed the total by 1 ms
    assert timer.total_seconds() >= timer.timings["busy"] + timer.timings["sleep"] - 0.0011


def test_command_line_becomes_job_options():
    import argparse

    parser = argparse.ArgumentParser()
    add_highlight_arguments(parser)
    demo = highlight_job_options(parser.parse_args(["q", "--demo", "--demo-size", "tiny", "-o", "o"]))
    assert (demo.scene, demo.demo, demo.resolution, demo.render_threads) == (None, "tiny", None, 1)
    args = parser.parse_args(["s", "q", "-o", "o", "--resolution", "320x180", "--no-effect", "zoom_in",
                              "--encoder", "simulated", "--render-threads", "0", "--format", "PNG"])
    opts = highlight_job_options(args)
    assert (opts.scene, opts.demo, opts.resolution, opts.no_effect) == ("s", None, (320, 180), ("zoom_in",))
    assert opts.encoder.name == "simulated" and opts.render_threads is None
    assert job_outputs("o", "PNG")["video"].name == "frames" and job_outputs("o")["video"].name == "highlight.mp4"
    assert DEMO_RESOLUTION == (640, 360)


def test_prepare_and_finish_write_plan_plot_and_report(tmp_path):
    bundle = language_bundle(tmp_path / "scene")
    out = tmp_path / "out"
    options = api.HighlightJobOptions(query=QUERY, output=out, scene=str(bundle), resolution=(64, 36), fps=3)
    timer = api.StageTimer()
    job = api.prepare_highlight_job(options, timer)
    plan = json.loads((out / "plan.json").read_text())
    assert plan == json.loads(json.dumps(job.plan))
    assert plan["resolution"] == [64, 36] and plan["localization"]["found"]
    assert (out / "scores.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / OUTPUTS_MARKER).is_file()  # claimed, not finished yet
    assert {"scene", "open query engine", "localize + plan"} <= set(timer.timings)

    report = api.finish_highlight_job(job, {"frames_rendered": 0}, timer, versions={"blender": "x"})
    assert json.loads((out / "report.json").read_text()) == report
    assert not (out / OUTPUTS_MARKER).exists()
    assert report["localization"] == plan["localization"] and report["render"] == {"frames_rendered": 0}
    assert set(report["timings_s"]) == set(report["cpu_timings_s"]) == set(timer.timings)
    assert report["versions"]["blender"] == "x" and "torch" in report["versions"]
    assert report["query_paths"] == {"temporal": "sketch", "spatial": "fast"}  # the engine's defaults
    assert set(report["outputs"]) == {"plan", "plot", "report"}  # the renderer wrote no video or .blend here
    with pytest.raises(api.OutputExistsError):  # a finished job is not overwritten
        api.prepare_highlight_job(options, api.StageTimer())
