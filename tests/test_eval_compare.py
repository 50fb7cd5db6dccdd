"""``fourlegs bench compare``: rows of several accuracy-time runs side by side."""
from __future__ import annotations

import json

import pytest

from fourlegs_engine.commands.main import main
from fourlegs_engine.errors import InputError
from fourlegs_bench.compare import compare_markdown, compare_reports, load_report


def _row(group, name, vap, tiou=0.2, seconds=1.0, per_t=None):
    metrics = {"vAP": {"mean": vap, "std": 0.01}, "tIoU": {"mean": tiou, "std": 0.0}}
    return {"group": group, "name": name, "metrics": metrics, "seconds": seconds, "distill_s_per_timestep": per_t}


def _report(scene, rows):
    return {"benchmark": "accuracy-time", "scene": {"name": scene}, "rows": rows}


def _write(tmp_path, name, report):
    d = tmp_path / name
    d.mkdir()
    (d / "accuracy_time.json").write_text(json.dumps(report))
    return d


@pytest.fixture
def reports():
    return [
        _report("s0", [_row("reference", "exact", 0.16, seconds=3.0), _row("distill", "lift", 0.17, per_t=0.2),
                       _row("distill", "optimize 2000 it", 0.204, per_t=50.0)]),
        _report("s1", [_row("reference", "exact", 0.17, seconds=2.0), _row("distill", "lift", 0.10, per_t=0.4),
                       _row("distill", "optimize 2000 it", 0.154, per_t=60.0),
                       _row("distill", "lift + kNN blur", 0.20, per_t=0.3)]),
    ]


def test_means_ratios_and_runs_below_target(reports):
    res = compare_reports(reports, reference="optimize 2000 it")
    rows = {r["name"]: r for r in res["rows"]}
    assert res["runs"] == ["s0", "s1"]
    lift = rows["lift"]
    assert lift["values"] == [0.17, 0.10]
    assert lift["mean"] == pytest.approx(0.135)
    assert lift["cost"] == pytest.approx(0.3)                       # distillation s per timestep, averaged
    assert lift["ratio"] == pytest.approx(0.135 / 0.179)
    assert lift["run_ratios"] == [pytest.approx(0.17 / 0.204), pytest.approx(0.10 / 0.154)]
    assert lift["below_target"] == ["s0", "s1"]                     # 83% and 65%
    assert rows["exact"]["cost"] == pytest.approx(2.5)              # query seconds where no distill time
    assert rows["exact"]["below_target"] == ["s0"]                  # 0.16 < 0.95 * 0.204; 0.17 >= 0.95 * 0.154
    # a row missing from a run is compared over the runs both rows share only
    blur = rows["lift + kNN blur"]
    assert blur["values"] == [None, 0.20] and blur["runs"] == 1
    assert blur["ratio"] == pytest.approx(0.20 / 0.154)
    assert blur["run_ratios"][0] is None and blur["below_target"] == []
    assert rows["optimize 2000 it"]["ratio"] == pytest.approx(1.0)


def test_groups_target_and_metric(reports):
    res = compare_reports(reports, reference="optimize 2000 it", groups=["distill"], target=0.6, metric="tIoU")
    assert [r["name"] for r in res["rows"]] == ["lift", "optimize 2000 it", "lift + kNN blur"]
    assert all(r["below_target"] == [] for r in res["rows"])        # tIoU 0.2 everywhere
    assert "ratio" not in compare_reports(reports)["rows"][0]


def test_zero_reference_gives_no_ratio(reports):
    reports[0]["rows"][2]["metrics"]["vAP"]["mean"] = 0.0
    reports[1]["rows"][2]["metrics"]["vAP"]["mean"] = 0.0
    res = compare_reports(reports, reference="optimize 2000 it")
    lift = next(r for r in res["rows"] if r["name"] == "lift")
    assert lift["ratio"] is None and lift["run_ratios"] == [None, None]
    assert "nan" not in compare_markdown(res).lower() and "inf" not in compare_markdown(res).lower()


def test_markdown_has_every_value(reports):
    md = compare_markdown(compare_reports(reports, reference="optimize 2000 it"))
    assert "| distill | lift | 17.0 | 10.0 | 13.5 | 0.30 | 75% | 2 / 2 |" in md
    assert "| distill | lift + kNN blur |  | 20.0 | 20.0 | 0.30 | 130% | 0 / 1 |" in md


def test_bad_input_names_file_and_field(tmp_path, reports):
    with pytest.raises(InputError, match="no such file"):
        load_report(tmp_path / "missing.json")
    (tmp_path / "x.json").write_text("{not json")
    with pytest.raises(InputError, match="x.json: not readable as JSON"):
        load_report(tmp_path / "x.json")
    (tmp_path / "y.json").write_text(json.dumps({"benchmark": "query-speed"}))
    with pytest.raises(InputError, match="y.json: benchmark"):
        load_report(tmp_path / "y.json")
    bad = _report("s", [_row("distill", "lift", 0.1)])
    bad["rows"][0]["metrics"]["vAP"]["mean"] = None
    (tmp_path / "z.json").write_text(json.dumps(bad))
    with pytest.raises(InputError, match=r"z.json: rows\[0\].metrics: metric 'vAP' has no finite 'mean'"):
        load_report(tmp_path / "z.json")
    with pytest.raises(InputError, match="no row named 'optimize 500 it'"):
        compare_reports(reports, reference="optimize 500 it")
    with pytest.raises(InputError, match="unknown metric"):
        compare_reports(reports, metric="accuracy")
    with pytest.raises(InputError, match="no rows in groups"):
        compare_reports(reports, groups=["codebook"])


def test_cli_writes_table_json_plot_and_keeps_outputs(tmp_path, reports, capsys):
    dirs = [_write(tmp_path, f"run{i}", r) for i, r in enumerate(reports)]
    prefix = tmp_path / "out" / "cmp"
    args = ["bench", "compare", *map(str, dirs), "--reference", "optimize 2000 it", "--out", str(prefix)]
    assert main(args) == 0
    assert "| distill | lift | 17.0 | 10.0 | 13.5 |" in capsys.readouterr().out
    saved = json.loads(prefix.with_suffix(".json").read_text())
    assert saved["runs"] == ["s0", "s1"] and len(saved["rows"]) == 4
    md = prefix.with_suffix(".md").read_text()
    assert md.count("\n| ") == 5                                     # header + 4 rows
    assert md.startswith(f"Command: `fourlegs bench compare {dirs[0]} {dirs[1]} --reference 'optimize 2000 it'")
    assert prefix.with_suffix(".png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    before = prefix.with_suffix(".md").read_text()
    assert main(args[:-2] + ["--out", str(prefix), "--metric", "tIoU"]) == 2       # exists, not overwritten
    assert "already exists" in capsys.readouterr().err
    assert prefix.with_suffix(".md").read_text() == before
    assert main(args + ["--metric", "tIoU", "--overwrite"]) == 0
    assert "tIoU s0" in prefix.with_suffix(".md").read_text()
