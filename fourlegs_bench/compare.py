"""``fourlegs bench compare``: the rows of several ``bench accuracy-time`` runs side by side.

One accuracy-time run answers a handful of queries on one synthetic scene, so a single fragile query
can move a row by several vAP points. Comparing runs on several scene seeds tells a real difference
from that noise: each row's metric per run, its mean over the runs that have it, and its ratio to a
reference row (e.g. ``optimize 2000 it``) — the ratio of the means over the runs both rows share, and
the per-run ratios with the runs where the row is below ``target`` × the reference.

Cost per row: ``distill_s_per_timestep`` where the run recorded it (distillation rows), else the
row's query ``seconds``; the cost is averaged over runs like the metric.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fourlegs_engine.errors import InputError
from fourlegs_engine.fileio import atomic_path
from .metrics import METRIC_NAMES

DEFAULT_TARGET = 0.95


def load_report(path: str | Path) -> dict[str, Any]:
    """An ``accuracy_time.json`` written by ``fourlegs bench accuracy-time``, checked."""
    path = Path(path)
    if path.is_dir():
        path = path / "accuracy_time.json"
    try:
        report = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError("no such file (expected an accuracy_time.json or its directory)", file=path) from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"not readable as JSON: {exc}", file=path) from None
    if not isinstance(report, dict) or report.get("benchmark") != "accuracy-time":
        raise InputError("not an accuracy-time report ('benchmark' is not 'accuracy-time')", file=path,
                         field="benchmark")
    rows = report.get("rows")
    if not isinstance(rows, list) or not rows:
        raise InputError("no rows", file=path, field="rows")
    for i, row in enumerate(rows):
        where = f"rows[{i}]"
        if not isinstance(row, dict) or not isinstance(row.get("name"), str) or not isinstance(row.get("group"), str):
            raise InputError("a row needs a 'group' and a 'name'", file=path, field=where)
        metrics = row.get("metrics")
        if not isinstance(metrics, dict):
            raise InputError("missing 'metrics'", file=path, field=where)
        for name, value in metrics.items():
            mean = value.get("mean") if isinstance(value, dict) else None
            if not isinstance(mean, (int, float)) or not np.isfinite(mean):
                raise InputError(f"metric {name!r} has no finite 'mean'", file=path, field=f"{where}.metrics")
    report["_path"] = str(path)
    return report


def _label(report: dict[str, Any], index: int) -> str:
    scene = report.get("scene") or {}
    return str(scene.get("name") or f"run {index}")


def _cost(row: dict[str, Any]) -> float | None:
    value = row.get("distill_s_per_timestep")
    if value is None:
        value = row.get("seconds")
    return float(value) if isinstance(value, (int, float)) and np.isfinite(value) else None


def compare_reports(reports: Sequence[dict[str, Any]], *, metric: str = "vAP", reference: str | None = None,
                    groups: Sequence[str] | None = None, target: float = DEFAULT_TARGET) -> dict[str, Any]:
    """Rows of ``reports`` (from :func:`load_report`) side by side.

    Returns ``{"metric", "runs": [labels], "reference", "target", "rows": [...]}`` where each row has
    ``group``, ``name``, ``values`` (metric mean in [0, 1] per run, None where the run lacks the row),
    ``mean``, ``cost`` (mean seconds) and, with a reference, ``ratio`` (mean over shared runs / the
    reference's mean over them; None when that mean is 0), ``run_ratios`` and ``below_target`` (labels
    of the runs where the row is below ``target`` × the reference).
    """
    if metric not in METRIC_NAMES:
        raise InputError(f"unknown metric {metric!r} (choose from {', '.join(METRIC_NAMES)})", field="--metric")
    if not reports:
        raise InputError("no reports to compare", field="reports")
    labels = [_label(r, i) for i, r in enumerate(reports)]
    seen: dict[str, int] = {}
    for i, label in enumerate(labels):  # two runs of one scene stay apart
        seen[label] = seen.get(label, 0) + 1
        if seen[label] > 1:
            labels[i] = f"{label} ({seen[label]})"
    table: dict[tuple[str, str], dict[str, Any]] = {}
    for k, report in enumerate(reports):
        for row in report["rows"]:
            if groups and row["group"] not in groups:
                continue
            entry = table.setdefault((row["group"], row["name"]), {"group": row["group"], "name": row["name"],
                                                                   "values": [None] * len(reports),
                                                                   "costs": [None] * len(reports)})
            value = row["metrics"].get(metric, {}).get("mean")
            entry["values"][k] = None if value is None else float(value)
            entry["costs"][k] = _cost(row)
    if not table:
        raise InputError(f"no rows in groups {list(groups or [])}", field="--groups")
    ref_entry = None
    if reference is not None:
        matches = [e for e in table.values() if e["name"] == reference]
        if not matches:
            names = ", ".join(dict.fromkeys(e["name"] for e in table.values()))
            raise InputError(f"no row named {reference!r} (rows: {names})", field="--reference")
        ref_entry = matches[0]
    rows = []
    for entry in table.values():
        vals = [v for v in entry["values"] if v is not None]
        costs = [c for c in entry["costs"] if c is not None]
        row = {"group": entry["group"], "name": entry["name"], "values": entry["values"],
               "mean": float(np.mean(vals)) if vals else None, "runs": len(vals),
               "cost": float(np.mean(costs)) if costs else None}
        if ref_entry is not None:
            shared = [k for k in range(len(reports))
                      if entry["values"][k] is not None and ref_entry["values"][k] is not None]
            ref_mean = float(np.mean([ref_entry["values"][k] for k in shared])) if shared else 0.0
            row["ratio"] = (float(np.mean([entry["values"][k] for k in shared])) / ref_mean
                            if shared and ref_mean > 0 else None)
            row["run_ratios"] = [entry["values"][k] / ref_entry["values"][k]
                                 if k in shared and ref_entry["values"][k] > 0 else None
                                 for k in range(len(reports))]
            row["below_target"] = [labels[k] for k in shared
                                   if entry["values"][k] < target * ref_entry["values"][k]]
        rows.append(row)
    return {"metric": metric, "runs": labels, "paths": [r.get("_path") for r in reports],
            "reference": reference, "target": target, "rows": rows}


def _pct(value: float | None) -> str:
    return "" if value is None else f"{100 * value:.1f}"


def compare_markdown(result: dict[str, Any]) -> str:
    """The comparison as a Markdown table (metric in %, ratio to the reference in %)."""
    metric, ref = result["metric"], result["reference"]
    head = ["group", "row"] + [f"{metric} {r}" for r in result["runs"]] + [f"mean {metric}", "mean s"]
    if ref is not None:
        head += [f"mean / {ref}", f"runs below {100 * result['target']:.0f}%"]
    lines = [f"{metric} of each row per run (%), its mean over the runs that have it, and its mean cost "
             "(distillation s per timestep for distillation rows, query s otherwise)"
             + (f"; ratio = mean over the runs shared with `{ref}` / its mean over them" if ref else ""), "",
             "| " + " | ".join(head) + " |", "|---|---|" + "---:|" * (len(head) - 2)]
    for row in result["rows"]:
        cells = [row["group"], row["name"]] + [_pct(v) for v in row["values"]]
        cells += [_pct(row["mean"]), "" if row["cost"] is None else f"{row['cost']:.2f}"]
        if ref is not None:
            cells += ["" if row["ratio"] is None else f"{100 * row['ratio']:.0f}%",
                      f"{len(row['below_target'])} / {sum(r is not None for r in row['run_ratios'])}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def compare_plot(result: dict[str, Any], path: str | Path, *, overwrite: bool = True) -> Path:
    """Mean metric against mean cost per row (log x), each run's value as a faint point."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    rows = [r for r in result["rows"] if r["mean"] is not None and r["cost"] is not None]
    fig, ax = plt.subplots(figsize=(7, 4.5))
    try:
        for i, row in enumerate(rows):
            color = plt.get_cmap("tab10")(i % 10)
            x = max(row["cost"], 1e-3)
            runs = [100 * v for v in row["values"] if v is not None]
            ax.scatter([x] * len(runs), runs, color=color, alpha=0.3, s=14)
            ax.scatter([x], [100 * row["mean"]], color=color, s=40, zorder=3, label=row["name"])
        ax.set_xscale("log")
        ax.set_xlabel("seconds (distillation: per timestep)")
        ax.set_ylabel(f"{result['metric']} (%)")
        ax.set_title(f"{result['metric']} over {len(result['runs'])} runs (faint: each run, solid: mean)")
        ax.legend(fontsize=7, loc="best")
        fig.tight_layout()
        with atomic_path(path, overwrite=overwrite) as tmp:
            fig.savefig(tmp, format="png")
    finally:
        plt.close(fig)
    return path


