"""``fourlegs bench render`` on a tiny configuration: records, tables, plot, and refusal to overwrite."""
from __future__ import annotations

import json

import pytest

from fourlegs_engine.commands.main import main
from fourlegs_bench.render_scene import make_bench_scene

TINY = ["bench", "render", "--sizes", "400", "--outputs", "rgb,features", "--repeats", "1", "--channels", "8",
        "--threads", "1",
        "--resolution", "64x36", "--small-n", "150", "--small-resolution", "48x27"]


def test_bench_render_writes_json_markdown_and_plot(tmp_path, capsys):
    js, md, png = tmp_path / "b.json", tmp_path / "b.md", tmp_path / "b.png"
    assert main(TINY + ["--json", str(js), "--markdown", str(md), "--plot", str(png)]) == 0
    records = json.loads(js.read_text())
    for r in records:
        assert {"n", "output", "mode", "device", "backend", "ms_median", "peak_mb"} <= set(r)
        assert r["ms_median"] > 0
    speed = [r for r in records if r["part"] == "speed"]
    assert {(r["output"], r["mode"]) for r in speed} == {(o, m) for o in ("rgb", "features")
                                                         for m in ("forward", "backward")}
    base = [r for r in records if r["part"] == "baseline"]
    assert {r["impl"] for r in base} == {"oracle_float64", "dense_tile", "fast"}
    knobs = [r for r in records if r["part"] == "knob"]
    exact = [r for r in knobs if r["knob"] == "tile_size" or r["value"] in ("opacity", "float32")]
    assert exact and all(r["max_abs_error"] < 1e-4 for r in exact)  # exact settings agree with the oracle
    three_sigma = [r for r in knobs if r["value"] == "3sigma"]
    assert all(r["max_abs_error"] >= max(e["max_abs_error"] for e in exact) for r in three_sigma)
    assert "| knob | value |" in md.read_text() and png.stat().st_size > 1000
    assert "Accuracy knobs" in capsys.readouterr().out
    # existing outputs are not replaced unless asked
    assert main(TINY + ["--skip-baselines", "--skip-knobs", "--json", str(js)]) == 2


def test_bench_render_rejects_bad_arguments(capsys):
    assert main(["bench", "render", "--outputs", "rgb,normals"]) == 2
    assert "--outputs" in capsys.readouterr().err
    assert main(["bench", "render", "--sizes", "ten"]) == 2


def test_bench_scene_is_deterministic_and_spread_like_a_capture():
    a, b = make_bench_scene(3000, feature_dim=4), make_bench_scene(3000, feature_dim=4)
    assert (a.means == b.means).all() and (a.features == b.features).all()
    scales = a.log_scales.exp()
    assert 0.005 < scales.median().item() < 0.02  # around 1 cm
    on_floor = (a.means[:, 2].abs() < 0.03).float().mean().item()
    assert 0.3 < on_floor < 0.45  # the floor
    people = (a.means[:, :2].norm(dim=1) < 3.2) & (a.means[:, 2] > 0.05)
    assert people.float().mean().item() > 0.4  # person-sized clusters standing on it
