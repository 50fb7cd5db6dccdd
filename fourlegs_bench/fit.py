"""``fourlegs bench fit``: held-out camera PSNR/SSIM of ``fourlegs fit`` against seconds per timestep.

Each run is one setting of the fit's knobs. For every run the bench fits the chosen timesteps
(resumable: an interrupted bench continues), times the first timestep and the later ones (wall clock
and process CPU time), renders the test cameras at every timestep and reports PSNR/SSIM per timestep
and their mean, the first-10 / last-10 means (drift) and an extrapolation to the whole sequence. It
writes a Markdown table, JSON, a Pareto plot (mean PSNR against seconds per timestep) and a contact
sheet of test-camera ground truth beside the renders.
"""
from __future__ import annotations

import argparse
import shlex
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from fourlegs_engine.fit.presets import FIT_PRESETS

DEFAULT_DATASET = "../shared/data/panoptic-basketball"
#: name -> knob overrides of FitOptions
PRESET_RUNS = {
    "fast": {"first_iterations": 150, "iterations": 10},
    "default": {},
    "long": {"first_iterations": 600, "iterations": 60, "max_gaussians": 120_000, "init_background": 60_000},
    "accurate": dict(FIT_PRESETS["accurate"]),
}
INT_KNOBS = ("first_iterations", "iterations", "max_iterations", "min_iterations", "max_gaussians", "init_foreground", "init_background",
             "background_stride", "knn", "seed", "clean_plate_samples")
STR_KNOBS = ("init", "device")
BOOL_KNOBS = ("densify",)
FLOAT_KNOBS = ("resolution_scale", "lr_means", "lr_means_later", "lr_colors", "lr_scales", "lr_opacities",
               "lr_rotations", "lr_rotations_later", "lr_camera", "voxel", "grad_threshold", "motion_step_range",
               "knn_lambda", "part_extent", "part_fraction",
               "free_part_fraction", "part_scale", "lr_colors_later")
#: loss weights as knobs: w_rigid=8 sets FitOptions.weights["rigid"] (the others keep their defaults)
WEIGHT_KNOBS = tuple(f"w_{name}" for name in ("im", "seg", "rigid", "rot", "iso", "floor", "plate"))


def register_bench(bench_sub: Any) -> None:
    p = bench_sub.add_parser(
        "fit", help="fourlegs fit on a real capture: test-camera PSNR/SSIM vs seconds per timestep",
        description="Fit the capture once per knob setting, then PSNR/SSIM on the held-out test cameras per "
        "timestep, against seconds per timestep (table, JSON, Pareto plot, contact sheet).")
    p.add_argument("--dataset", default=DEFAULT_DATASET, help=f"capture directory (default {DEFAULT_DATASET})")
    p.add_argument("--out", default="bench-fit", help="output directory (fitted scenes, table, JSON, plots)")
    p.add_argument("--timesteps", default="0:10", help="half-open range a:b (default 0:10)")
    p.add_argument("--runs", default="default",
                   help="runs separated by ';', each a preset name (" + ", ".join(PRESET_RUNS) + ") or "
                   "NAME:knob=value,knob=value (FitOptions fields)")
    p.add_argument("--resolution-scale", type=float, default=0.5, help="fit and evaluation scale (default 0.5)")
    p.add_argument("--sequence-length", type=int, default=150, help="timesteps of the whole sequence (extrapolation)")
    p.add_argument("--contact-timesteps", type=int, default=3, help="timesteps shown in the contact sheet")
    p.set_defaults(func=bench_fit)

    q = bench_sub.add_parser(
        "fit-pareto", help="one Pareto plot and table of the runs of several `bench fit` JSON files",
        description="Merge the records of several `fourlegs bench fit` runs (their fit_bench.json) into one "
        "table and one plot of mean test PSNR, whole frame and ball region, against CPU minutes of the sequence.")
    q.add_argument("json", nargs="+", help="fit_bench.json files")
    q.add_argument("--out", required=True, help="output directory (fit_pareto.png, fit_pareto.md)")
    q.add_argument("--sequence-length", type=int, default=150, help="timesteps of the whole sequence (extrapolation)")
    q.set_defaults(func=bench_fit_pareto)