def _command_line(args: Any) -> str:
    """The command that reproduces this comparison (for the Markdown file)."""
    import shlex
    words = ["fourlegs", "bench", "compare", *map(str, args.reports)]
    for flag, value, default in (("--reference", args.reference, None), ("--metric", args.metric, "vAP"),
                                 ("--groups", args.groups, None), ("--target", args.target, DEFAULT_TARGET),
                                 ("--out", args.out, None)):
        if value != default:
            words += [flag, str(value)]
    return " ".join(shlex.quote(w) for w in words)


def run_compare_cli(args: Any) -> int:
    from fourlegs_engine.errors import OutputExistsError
    from fourlegs_engine.fileio import write_json_atomic

    reports = [load_report(p) for p in args.reports]
    groups = [g.strip() for g in args.groups.split(",") if g.strip()] if args.groups else None
    result = compare_reports(reports, metric=args.metric, reference=args.reference, groups=groups,
                             target=args.target)
    table = compare_markdown(result)
    if args.out:
        prefix = Path(args.out)
        outputs = [prefix.with_suffix(s) for s in (".json", ".md", ".png")]
        for p in outputs:
            if p.exists() and not args.overwrite:
                raise OutputExistsError(p)
        prefix.parent.mkdir(parents=True, exist_ok=True)
        write_json_atomic(outputs[0], result, overwrite=True)
        command = _command_line(args)
        with atomic_path(outputs[1]) as tmp:
            tmp.write_text(f"Command: `{command}`\n\n{table}\n", encoding="utf-8")
        compare_plot(result, outputs[2])
    print(table)
    if args.out:
        print(f"\nwrote {', '.join(str(p) for p in outputs)}")
    return 0
