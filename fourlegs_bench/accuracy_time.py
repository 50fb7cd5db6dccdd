"""``fourlegs bench accuracy-time``: the price of every querying shortcut, in seconds and accuracy.

Each row runs the 4D method of the grounding benchmark (:mod:`.method4d`) with one knob changed and
reports, in the same run, its time (total, temporal part, spatial-map part, one-off precomputation) and
the six grounding metrics (vAP, vIoU, tIoU, tRec, tPrec, tAP; mean over the test views, ± std) against
the exact ground truth. Groups:

* ``reference`` — exact temporal path, exact (128-channel) maps, full resolution, every timestep.
* ``codebook`` — K = 65536, 4096, 256 (codebook build reported as precomputation), and K = 65536 / 4096
  with a sampled R_avg and exact re-scoring, where a decision needs it, of the codes within ±0.0075 / ±0.02 of R_avg.
* ``stride`` — temporal stride 2, 5, 10.
* ``scale`` — maps at 0.5 and 0.25 of the camera resolution (upsampled for scoring).
* ``spatial`` — fast 1-channel relevancy render instead of the 128-channel render.
* ``precision`` — decoder run in float16 / bfloat16 instead of float32 (latents are stored float16), on
  the fast-maps + codebook configuration (float16 products are several times slower on a CPU).
* ``distill`` / ``knn`` — distillation mode and iterations (and the lift's learning-free kNN blur), and the
  kNN k of the attention smoothing.
  Distilling is the slow stage, so these rows distil only every k-th timestep (``--distill-timesteps``;
  automatic: at most 3 timesteps; 25 and 100 iterations instead of the paper's 2000) and the other timesteps hold the nearest distilled timestep's latents;
  their reference row is ``lift`` with the same subsampling, all of them are scored with the exact
  temporal path and fast maps, and their time is distillation seconds per timestep (recorded beside the
  distilled steps, so a rerun that reuses them still reports it). The table says so.

Outputs in ``--out``: ``accuracy_time.json``, ``accuracy_time.md`` and ``accuracy_time.png`` (Pareto
plot: vAP and tIoU against seconds, Pareto-optimal rows joined).

Rows whose temporal results or maps are identical by construction (e.g. the codebook rows all use the
exact maps) compute them once; every row is still charged the seconds those results took, so each
row's time is what that configuration costs on its own.
"""
from __future__ import annotations

import shlex
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import numpy as np
import torch

from fourlegs_engine.errors import InputError, OutputExistsError
from fourlegs_engine.fileio import atomic_path, load_npy, write_json_atomic
from .grounding import _summary, build_context, score_view
from .ground_truth import ensure_ground_truth
from .method4d import FourLegsMethod
from .metrics import METRIC_NAMES, format_percent

DISTILL_ITERATIONS = (25, 100)  # the paper's 2000 iterations per timestep do not fit a CPU bench
DISTILL_MAX_TIMESTEPS = 3
#: the distillation rows share one query configuration: exact temporal path, fast maps (exact maps decode
#: every pixel of every scored frame, which would multiply the run time by the number of rows)
DISTILL_QUERY_OPTIONS = {"spatial": "fast"}
GROUPS = ("reference", "codebook", "sketch", "stride", "scale", "spatial", "precision", "distill", "knn")


@dataclass
class Variant:
    group: str
    name: str
    options: dict = field(default_factory=dict)
    field_factory: Optional[Callable[[], Any]] = None
    note: str = ""


class CastField:
    """A field whose decoder runs in another precision (latents, outputs float32)."""

    def __init__(self, base: Any, dtype: torch.dtype):
        import copy
        self.base = base
        self.latents = base.latents
        self.canonical_phrases = base.canonical_phrases
        self.encoder_name = base.encoder_name
        self.dtype = dtype
        self.decoder = copy.deepcopy(base.decoder).to(dtype).eval()

    @torch.no_grad()
    def decode(self, z) -> torch.Tensor:
        z = torch.nan_to_num(torch.as_tensor(z, dtype=torch.float32)).to(self.dtype)
        return self.decoder(z).float()


class HeldField:
    """A field with other latents (same decoder): used for the distillation variants."""

    def __init__(self, base: Any, latents: np.ndarray):
        self.base = base
        self.latents = latents
        self.canonical_phrases = base.canonical_phrases
        self.encoder_name = base.encoder_name
        self.decoder = getattr(base, "decoder", None)

    def decode(self, z) -> torch.Tensor:
        return self.base.decode(z)