def parse_runs(text: str) -> list[tuple[str, dict[str, Any]]]:
    from fourlegs_engine.errors import InputError

    runs = []
    for part in (s.strip() for s in text.split(";")):
        if not part:
            continue
        if ":" not in part:
            if part not in PRESET_RUNS:
                raise InputError(f"unknown preset {part!r} (have {', '.join(PRESET_RUNS)})", field="--runs")
            runs.append((part, dict(PRESET_RUNS[part])))
            continue
        name, knobs = part.split(":", 1)
        kw: dict[str, Any] = {}
        for item in (s.strip() for s in knobs.split(",") if s.strip()):
            key, _, value = item.partition("=")
            key = key.strip().replace("-", "_")
            if key not in INT_KNOBS + FLOAT_KNOBS + STR_KNOBS + WEIGHT_KNOBS + BOOL_KNOBS:
                raise InputError(f"unknown knob {key!r}", field="--runs")
            try:
                if key in WEIGHT_KNOBS:
                    from fourlegs_engine.fit import FitOptions
                    weights = kw.setdefault("weights", dict(FitOptions().weights))
                    weights[key[2:]] = float(value)
                elif key in INT_KNOBS:
                    kw[key] = int(value)
                elif key in FLOAT_KNOBS:
                    kw[key] = float(value)
                elif key in STR_KNOBS:
                    kw[key] = value.strip()
                else:
                    kw[key] = value.strip().lower() in ("1", "true", "yes")
            except ValueError:
                raise InputError(f"bad value for {key}: {value!r}", field="--runs") from None
        runs.append((name.strip(), kw))
    if not runs:
        raise InputError("no runs given", field="--runs")
    return runs


class _Timer:
    """Progress callback recording wall and CPU seconds of every finished timestep; with a ``path`` the
    records so far (merged into those a cancelled run left there) are written after each timestep, so a
    resumed run still has the whole sequence's times."""

    def __init__(self, name: str = "", total: int = 0, path: Path | None = None):
        self.wall0, self.cpu0 = time.perf_counter(), time.process_time()
        self.per_timestep: dict[int, dict[str, float]] = {}
        self.name, self.total, self.path = name, total, path

    def __call__(self, ev) -> None:
        if ev.kind != "timestep" or ev.resumed:
            return
        wall, cpu = time.perf_counter(), time.process_time()
        self.per_timestep[ev.timestep] = {"wall_s": wall - self.wall0, "cpu_s": cpu - self.cpu0,
                                          "train_psnr": ev.train_psnr}
        self.wall0, self.cpu0 = wall, cpu
        rec = self.per_timestep[ev.timestep]
        if self.path is not None:
            from fourlegs_engine.fileio import read_json, write_json_atomic

            previous = read_json(self.path) if self.path.is_file() else {}
            finite = {k: (v if np.isfinite(v) else None) for k, v in rec.items()}  # JSON has no NaN
            write_json_atomic(self.path, {**previous, str(ev.timestep): finite})
        print(f"[bench fit] {self.name}: timestep {ev.timestep} fitted ({len(self.per_timestep)}/{self.total}) in "
              f"{rec['wall_s']:.1f} s ({rec['cpu_s']:.1f} CPU s), training PSNR {ev.train_psnr:.2f} dB", flush=True)


