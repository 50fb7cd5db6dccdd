"""``fourlegs bench render``: the kernel generations side by side, the work/floor table and the
busy-process rows (tiny configurations; the figures themselves are for docs/benchmarks.md)."""
from __future__ import annotations

import json

from fourlegs_bench.render_floor import FLOPS_PER_BLENDED_PAIR, FLOPS_PER_REJECTED_PAIR, floor_ms, measure_peak
from fourlegs_engine.commands.main import main

TINY = ["bench", "render", "--sizes", "600", "--outputs", "rgb,features", "--repeats", "1", "--channels", "8",
        "--threads", "1", "--resolution", "64x36", "--skip-baselines", "--skip-knobs"]


def test_bench_render_prints_both_kernels_and_the_ratio_to_the_floor(tmp_path, capsys):
    js = tmp_path / "b.json"
    assert main(TINY + ["--json", str(js)]) == 0
    records = json.loads(js.read_text())
    speed = [r for r in records if r["part"] == "speed"]
    assert {(r["output"], r["mode"], r["kernel"]) for r in speed} == {
        (o, m, k) for o in ("rgb", "features") for m in ("forward", "backward") for k in ("v1", "v2")}
    floor = [r for r in records if r["part"] == "floor"]
    assert {(r["output"], r["kernel"]) for r in floor} == {(o, k) for o in ("rgb", "features") for k in ("v1", "v2")}
    for r in floor:
        assert r["in_boxes"] >= r["in_footprints"] >= r["blended"] > 0 and r["evaluated"] >= r["blended"]
        assert r["peak_gflops"] > 0 and r["peak_gexp_per_s"] > 0
        assert r["floor_flop_ms"] > 0 and r["floor_exp_ms"] > 0
        assert abs(r["x_flop_floor"] - r["cpu_ms_median"] / r["floor_flop_ms"]) <= 0.051 * r["x_flop_floor"] + 0.1
    out = capsys.readouterr().out
    assert "| kernel |" in out and "× flop floor" in out and "| v1 |" in out and "| v2 |" in out
    assert main(TINY + ["--kernels", "v3"]) == 2


def test_floor_arithmetic():
    work = {"in_boxes": 1000, "in_footprints": 600, "blended": 400}
    flop, exp = floor_ms(work, {"gflops": 1.0, "gexp_per_s": 0.001}, channels=3)
    assert flop == (400 * (FLOPS_PER_BLENDED_PAIR + 6) + 600 * FLOPS_PER_REJECTED_PAIR) / 1e9 * 1e3
    assert exp == 600 / 1e6 * 1e3
    peak = measure_peak(repeats=1, matmul_side=128, exp_elements=1 << 14)
    assert peak["gflops"] > 0.1 and peak["gexp_per_s"] > 0.001


def test_bench_render_busy_rows_run_each_policy_in_a_fresh_process(tmp_path):
    js = tmp_path / "busy.json"
    assert main(TINY + ["--skip-floor", "--kernels", "v2", "--busy", "--busy-n", "400", "--busy-threads", "2",
                        "--json", str(js)]) == 0
    busy = [r for r in json.loads(js.read_text()) if r["part"] == "busy"]
    assert {(r["policy"], r["competitor"]) for r in busy} == {
        (p, c) for p in ("passive", "openmp-default") for c in (False, True)}
    for r in busy:
        assert r["omp_wait_policy"] == ("PASSIVE" if r["policy"] == "passive" else "default")
        assert r["ms_median"] > 0 and r["step_threads"] == 2
        assert r["x_alone"] == 1.0 or r["competitor"]