def hold_fill(step_files: dict[int, Path], num_timesteps: int, out: Path) -> np.ndarray:
    """(T,N,d) latents where each timestep holds the nearest distilled timestep's latents."""
    done = np.array(sorted(step_files))
    first = load_npy(step_files[int(done[0])], field="latents")
    arr = np.lib.format.open_memmap(out, mode="w+", dtype=np.float16,
                                    shape=(num_timesteps,) + tuple(first.shape))
    for t in range(num_timesteps):
        src = int(done[np.argmin(np.abs(done - t))])
        arr[t] = np.asarray(load_npy(step_files[src], field="latents"), dtype=np.float16)
    arr.flush()
    del arr
    return np.load(out, mmap_mode="r")


def evaluate(ctx: Any, gt: Any, method: FourLegsMethod) -> dict[str, Any]:
    """Six metrics (mean ± std over views) and the time split of one configured method."""
    start = time.perf_counter()
    per_view: dict[str, dict[str, dict[str, float]]] = {}
    for cam in ctx.cameras:
        preds = method.predict_view(ctx, cam)
        per_view[cam.name] = {q: score_view(preds[q], gt.frames[q], gt.masks[cam.name][:, qi], gt.boxes[cam.name][:, qi])
                              for qi, q in enumerate(ctx.queries)}
    wall = time.perf_counter() - start
    summary = _summary(per_view, ctx.queries)["overall"]
    # a row is charged what its configuration costs on its own: temporal results and maps it reused
    # from an identical configuration count with the seconds they took there
    charged = method.timings["temporal"] + method.timings["maps"]
    return {"metrics": summary, "seconds": charged, "wall_s": wall, "temporal_s": method.timings["temporal"],
            "maps_s": method.timings["maps"], "stats": dict(method.engine.stats)}


def _distill_variants(scene: Any, base_field: Any, every: int, out_root: Path, progress: bool,
                      iterations: Sequence[int] = DISTILL_ITERATIONS, skip: Sequence[str] = ()) -> list[Variant]:
    """Distillation mode / iterations and kNN k rows, each distilled on every ``every``-th timestep:
    lift, lift with the kNN blur, lift+refine (first iteration count), optimize at every count, and
    lift+refine with k = 5, 10. Rows of a group in ``skip`` are not distilled at all."""
    from fourlegs_engine.language.distill import distill_scene

    T = scene.num_timesteps
    steps = list(range(0, T, every))
    first = int(iterations[0])
    specs = [("distill", "lift", dict(mode="lift")),
             ("distill", "lift + kNN blur", dict(mode="lift", lift_smoothing="blur")),
             ("distill", f"lift+refine {first} it", dict(mode="lift+refine", iterations=first))]
    specs += [("distill", f"optimize {int(n)} it", dict(mode="optimize", iterations=int(n))) for n in iterations]
    specs += [("knn", f"lift+refine {first} it, k={k}", dict(mode="lift+refine", iterations=first, neighbours=k))
              for k in (5, 10)]
    specs = [spec for spec in specs if spec[0] not in skip]
    out = []
    for group, name, opts in specs:
        vdir = out_root / "distill" / name.replace(" ", "_").replace(",", "").replace("=", "")
        start = time.perf_counter()
        result = distill_scene(scene, timesteps=steps, out_dir=vdir, merge=False, progress=progress, **opts)
        spent = time.perf_counter() - start
        per_t = _distill_seconds(vdir, result)
        files = {t: vdir / "steps" / f"t{t:06d}.npy" for t in steps}
        missing = [t for t, p in files.items() if not p.is_file()]
        if missing:
            raise InputError(f"distillation left timesteps {missing} unfinished", file=vdir)
        latents = hold_fill(files, T, vdir / "held_latents.npy")
        out.append(Variant(group, name, dict(DISTILL_QUERY_OPTIONS),
                           field_factory=lambda lat=latents: HeldField(base_field, lat),
                           note=f"distilled {len(steps)}/{T} timesteps" +
                                (f" (every {every}), others held; " if len(steps) < T else "; ") +
                                f"{'%.2f' % per_t if per_t else 'cached'} s/timestep" +
                                ("" if per_t else f" ({spent:.1f} s reused)") + "; fast maps"))
        out[-1].options["distill_s_per_timestep"] = per_t
    return out


