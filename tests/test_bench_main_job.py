"""`fourlegs bench main-job`: the main job from an empty cache, as a stage table (answer and stages, not seconds)."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from _blender_helpers import child_env
from fourlegs_bench import main_job

#: what the job times, in the order it runs, for a --demo run rendered to MP4 (encode mp4 inside render)
JOB_STAGES = ["scene", "extract features", "train autoencoder", "distil (lift)", "open query engine",
              "localize + plan", "blender import", "generate highlight", "render", "encode mp4", "save .blend"]


def test_stage_rows_follow_the_run_order_and_nest_the_encoder():
    wall = {"scene": 2.0, "render": 30.0, "encode mp4": 5.0, "extract features": 10.0, "localize + plan": 8.0}
    report = {"timings_s": wall, "cpu_timings_s": {"scene": 1.5, "render": 40.0}, "total_seconds": 50.0}
    rows = main_job.stage_rows(report)
    assert [r["stage"] for r in rows] == ["scene", "extract features", "localize + plan", "render", "encode mp4"]
    by = {r["stage"]: r for r in rows}
    assert by["encode mp4"]["inside"] == "render" and by["encode mp4"]["share"] is None
    assert by["render"]["share"] == pytest.approx(0.6) and by["render"]["cpu_s"] == 40.0
    assert by["extract features"]["cpu_s"] is None  # not recorded: shown as a dash, never as 0
    assert "| extract features | 10.0 | – |" in main_job.markdown({
        "command": "c", "bench_command": "b", "job": {"wall_seconds": 51.0, "cpu_seconds": 60.0, "peak_rss_mb": 900.0},
        "report_total_seconds": 50.0, "stages": rows, "answer": {"segment": [28, 38], "peak": 33, "best_view": "cam05"},
        "frames": 242, "resolution": [640, 360], "render_threads": "1", "ae_epochs": [], "machine": "m"})


def test_epoch_rows_accumulate_seconds_and_keep_the_cosines():
    ae = {"loss_history": [0.02, 0.01, 0.009], "cosine_history": [0.80, 0.85, 0.86], "epoch_seconds": [3.0, 3.5, 3.0]}
    rows = main_job.epoch_rows(ae)
    assert [r["cumulative_seconds"] for r in rows] == [3.0, 6.5, 9.5]
    assert [r["heldout_cosine"] for r in rows] == [0.80, 0.85, 0.86]
    assert main_job.epoch_rows({"loss_history": [0.1]})[0]["heldout_cosine"] is None  # an older report
    assert main_job.segment_iou([28, 38], [28, 38]) == 1.0
    assert main_job.segment_iou([0, 9], [5, 14]) == pytest.approx(5 / 15)
    assert main_job.segment_iou(None, [1, 2]) is None


def test_bad_epoch_list_is_one_line(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "fourlegs_engine.commands.main", "bench", "main-job", "-o", str(tmp_path / "b"),
                           "--ae-epochs", "2,zero"], capture_output=True, text=True, env=child_env(), timeout=120)
    assert proc.returncode == 2 and "--ae-epochs" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "b").exists()


@pytest.mark.blender
@pytest.mark.slow
def test_main_job_from_scratch_on_the_tiny_scene(tmp_path):
    pytest.importorskip("bpy")
    out, cache = tmp_path / "bench", tmp_path / "cache"
    cmd = [sys.executable, "-m", "fourlegs_engine.commands.main", "bench", "main-job", "--demo-size", "tiny",
           "--resolution", "64x36", "--fps", "3", "-o", str(out), "--cache", str(cache)]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=child_env(), timeout=900)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    result = json.loads((out / "main_job.json").read_text())
    assert [r["stage"] for r in result["stages"]] == JOB_STAGES
    assert all(r["cpu_s"] is not None for r in result["stages"])
    answer = result["answer"]
    assert answer["found"] and answer["segment"] == [6, 8] and answer["peak"] == 7
    assert result["frames"] == 31 and result["resolution"] == [64, 36]
    assert [r["epoch"] for r in result["ae_epochs"]] == [1, 2, 3, 4]
    assert all(0.0 < r["heldout_cosine"] <= 1.0 for r in result["ae_epochs"])
    assert (out / "job" / "highlight.mp4").is_file() and (out / "ae_epochs.png").is_file()
    assert "| train autoencoder |" in (out / "main_job.md").read_text()
    # the cache was the job's own, so everything ran: features, autoencoder and field were made here
    scene_dirs = [p for p in (cache / "scenes").iterdir() if not p.name.startswith(".")]  # not the run locks
    assert len(scene_dirs) == 1 and (scene_dirs[0] / "language" / "latents.npy").is_file()
    # a second run refuses to overwrite the result, and refuses a cache that is not empty
    again = subprocess.run(cmd, capture_output=True, text=True, env=child_env(), timeout=120)
    assert again.returncode == 2 and "exists" in again.stderr


def test_epoch_sweep_table_says_when_the_query_is_lost():
    base = {"command": "c", "bench_command": "b", "job": {"wall_seconds": 1.0, "cpu_seconds": 1.0, "peak_rss_mb": 1.0},
            "report_total_seconds": 1.0, "stages": [], "frames": 242, "resolution": [640, 360], "render_threads": "1",
            "ae_epochs": [], "machine": "m",
            "answer": {"segment": [28, 38], "peak": 33, "best_view": "cam05", "action_centre": [0.0, 0.0, 0.0]}}
    rows = [{"epochs": 2, "heldout_cosine": 0.872, "train_ae_s": 16.3, "lift_s": 55.5, "localize_s": 38.3,
             "found": False, "segment": None, "peak": None, "best_view": None, "action_centre": None},
            {"epochs": 4, "heldout_cosine": 0.857, "train_ae_s": 30.0, "lift_s": 55.0, "localize_s": 38.0,
             "found": True, "segment": [28, 37], "peak": 33, "best_view": "cam05", "action_centre": [0.0, 0.3, 0.4]}]
    text = main_job.markdown({**base, "ae_sweep": rows})
    assert "| 2 | 0.8720 | 16.3 | 55.5 | 38.3 | no | None | None | – | None | – |" in text
    assert "| 4 | 0.8570 | 30.0 | 55.0 | 38.0 | yes | [28, 37] | 33 | 0.91 | cam05 | 0.500 |" in text