def bench_fit(args: argparse.Namespace) -> int:
    import torch

    from fourlegs_engine.errors import InputError
    from fourlegs_engine.fileio import read_json, write_json_atomic
    from fourlegs_engine.fit import Capture, FitOptions, fit_capture
    from fourlegs_engine.commands.fit import parse_timesteps
    from fourlegs_engine.fit.evaluate import evaluate_test_views
    from fourlegs_engine.scene.bundle import is_bundle

    from .real_annotations import ball_mask

    dataset = Path(args.dataset)
    if not dataset.is_dir():
        raise InputError("capture directory not found (pass --dataset)", file=dataset)
    capture = Capture(dataset)
    a, b = parse_timesteps(args.timesteps)
    steps = capture.timestep_range((a, b))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    command = "fourlegs bench fit " + " ".join(shlex.quote(x) for x in sys.argv[3:]) if len(sys.argv) > 2 else ""
    records = []
    for name, knobs in parse_runs(args.runs):
        opts = replace(FitOptions(resolution_scale=args.resolution_scale), timesteps=(steps.start, steps.stop), **knobs)
        scene_dir = out / "scenes" / name
        timing_path = out / "scenes" / f"{name}.timing.json"
        timer = _Timer(name, len(steps), timing_path)
        if not is_bundle(scene_dir):
            print(f"[bench fit] {name}: fitting timesteps {steps.start}:{steps.stop} with {knobs or 'defaults'}",
                  flush=True)
            previous = read_json(timing_path) if timing_path.is_file() else {}
            fit_capture(capture, scene_dir, opts, progress=timer)
            merged = {**previous, **{str(k): v for k, v in timer.per_timestep.items()}}
            write_json_atomic(timing_path, merged)
        init_path = out / "scenes" / f"{name}.init.json"
        if not init_path.is_file():
            write_json_atomic(init_path, measure_initialisation(capture, opts))
        init_stats = read_json(init_path)
        timing = {int(k): v for k, v in read_json(timing_path).items()} if timing_path.is_file() else {}
        keep = sorted({0, len(steps) // 2, len(steps) - 1}) if args.contact_timesteps >= 3 else [0, len(steps) - 1]
        metrics = evaluate_test_views(scene_dir, capture, resolution_scale=opts.resolution_scale,
                                      keep_images_at=tuple(keep[:max(1, args.contact_timesteps)]), region=ball_mask)
        meta = read_json(scene_dir / "scene.json")
        first = timing.get(steps.start, {})
        later = [timing[t] for t in steps[1:] if t in timing]
        # None (JSON null) when only the first timestep was fitted
        later_wall = float(np.mean([v["wall_s"] for v in later])) if later else None
        later_cpu = float(np.mean([v["cpu_s"] for v in later])) if later else None
        per_t = metrics.psnr.mean(1)
        k = min(10, max(1, len(per_t) // 2))
        rec = {
            "run": name, "knobs": knobs, "options": opts.fingerprint(), "timesteps": [steps.start, steps.stop],
            "num_gaussians": int(meta["num_gaussians"]),
            "resolution": [round(capture.width * opts.resolution_scale), round(capture.height * opts.resolution_scale)],
            "test_cameras": metrics.cameras, "torch_threads": torch.get_num_threads(),
            "init_method": opts.init, "init_wall_s": init_stats["wall_s"], "init_cpu_s": init_stats["cpu_s"],
            "init_points": init_stats["points"], "init_foreground_points": init_stats["foreground_points"],
            "init_train_psnr": init_stats["train_psnr"],
            "first_timestep_wall_s": first.get("wall_s"), "first_timestep_cpu_s": first.get("cpu_s"),
            "later_timestep_wall_s": later_wall, "later_timestep_cpu_s": later_cpu,
            "psnr_per_timestep": per_t.round(3).tolist(), "ssim_per_timestep": metrics.ssim.mean(1).round(4).tolist(),
            "psnr_per_camera_first": metrics.psnr[0].round(3).tolist(),
            "psnr_first_timestep": float(per_t[0]), "ssim_first_timestep": float(metrics.ssim[0].mean()),
            "psnr_mean": metrics.mean_psnr, "ssim_mean": metrics.mean_ssim,
            "psnr_first_k": float(per_t[:k].mean()), "psnr_last_k": float(per_t[-k:].mean()), "drift_k": k,
            **ball_record(metrics, k),
            "later_iterations": {t: e.get("iterations") for t, e in
                                 ((meta.get("metadata") or {}).get("fit") or {}).get("later_iterations", {}).items()},
        }
        if first.get("wall_s") is not None and later:
            rec["extrapolated_sequence_wall_min"] = (first["wall_s"] + (args.sequence_length - 1) * later_wall) / 60
            rec["extrapolated_sequence_cpu_min"] = (first["cpu_s"] + (args.sequence_length - 1) * later_cpu) / 60
        if len(steps) == args.sequence_length and all(t in timing for t in steps):  # the whole sequence, measured
            rec["measured_fit_cpu_min"] = sum(timing[t]["cpu_s"] for t in steps) / 60
            rec["measured_fit_wall_min"] = sum(timing[t]["wall_s"] for t in steps) / 60
        records.append(rec)
        _contact_sheet(metrics, out / f"contact_{name}.png", name, region_fn=ball_mask)
        print(f"[bench fit] {name}: first-timestep PSNR {rec['psnr_first_timestep']:.2f} dB, mean "
              f"{rec['psnr_mean']:.2f} dB (ball region {_fmt(rec['ball_psnr_mean'])} dB) over {len(per_t)} timesteps",
              flush=True)
    result = {"command": command, "dataset": str(dataset.resolve()), "records": records}
    write_json_atomic(out / "fit_bench.json", result)
    table = markdown_table(records, args.sequence_length)
    (out / "fit_bench.md").write_text((f"`{command}`\n\n" if command else "") + table + "\n")
    _pareto_plot(records, out / "fit_pareto.png")
    print(table)
    print(f"[bench fit] wrote {out / 'fit_bench.md'}, {out / 'fit_bench.json'}, {out / 'fit_pareto.png'}, "
          f"contact sheets in {out}")
    return 0


def ball_record(metrics, k: int) -> dict[str, Any]:
    """The ball-region figures of one run: PSNR per timestep (None where no test camera sees orange), its
    mean over every (timestep, camera) that does, and the first-k / last-k means of the timesteps that have one."""
    per_t = metrics.region_psnr_per_timestep()
    seen = [v for v in per_t if v is not None]
    kk = min(k, max(1, len(seen) // 2)) if seen else 0
    return {"ball_psnr_per_timestep": [None if v is None else round(v, 3) for v in per_t],
            "ball_pixels_per_timestep": metrics.region_pixels.sum(1).astype(int).tolist(),
            "ball_psnr_mean": metrics.mean_region_psnr,
            "ball_psnr_first_k": float(np.mean(seen[:kk])) if seen else None,
            "ball_psnr_last_k": float(np.mean(seen[-kk:])) if seen else None}


def bench_fit_pareto(args: argparse.Namespace) -> int:
    from fourlegs_engine.errors import InputError
    from fourlegs_engine.fileio import read_json

    records = []
    for path in map(Path, args.json):
        data = read_json(path)
        if not isinstance(data, dict) or not isinstance(data.get("records"), list):
            raise InputError("not a `bench fit` JSON (no records list)", file=path, field="records")
        for r in data["records"]:
            missing = [k for k in ("run", "psnr_mean", "timesteps") if k not in r]
            if missing:
                raise InputError(f"a record lacks {', '.join(missing)}", file=path, field="records")
            a, b = r["timesteps"]
            r = {**r, "run": f"{r['run']} ({a}:{b})"}
            if b - a != args.sequence_length:  # a shorter run's measured minutes are not the sequence's
                r.pop("measured_fit_cpu_min", None)
                r.pop("measured_fit_wall_min", None)
            records.append(r)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    _pareto_plot(records, out / "fit_pareto.png")
    table = pareto_table(records)
    (out / "fit_pareto.md").write_text(table + "\n")
    print(table)
    print(f"[bench fit-pareto] wrote {out / 'fit_pareto.png'}, {out / 'fit_pareto.md'}")
    return 0


def pareto_table(records: list[dict[str, Any]]) -> str:
    """One row per run, cheapest first: CPU minutes of the sequence and the mean test PSNRs."""
    rows = ["| run (timesteps) | knobs | CPU min, sequence | mean PSNR, whole frame | mean PSNR, ball region | "
            "first-k → last-k PSNR | later iterations: mean (min–max) |", "|---|---|---|---|---|---|---|"]
    for r in sorted(records, key=lambda r: (sequence_cpu_minutes(r) is None, sequence_cpu_minutes(r) or 0.0)):
        knobs = ", ".join(f"{k}={v}" for k, v in (r.get("knobs") or {}).items()) or "defaults"
        how = "measured" if r.get("measured_fit_cpu_min") is not None else "extrapolated"
        rows.append(f"| {r['run']} | {knobs} | {_fmt(sequence_cpu_minutes(r), '.1f')} ({how}) | "
                    f"{_fmt(r.get('psnr_mean'))} | {_fmt(r.get('ball_psnr_mean'))} | "
                    f"{_fmt(r.get('psnr_first_k'))} → {_fmt(r.get('psnr_last_k'))} | "
                    f"{_iterations_summary(r.get('later_iterations') or {})} |")
    return "\n".join(rows)


def measure_initialisation(capture, opts) -> dict[str, Any]:
    """The initial cloud of the first timestep on its own: seconds to make it (wall and process CPU),
    its points, and the mean PSNR of the training views rendered from it before any optimisation."""
    import torch

    from fourlegs_engine.fit.model import TrainingFrames, initial_model, render_views
    from fourlegs_engine.fit.losses import psnr

    opts = opts.check()
    steps = capture.timestep_range(opts.timesteps)
    cams_idx = capture.camera_indices("train", opts.cameras)
    cameras = [capture.train.cameras[steps.start][c].scaled(opts.resolution_scale) for c in cams_idx]
    frames = TrainingFrames(capture, steps.start, cams_idx, (cameras[0].width, cameras[0].height), torch.device("cpu"))
    wall0, cpu0 = time.perf_counter(), time.process_time()
    model, _ = initial_model(frames, cameras, opts, torch.device("cpu"))
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    with torch.no_grad():
        scores = [psnr(render_views(model, cam, with_seg=False)["rgb"], frames.images[i])
                  for i, cam in enumerate(cameras)]
    return {"method": opts.init, "wall_s": wall, "cpu_s": cpu, "points": int(model.means.shape[0]),
            "foreground_points": int(model.foreground.sum()), "train_psnr": float(np.mean(scores))}


def _fmt(v, spec=".2f") -> str:
    return "–" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v, spec)


def markdown_table(records: list[dict[str, Any]], sequence_length: int) -> str:
    head = ("| run | knobs | init s (CPU s) | init points (fg) | init train PSNR | Gaussians | res | t0 s (CPU s) | "
            "later s/timestep (CPU s) | t0 PSNR / SSIM | "
            f"mean PSNR / SSIM | first-k → last-k PSNR | {sequence_length} timesteps, min (CPU min) | "
            "ball-region PSNR: mean, first-k → last-k | later iterations: mean (min–max) |")
    rows = [head, "|" + "---|" * 15]
    for r in records:
        knobs = ", ".join(f"{k}={v}" for k, v in r["knobs"].items()) or "defaults"
        rows.append(
            f"| {r['run']} | {knobs} | {_fmt(r.get('init_wall_s'), '.1f')} ({_fmt(r.get('init_cpu_s'), '.1f')}) | "
            f"{r.get('init_points', '–')} ({r.get('init_foreground_points', '–')}) | "
            f"{_fmt(r.get('init_train_psnr'))} | "
            f"{r['num_gaussians']} | {r['resolution'][0]}×{r['resolution'][1]} | "
            f"{_fmt(r['first_timestep_wall_s'], '.0f')} ({_fmt(r['first_timestep_cpu_s'], '.0f')}) | "
            f"{_fmt(r['later_timestep_wall_s'], '.1f')} ({_fmt(r['later_timestep_cpu_s'], '.1f')}) | "
            f"{r['psnr_first_timestep']:.2f} / {r['ssim_first_timestep']:.3f} | "
            f"{r['psnr_mean']:.2f} / {r['ssim_mean']:.3f} | "
            f"{r['psnr_first_k']:.2f} → {r['psnr_last_k']:.2f} (k={r['drift_k']}) | "
            f"{_fmt(r.get('measured_fit_wall_min', r.get('extrapolated_sequence_wall_min')), '.0f')} "
            f"({_fmt(r.get('measured_fit_cpu_min', r.get('extrapolated_sequence_cpu_min')), '.1f')}"
            f"{'' if 'measured_fit_cpu_min' in r else ', extrapolated'}) | "
            f"{_fmt(r.get('ball_psnr_mean'))}, {_fmt(r.get('ball_psnr_first_k'))} → {_fmt(r.get('ball_psnr_last_k'))} | "
            f"{_iterations_summary(r.get('later_iterations') or {})} |")
    return "\n".join(rows)


def _iterations_summary(later: dict[str, Any]) -> str:
    counts = [int(v) for v in later.values() if v is not None]
    if not counts:
        return "–"
    return f"{np.mean(counts):.1f} ({min(counts)}–{max(counts)})"


def sequence_cpu_minutes(r: dict[str, Any]) -> float | None:
    """CPU minutes of the whole sequence: measured when every timestep was fitted in this run, else extrapolated
    from the first and later timesteps (else the first timestep's alone)."""
    for key in ("measured_fit_cpu_min", "extrapolated_sequence_cpu_min"):
        if r.get(key) is not None:
            return float(r[key])
    return r["first_timestep_cpu_s"] / 60 if r.get("first_timestep_cpu_s") is not None else None


def pareto_front(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The points no other point beats in both cost (x, lower is better) and quality (y, higher is better)."""
    front, best = [], -np.inf
    for x, y in sorted(points):
        if y > best:
            front.append((x, y))
            best = y
    return front


def _pareto_plot(records: list[dict[str, Any]], path: Path) -> None:
    """Two panels against CPU minutes of the sequence: whole-frame and ball-region mean test PSNR."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fourlegs_engine.fileio import atomic_path

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for ax, key, label in ((axes[0], "psnr_mean", "whole frame"), (axes[1], "ball_psnr_mean", "ball region")):
        pts = []
        for r in records:
            x, y = sequence_cpu_minutes(r), r.get(key)
            if x is None or y is None:
                continue
            pts.append((x, y))
            ax.scatter([x], [y], s=40)
            ax.annotate(r["run"], (x, y), textcoords="offset points", xytext=(5, 5), fontsize=8)
        front = pareto_front(pts)
        if len(front) > 1:
            ax.plot(*zip(*front), "k--", lw=1, label="Pareto front")
            ax.legend(loc="lower right")
        if key == "psnr_mean":
            ax.axhline(27.0, color="r", lw=0.8, ls=":")
        ax.axvline(20.0, color="r", lw=0.8, ls=":")
        # CPU minutes: repeatable on a shared machine, where wall clock depends on the others' load
        ax.set_xlabel("CPU minutes, whole sequence (measured or extrapolated)")
        ax.set_ylabel(f"mean test-camera PSNR, {label} (dB)")
        ax.set_title(f"fourlegs fit: {label}")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def _ball_zoom(target: np.ndarray, render: np.ndarray, region_fn, size: tuple[int, int]) -> np.ndarray | None:
    """(h, w, 3) panel: the ground truth's ball neighbourhood (left) beside the render's (right), each a
    crop of a quarter of the frame around the ball's centre in the ground truth, magnified 2x."""
    w, h = size
    mask = region_fn((np.clip(target, 0, 1) * 255).round().astype(np.uint8))
    if not mask.any():
        return None
    ys, xs = np.nonzero(mask)
    cw, ch = w // 4, h // 2
    x0 = int(np.clip(xs.mean() - cw / 2, 0, w - cw))
    y0 = int(np.clip(ys.mean() - ch / 2, 0, h - ch))
    crops = [np.repeat(np.repeat(im[y0:y0 + ch, x0:x0 + cw], 2, 0), 2, 1) for im in (target, render)]
    return np.concatenate(crops, axis=1)[:h, :w]


def _contact_sheet(metrics, path: Path, title: str, region_fn=None) -> None:
    """Rows: test cameras; per kept timestep three columns: ground truth | render (whole-frame and ball-region
    PSNR in the label) | the ball's neighbourhood magnified, ground truth beside render (when it is seen)."""
    from PIL import Image, ImageDraw

    from fourlegs_engine.fileio import atomic_path

    keys = sorted(metrics.renders)
    times = sorted({t for t, _ in keys})
    cams = [c for c in metrics.cameras if (times[0], c) in metrics.renders] if times else []
    if not times or not cams:
        return
    h, w = metrics.renders[(times[0], cams[0])].shape[:2]
    cols = 3 if region_fn is not None else 2
    region = metrics.region_psnr() if region_fn is not None else None
    label_h = 14
    sheet = Image.new("RGB", (cols * w * len(times), (h + label_h) * len(cams) + label_h), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    draw.text((4, 1), f"{title}: ground truth | render | ball x2 (GT, render), test cameras {', '.join(cams)}",
              fill=(0, 0, 0))
    to_image = lambda im: Image.fromarray((np.clip(im, 0, 1) * 255).astype(np.uint8))  # noqa: E731
    for ci, cam in enumerate(cams):
        for ti, t in enumerate(times):
            i = metrics.timesteps.index(t)
            j = metrics.cameras.index(cam)
            y = label_h + ci * (h + label_h)
            target, render = metrics.targets[(t, cam)], metrics.renders[(t, cam)]
            for k, img in enumerate((target, render)):
                x = (cols * ti + k) * w
                sheet.paste(to_image(img), (x, y + label_h))
                ball = f", ball {region[i][j]:.1f}" if region is not None and region[i][j] is not None else ""
                text = f"cam {cam} t={t} " + ("GT" if k == 0 else f"render {metrics.psnr[i, j]:.1f} dB{ball}")
                draw.text((x + 3, y + 1), text, fill=(0, 0, 0))
            if region_fn is not None:
                zoom = _ball_zoom(target, render, region_fn, (w, h))
                x = (cols * ti + 2) * w
                if zoom is not None:
                    sheet.paste(to_image(zoom), (x, y + label_h))
                draw.text((x + 3, y + 1), "ball x2: GT | render" if zoom is not None else "no ball in view",
                          fill=(0, 0, 0))
    with atomic_path(path) as tmp:
        sheet.save(tmp)