def _distill_seconds(vdir: Path, result: Any) -> Optional[float]:
    """Seconds per distilled timestep of a variant: measured now, or as recorded when it was distilled
    (a rerun reuses the finished timesteps, and their cost is still the row's cost)."""
    record = vdir / "distill_seconds.json"
    if result.timings:
        per_t = float(result.seconds_per_timestep)
        write_json_atomic(record, {"seconds_per_timestep": per_t, "timesteps": len(result.timings),
                                   "threads": torch.get_num_threads()}, overwrite=True)
        return per_t
    if record.is_file():
        import json
        return float(json.loads(record.read_text())["seconds_per_timestep"])
    return None


def variants(skip: Sequence[str]) -> list[Variant]:
    rows = [Variant("reference", "exact", {})]
    rows += [Variant("codebook", f"codebook K={k}", {"path": "codebook", "codebook_size": k})
             for k in (65536, 4096, 256)]
    # sampled R_avg and exact re-scoring of the codes within the margin of R_avg where a decision needs it
    rows += [Variant("codebook", f"codebook K={k} + exact re-scoring ±{m:g}",
                     {"path": "codebook", "codebook_size": k, "codebook_refine": m})
             for k, m in ((65536, 0.0075), (4096, 0.02))]
    # the per-pair sketch: every pair bounded, exact scores only where a decision needs them
    rows += [Variant("sketch", f"sketch rank {r}", {"path": "sketch", "sketch_rank": r}) for r in (32, 8)]
    rows += [Variant("sketch", "fast maps + sketch rank 32 (the default)", {"spatial": "fast", "path": "sketch"})]
    rows += [Variant("stride", f"temporal stride {s}", {"temporal_stride": s}) for s in (2, 5, 10)]
    rows += [Variant("scale", f"resolution scale {s}", {"resolution_scale": s}) for s in (0.5, 0.25)]
    rows += [Variant("spatial", "fast 1-channel maps", {"spatial": "fast"}),
             Variant("spatial", "fast maps + codebook K=4096", {"spatial": "fast", "path": "codebook",
                                                                 "codebook_size": 4096}),
             Variant("spatial", "fast maps + codebook K=65536 ±0.0075", {"spatial": "fast", "path": "codebook",
                                                                        "codebook_size": 65536,
                                                                        "codebook_refine": 0.0075})]
    # precision: on the cheapest configuration (its decodes are the K codes and the background), because
    # float16 matrix products on a CPU are several times slower than float32; latents are stored float16
    rows += [Variant("precision", f"fast maps + codebook K=4096, decoder {n}",
                     {"spatial": "fast", "path": "codebook", "codebook_size": 4096, "_dtype": dt})
             for n, dt in (("float16", torch.float16), ("bfloat16", torch.bfloat16))]
    return [r for r in rows if r.group not in skip]


