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
import json
import shlex
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

DEFAULT_DATASET = "../shared/data/panoptic-basketball"
#: name -> knob overrides of FitOptions
PRESET_RUNS = {
    "fast": {"first_iterations": 150, "iterations": 10},
    "default": {},
    "long": {"first_iterations": 600, "iterations": 60, "max_gaussians": 120_000, "init_background": 60_000},
}
INT_KNOBS = ("first_iterations", "iterations", "max_gaussians", "init_foreground", "init_background",
             "background_stride", "knn", "seed", "clean_plate_samples")
STR_KNOBS = ("init",)
FLOAT_KNOBS = ("resolution_scale", "lr_means", "lr_means_later", "lr_colors", "lr_scales", "lr_opacities",
               "lr_rotations", "lr_rotations_later", "lr_camera", "voxel", "grad_threshold")


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
            try:
                if key in INT_KNOBS:
                    kw[key] = int(value)
                elif key in FLOAT_KNOBS:
                    kw[key] = float(value)
                elif key in STR_KNOBS:
                    kw[key] = value.strip()
                elif key == "densify":
                    kw[key] = value.strip().lower() in ("1", "true", "yes")
                else:
                    raise InputError(f"unknown knob {key!r}", field="--runs")
            except ValueError:
                raise InputError(f"bad value for {key}: {value!r}", field="--runs") from None
        runs.append((name.strip(), kw))
    if not runs:
        raise InputError("no runs given", field="--runs")
    return runs


class _Timer:
    """Progress callback recording wall and CPU seconds of every finished timestep."""

    def __init__(self, name: str = "", total: int = 0):
        self.wall0, self.cpu0 = time.perf_counter(), time.process_time()
        self.per_timestep: dict[int, dict[str, float]] = {}
        self.name, self.total = name, total

    def __call__(self, ev) -> None:
        if ev.kind != "timestep" or ev.resumed:
            return
        wall, cpu = time.perf_counter(), time.process_time()
        self.per_timestep[ev.timestep] = {"wall_s": wall - self.wall0, "cpu_s": cpu - self.cpu0,
                                          "train_psnr": ev.train_psnr}
        self.wall0, self.cpu0 = wall, cpu
        rec = self.per_timestep[ev.timestep]
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
        timer = _Timer(name, len(steps))
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
                                      keep_images_at=tuple(keep[:max(1, args.contact_timesteps)]))
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
        }
        if first.get("wall_s") is not None and later:
            rec["extrapolated_sequence_wall_min"] = (first["wall_s"] + (args.sequence_length - 1) * later_wall) / 60
            rec["extrapolated_sequence_cpu_min"] = (first["cpu_s"] + (args.sequence_length - 1) * later_cpu) / 60
        records.append(rec)
        _contact_sheet(metrics, out / f"contact_{name}.png", name)
        print(f"[bench fit] {name}: first-timestep PSNR {rec['psnr_first_timestep']:.2f} dB, mean "
              f"{rec['psnr_mean']:.2f} dB over {len(per_t)} timesteps", flush=True)
    result = {"command": command, "dataset": str(dataset.resolve()), "records": records}
    write_json_atomic(out / "fit_bench.json", result)
    table = markdown_table(records, args.sequence_length)
    (out / "fit_bench.md").write_text((f"`{command}`\n\n" if command else "") + table + "\n")
    _pareto_plot(records, out / "fit_pareto.png")
    print(table)
    print(f"[bench fit] wrote {out / 'fit_bench.md'}, {out / 'fit_bench.json'}, {out / 'fit_pareto.png'}, "
          f"contact sheets in {out}")
    return 0


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
            f"mean PSNR / SSIM | first-k → last-k PSNR | {sequence_length} timesteps, min (CPU min) |")
    rows = [head, "|" + "---|" * 13]
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
            f"{_fmt(r.get('extrapolated_sequence_wall_min'), '.0f')} "
            f"({_fmt(r.get('extrapolated_sequence_cpu_min'), '.0f')}) |")
    return "\n".join(rows)


def _pareto_plot(records: list[dict[str, Any]], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fourlegs_engine.fileio import atomic_path

    fig, ax = plt.subplots(figsize=(6, 4))
    for r in records:
        x = r["later_timestep_cpu_s"]
        if x is None:
            x = r["first_timestep_cpu_s"] or float("nan")
        ax.scatter([x], [r["psnr_mean"]], s=40)
        ax.annotate(r["run"], (x, r["psnr_mean"]), textcoords="offset points", xytext=(5, 5))
    pts = sorted((r["later_timestep_cpu_s"], r["psnr_mean"]) for r in records if r["later_timestep_cpu_s"] is not None)
    front, best = [], -np.inf
    for x, y in pts:
        if y > best:
            front.append((x, y))
            best = y
    if len(front) > 1:
        ax.plot(*zip(*front), "k--", lw=1, label="Pareto front")
        ax.legend()
    ax.axhline(24.0, color="r", lw=0.8, ls=":")
    # CPU seconds: repeatable on a shared machine, where wall clock depends on the others' load
    only_first = all(r["later_timestep_cpu_s"] is None for r in records)
    ax.set_xlabel("CPU seconds of the first timestep" if only_first else "CPU seconds per later timestep")
    ax.set_ylabel("mean test-camera PSNR (dB)")
    ax.set_title("fourlegs fit: accuracy vs time")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def _contact_sheet(metrics, path: Path, title: str) -> None:
    """Rows: test cameras; per kept timestep two columns: ground truth | render (PSNR in the label)."""
    from PIL import Image, ImageDraw

    from fourlegs_engine.fileio import atomic_path

    keys = sorted(metrics.renders)
    times = sorted({t for t, _ in keys})
    cams = [c for c in metrics.cameras if (times[0], c) in metrics.renders] if times else []
    if not times or not cams:
        return
    h, w = metrics.renders[(times[0], cams[0])].shape[:2]
    label_h = 14
    sheet = Image.new("RGB", (2 * w * len(times), (h + label_h) * len(cams) + label_h), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    draw.text((4, 1), f"{title}: ground truth | render, test cameras {', '.join(cams)}", fill=(0, 0, 0))
    for ci, cam in enumerate(cams):
        for ti, t in enumerate(times):
            i = metrics.timesteps.index(t)
            j = metrics.cameras.index(cam)
            y = label_h + ci * (h + label_h)
            for k, img in enumerate((metrics.targets[(t, cam)], metrics.renders[(t, cam)])):
                x = (2 * ti + k) * w
                sheet.paste(Image.fromarray((np.clip(img, 0, 1) * 255).astype(np.uint8)), (x, y + label_h))
                text = f"cam {cam} t={t} " + ("GT" if k == 0 else f"render {metrics.psnr[i, j]:.1f} dB")
                draw.text((x + 3, y + 1), text, fill=(0, 0, 0))
    with atomic_path(path) as tmp:
        sheet.save(tmp)