def run_accuracy_time(scene: Any, *, out_dir: Path, skip: Sequence[str] = (), distill_every: int = 0,
                      distill_iterations: Sequence[int] = DISTILL_ITERATIONS,
                      seed: int = 0, progress: bool = True) -> dict[str, Any]:
    from fourlegs_engine.query.codebook import ensure_codebook
    from .query_fixtures import scene_with_field

    unknown = set(skip) - set(GROUPS)
    if unknown:
        raise InputError(f"unknown groups {sorted(unknown)} (choose from {', '.join(GROUPS)})", field="--skip")
    ctx = build_context(scene, seed=seed, progress=False)
    scene, base_field, _ = scene_with_field(scene, ctx.video_encoder, progress=progress)
    ctx.scene = scene
    gt = ensure_ground_truth(scene, ctx.cameras, progress=progress, videos=ctx.videos)
    rows_spec = variants(skip)
    if not ({"distill", "knn"} <= set(skip)):
        every = distill_every or max(1, -(-scene.num_timesteps // DISTILL_MAX_TIMESTEPS))
        rows_spec += _distill_variants(scene, base_field, every, out_dir, progress, distill_iterations, skip)
    rows = []
    shared: dict = {}
    for v in rows_spec:
        opts = {k: val for k, val in v.options.items() if not k.startswith("_") and k != "distill_s_per_timestep"}
        field_key = (v.group if v.field_factory else "base", v.name if v.field_factory else
                     str(v.options.get("_dtype", "float32")))
        spatial = opts.get("spatial", "exact")
        # fast maps on the exact path score every Gaussian at every scored frame: the temporal pass of the
        # same engine already has those scores, so such rows run (and are charged) their own temporal pass
        own_pass = spatial == "fast" and opts.get("path", "exact") == "exact"
        temporal_key = (field_key, opts.get("path", "exact"), opts.get("codebook_size"), opts.get("codebook_refine", 0.0),
                        opts.get("temporal_stride", 1), "own" if own_pass else "")
        map_key = (field_key, spatial, opts.get("resolution_scale", 1.0)) + (
            (opts.get("path", "exact"), opts.get("codebook_size")) if spatial == "fast" else ())
        fld = v.field_factory() if v.field_factory else (
            CastField(base_field, v.options["_dtype"]) if "_dtype" in v.options else base_field)
        precompute = 0.0
        if opts.get("path") == "codebook":
            start = time.perf_counter()
            opts["codebook"] = ensure_codebook(fld.latents, opts["codebook_size"], Path(scene.root) / "language",
                                               progress=progress)
            precompute = time.perf_counter() - start
        elif opts.get("path") == "sketch":  # built (or loaded) beside the field before the timed run
            from fourlegs_engine.query.engine import QueryEngine, QueryOptions

            start = time.perf_counter()
            QueryEngine(scene, fld, ctx.text_encoder, QueryOptions(path="sketch", sketch_rank=opts.get("sketch_rank", 32)),
                        codebook_dir=Path(scene.root) / "language").load_index()
            precompute = time.perf_counter() - start
            opts["codebook_dir"] = Path(scene.root) / "language"
        if progress:
            print(f"accuracy-time: {v.group} / {v.name} ...", file=sys.stderr)
        method = FourLegsMethod(ctx, field=fld, shared=shared, temporal_key=temporal_key, map_key=map_key, **opts)
        res = evaluate(ctx, gt, method)
        row = {"group": v.group, "name": v.name, "note": v.note, "precompute_s": precompute,
               "distill_s_per_timestep": v.options.get("distill_s_per_timestep"), **res}
        rows.append(row)
        if progress:
            m = row["metrics"]
            print(f"  {row['seconds']:.1f} s  vAP {100 * m['vAP']['mean']:.1f}  tIoU {100 * m['tIoU']['mean']:.1f}",
                  file=sys.stderr)
    meta = (scene.metadata or {}).get("generator", {})
    return {"benchmark": "accuracy-time", "scene": {"name": scene.name, "size": meta.get("size"),
                                                     "num_gaussians": scene.num_gaussians,
                                                     "num_timesteps": scene.num_timesteps,
                                                     "views": [c.name for c in ctx.cameras],
                                                     "queries": list(ctx.queries)},
            "torch_threads": torch.get_num_threads(), "metrics": list(METRIC_NAMES), "rows": rows}


def markdown_table(report: dict[str, Any]) -> str:
    s = report["scene"]
    lines = [f"Accuracy vs time on {s['name']} (N={s['num_gaussians']:,}, T={s['num_timesteps']}, "
             f"{len(s['views'])} test views, {len(s['queries'])} queries, torch threads {report['torch_threads']}); "
             "metrics in %, ± = std over views; seconds = the method's whole run over all views and queries "
             "(temporal + maps), precompute = one-off index build (codebook or sketch)", "",
             "| group | variant | seconds | temporal s | maps s | precompute s | " + " | ".join(report["metrics"])
             + " | note |", "|---" * (len(report["metrics"]) + 7) + "|"]
    for r in report["rows"]:
        m = r["metrics"]
        lines.append(f"| {r['group']} | {r['name']} | {r['seconds']:.1f} | {r['temporal_s']:.2f} | {r['maps_s']:.1f} | "
                     f"{r['precompute_s']:.1f} | " + " | ".join(format_percent(m[k]['mean'], m[k]['std'])
                                                              for k in report["metrics"]) + f" | {r['note']} |")
    if any(r["group"] in ("distill", "knn") for r in report["rows"]):
        lines += ["", "Distillation rows (distill, knn) distil only a subsample of timesteps (see note); the other "
                      "timesteps hold the nearest distilled timestep, so compare them with the `lift` row of the "
                      "same group, not with `exact`. They are all scored with the exact temporal path and fast maps. "
                      "Their cost is the distillation time per timestep in the note."]
    return "\n".join(lines)


def _pareto(ax, xs: np.ndarray, ys: np.ndarray) -> None:
    """Join the Pareto-optimal points (no other point is both faster and more accurate)."""
    front, best = [], -np.inf
    for i in np.argsort(xs, kind="stable"):
        if ys[i] > best:
            front.append(i)
            best = ys[i]
    if front:
        ax.plot(xs[front], ys[front], color="black", lw=1, ls="--", zorder=2, label="Pareto front")


def pareto_plot(report: dict[str, Any], path: Path, *, overwrite: bool = True) -> Path:
    """vAP and tIoU against query seconds (query knobs), and vAP against distillation seconds per
    timestep (distillation knobs, when present)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    query_rows = [r for r in report["rows"] if r["group"] not in ("distill", "knn")]
    distill_rows = [r for r in report["rows"] if r["group"] in ("distill", "knn") and r.get("distill_s_per_timestep")]
    panels = [("vAP", query_rows, "seconds", "seconds (method's whole benchmark run)"),
              ("tIoU", query_rows, "seconds", "seconds (method's whole benchmark run)")]
    if distill_rows:
        panels.append(("vAP", distill_rows, "distill_s_per_timestep", "distillation seconds per timestep"))
    groups = list(dict.fromkeys(r["group"] for r in report["rows"]))
    colors = {g: plt.cm.tab10(i % 10) for i, g in enumerate(groups)}
    fig, axes = plt.subplots(1, len(panels), figsize=(6 * len(panels), 4.5), dpi=100, squeeze=False)
    try:
        for ax, (metric, rows, xkey, xlabel) in zip(axes[0], panels):
            if not rows:
                ax.set_visible(False)
                continue
            xs = np.array([max(float(r[xkey]), 1e-3) for r in rows])
            ys = np.array([100 * r["metrics"][metric]["mean"] for r in rows])
            for r, x, y in zip(rows, xs, ys):
                ax.scatter(x, y, color=colors[r["group"]], s=30, zorder=3)
                ax.annotate(r["name"], (x, y), fontsize=6, xytext=(3, 3), textcoords="offset points")
            _pareto(ax, xs, ys)
            ax.set_xscale("log")
            ax.set_xlabel(xlabel)
            ax.set_ylabel(f"{metric} (%)")
            ax.set_title(f"{metric} vs time" + (" (distillation knobs)" if xkey != "seconds" else ""))
            for g in dict.fromkeys(r["group"] for r in rows):
                ax.scatter([], [], color=colors[g], label=g)
            ax.legend(fontsize=7, loc="lower right")
        fig.suptitle(f"accuracy vs time: {report['scene']['name']}")
        fig.tight_layout()
        with atomic_path(path, overwrite=overwrite) as tmp:
            fig.savefig(tmp, format="png")
    finally:
        plt.close(fig)
    return path


def run_accuracy_time_cli(args: Any) -> int:
    from fourlegs_engine.scene.bundle import load_bundle
    from fourlegs_engine.demo.synthetic import ensure_demo_bundle

    if args.threads:
        torch.set_num_threads(args.threads)
    path = Path(args.bundle) if args.bundle else ensure_demo_bundle(args.scene, args.seed)
    out = Path(args.out) if args.out else path / "bench" / "accuracy_time"
    json_path = Path(args.json) if args.json else out / "accuracy_time.json"
    md_path, png_path = out / "accuracy_time.md", out / "accuracy_time.png"
    for p in (json_path, md_path, png_path):
        if p.exists() and not args.overwrite:
            raise OutputExistsError(p)
    skip = [s.strip() for s in args.skip.split(",") if s.strip()]
    start = time.perf_counter()
    report = run_accuracy_time(load_bundle(path), out_dir=out, skip=skip, distill_every=args.distill_timesteps,
                               distill_iterations=[int(v) for v in args.distill_iterations.split(",") if v.strip()],
                               seed=args.seed)
    report["total_seconds"] = time.perf_counter() - start
    report["scene"]["path"] = str(path)
    table = markdown_table(report)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(json_path, report, overwrite=True)
    command = "fourlegs " + " ".join(shlex.quote(a) for a in sys.argv[1:]) if sys.argv[1:] else ""
    with atomic_path(md_path) as tmp:
        tmp.write_text((f"Command: `{command}`\n\n" if command else "") + table + "\n", encoding="utf-8")
    pareto_plot(report, png_path)
    print(table)
    print(f"\ntotal {report['total_seconds']:.1f} s; wrote {json_path}, {md_path}, {png_path}")
    return 0
