"""``fourlegs bench language-cost``: what each extraction cost knob saves and what it costs in accuracy.

Every row extracts the teacher features with one plan (:class:`~fourlegs_engine.language.plans.ExtractPlan`),
lifts the field (the pipeline's lift) and scores it. The autoencoder is trained once, on the reference row's
(full) features, and shared by every row, so rows differ only in their teacher features
(``--own-autoencoder`` trains one per row). Two proxies, named as what they are:

* ``synthetic`` — a synthetic scene (default ``bench``) with the *simulated* video-text encoder; all six
  grounding metrics on its test views against the exact ground truth (exact temporal path, fast maps).
* ``real`` — a fitted real capture with the *annotation-mask* teacher ("a person" = the capture's
  foreground masks; not a language model); training cameras held out as in ``bench real-lift``, the
  evidence comes from the others, subsampled by the plan, and the relevancy rendered from the held-out
  cameras is scored against their masks (vAP = pixel AP, vIoU = box IoU per timestep; every timestep
  holds people, so there is no temporal metric on this proxy).

Cost: the clips each row's extraction actually sent to the encoder (counted in the run: early exits are
measured, not assumed), priced at ViCLIP-L/14's seconds per clip — measured here on the CPU by the
planner's calibration (random weights: seconds depend only on shapes) or read from a calibration JSON
(``fourlegs extract --dry-run --plan-json``; the GPU figure is from the device check, marked derived).
Also the plan's clips on a Panoptic-sized rig (27 cameras x 150 timesteps at 640x360, 30 fps) with the
early-exit share measured over a whole fitted sequence on every camera (``--exit-share-scene``), or else on
the real proxy's row of the same plan.

Outputs in ``--out``: ``language_cost.json``, ``language_cost.md``, ``language_cost.png``. Rows already
scored in ``--work`` are reused (each row's result is kept beside its bundle).
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fourlegs_engine.errors import InputError
from fourlegs_engine.fileio import atomic_path, write_json_atomic
from fourlegs_engine.language.plans import PLANS, ExtractPlan, plan_clips

PROXIES = ("synthetic", "real")
PANOPTIC = {"cameras": 27, "timesteps": 150, "width": 640, "height": 360, "fps": 30.0}
#: synthetic rows are scored like the main job: exact temporal path, fast 1-channel maps
SYNTHETIC_QUERY = {"spatial": "fast"}
REAL_PHRASE = "a person"


def knob_rows(num_cameras: int) -> list[tuple[str, str, ExtractPlan]]:
    """(group, name, plan) of every row: the reference, each knob alone at a few settings, the default."""
    full = PLANS["full"]
    rows = [("reference", "full (paper)", full)]
    for frac in (2 / 3, 1 / 2, 1 / 3):
        k = max(1, int(round(frac * num_cameras)))
        rows.append(("cameras", f"{k} of {num_cameras} cameras (coverage)", full.with_(cameras=k)))
    for s in (2, 4, 6, 8):
        rows.append(("timestep stride", f"stride {s}, interpolate", full.with_(timestep_stride=s)))
    rows.append(("timestep stride", "stride 4, reuse", full.with_(timestep_stride=4, fill="reuse")))
    for s in (4, 6, 8):
        rows.append(("timestep stride", f"stride {s}, latents", full.with_(timestep_stride=s, fill="latents")))
    rows += [("levels", "levels 1-4 (no smallest)", full.with_(levels=(1, 2, 3, 4))),
             ("levels", "levels 2-4", full.with_(levels=(2, 3, 4)))]
    rows += [("crop stride", f"crop stride {f:g}", full.with_(crop_stride=f)) for f in (0.65, 0.75, 1.0)]
    rows += [("early exit", f"early exit {m}", full.with_(early_exit=m)) for m in ("foreground", "difference")]
    rows += [("combined", "stride 4 + crop stride 1 + early exit", full.with_(timestep_stride=4, crop_stride=1.0,
                                                                           early_exit="foreground")),
             ("combined", "stride 8 + crop stride 0.75 + early exit", full.with_(timestep_stride=8, crop_stride=0.75,
                                                                              early_exit="foreground")),
             ("combined", "stride 6 + crop stride 0.75 + early exit (the previous default)",
              full.with_(timestep_stride=6, crop_stride=0.75, early_exit="foreground"))]
    rows += [("combined", f"stride {s} + crop stride 0.75 + early exit, latents",
              full.with_(timestep_stride=s, crop_stride=0.75, early_exit="foreground", fill="latents"))
             for s in (5, 6, 8)]
    # the cheapest plans without a timestep stride above 2: every knob that keeps the labels of each timestep
    rows += [("combined", "early exit + crop stride 0.75", full.with_(crop_stride=0.75, early_exit="foreground")),
             ("combined", "early exit + crop stride 0.65", full.with_(crop_stride=0.65, early_exit="foreground")),
             ("combined", "stride 6 + crop stride 0.65 + early exit", full.with_(timestep_stride=6, crop_stride=0.65,
                                                                              early_exit="foreground")),
             ("combined", "stride 2 + crop stride 0.75 + levels 1-4 + early exit",
              full.with_(timestep_stride=2, crop_stride=0.75, levels=(1, 2, 3, 4), early_exit="foreground"))]
    rows.append(("default", "default plan", PLANS["default"]))
    return rows


def _slug(name: str) -> str:
    return "".join(ch if ch.isalnum() else "_" for ch in name).strip("_")


def linked_bundle(source: Path, target: Path) -> Path:
    """A bundle at ``target`` whose arrays are hard links to ``source``'s (copies across file systems), with
    its own features, autoencoder and field; the source stays untouched (the arrays are only read)."""
    if (target / "scene.json").is_file():
        return target
    meta = json.loads((source / "scene.json").read_text(encoding="utf-8"))
    meta["language"] = None
    meta["arrays"] = {k: v for k, v in meta["arrays"].items() if k != "latents"}
    tmp = target.with_name(target.name + ".tmp")
    if tmp.exists():
        import shutil
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    for rel in meta["arrays"].values():
        (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link((source / rel).resolve(), tmp / rel)
        except OSError:  # another file system: a copy
            import shutil
            shutil.copyfile(source / rel, tmp / rel)
    write_json_atomic(tmp / "scene.json", meta)
    tmp.rename(target)
    return target


def build_field(bundle: Path, encoder: Any, config: Any, *, ae_epochs: int, view_scale: float,
                progress: bool, shared_autoencoder: Path | None = None) -> dict[str, Any]:
    """Extract with ``config``, train the autoencoder (or take the one of the bundle ``shared_autoencoder``),
    lift; returns the extraction's counts and seconds."""
    import shutil
    from fourlegs_engine.language.autoencoder import AE_REPORT, DECODER_FILE, ENCODER_FILE, AETrainOptions, \
        train_autoencoder
    from fourlegs_engine.language.distill import distill_scene
    from fourlegs_engine.language.extract import extract_features
    from fourlegs_engine.scene.bundle import load_bundle

    scene = load_bundle(bundle)
    shutil.rmtree(bundle / "features", ignore_errors=True)  # a whole extraction: its clips are the row's cost
    rep = extract_features(scene, encoder, config, overwrite=True, progress=progress)
    start = time.perf_counter()
    if shared_autoencoder is None:
        train_autoencoder(scene, AETrainOptions(epochs=ae_epochs), overwrite=True)
    else:
        for rel in (AE_REPORT, ENCODER_FILE, DECODER_FILE):
            (bundle / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(shared_autoencoder / rel, bundle / rel)
    ae_s = time.perf_counter() - start
    start = time.perf_counter()
    distill_scene(scene, mode="lift", view_scale=view_scale, overwrite=True)
    return {"clips_encoded": rep.clips_encoded, "clips_copied": rep.clips_copied,
            "timesteps_encoded": len(rep.timesteps_done), "timesteps_filled": len(rep.timesteps_filled),
            "crops_per_timestep": rep.crops_per_timestep, "extract_s": rep.seconds, "extract_cpu_s": rep.cpu_seconds,
            "train_ae_s": ae_s, "lift_s": time.perf_counter() - start}


# ------------------------------------------------------------------------------------ proxies
def run_synthetic(rows: Sequence[tuple[str, str, ExtractPlan]], *, size: str, seed: int, work: Path,
                  ae_epochs: int, view_scale: float, progress: bool, own_autoencoder: bool = False,
                  cached_only: bool = False, keep_bundles: bool = False) -> list[dict[str, Any]]:
    """Every row on the synthetic scene with the simulated encoder; six metrics on its test views."""
    from fourlegs_engine.language.field import LanguageField
    from fourlegs_engine.pipeline import text_encoder
    from fourlegs_engine.scene.bundle import load_bundle
    from fourlegs_engine.demo.synthetic import ensure_demo_bundle
    from .accuracy_time import evaluate
    from .grounding import build_context
    from .ground_truth import ensure_ground_truth
    from .method4d import FourLegsMethod

    source = Path(ensure_demo_bundle(size, seed))
    base_scene = load_bundle(source)
    ctx = build_context(base_scene, seed=seed, progress=False)
    gt = ensure_ground_truth(base_scene, ctx.cameras, progress=progress, videos=ctx.videos)
    settings = {"scene": size, "seed": seed, "ae_epochs": ae_epochs, "view_scale": view_scale,
                "autoencoder": "own" if own_autoencoder else "shared"}
    out = []
    for group, name, plan in rows:
        vdir = work / "synthetic" / _slug(name)
        cached = _cached(vdir, plan, settings)
        if cached is not None:
            out.append(cached)
            continue
        if cached_only:
            continue
        bundle = linked_bundle(source, vdir / "bundle")
        scene = load_bundle(bundle)
        encoder = text_encoder(scene)
        config = plan.extract_config(scene)
        if progress:
            print(f"language-cost synthetic: {name} ...", file=sys.stderr)
        built = build_field(bundle, encoder, config, ae_epochs=ae_epochs, view_scale=view_scale, progress=progress,
                            shared_autoencoder=_shared_ae(work / "synthetic", group, own_autoencoder))
        scene = load_bundle(bundle)
        ctx.scene = scene
        method = FourLegsMethod(ctx, field=LanguageField.open(bundle), **SYNTHETIC_QUERY)
        res = evaluate(ctx, gt, method)
        row = {"proxy": "synthetic", "group": group, "name": name, "plan": asdict(plan), "settings": settings,
               "config": config.knobs_dict(),
               **built, "clips_full": _full_clips(scene), "metrics": res["metrics"],
               "scene": {"name": scene.name, "cameras": scene.cameras.num_cameras("train"),
                         "timesteps": scene.num_timesteps, "gaussians": scene.num_gaussians,
                         "views": [c.name for c in ctx.cameras]}}
        _keep(vdir, row, keep_bundles)
        out.append(row)
        if progress:
            print(f"  clips {row['clips_encoded']:,} of {row['clips_full']:,}  vAP {100 * row['metrics']['vAP']['mean']:.1f}"
                  f"  tIoU {100 * row['metrics']['tIoU']['mean']:.1f}", file=sys.stderr)
    return out


def run_real(rows: Sequence[tuple[str, str, ExtractPlan]], *, scene_path: Path, masks: Path, held_out: int,
             timesteps: int, work: Path, ae_epochs: int, view_scale: float, score_scale: float,
             progress: bool, own_autoencoder: bool = False, cached_only: bool = False,
             keep_bundles: bool = False) -> list[dict[str, Any]]:
    """Every row on a fitted real capture with the annotation-mask teacher, scored on held-out cameras."""
    from fourlegs_engine.language.annotations import AnnotationMaskEncoder
    from fourlegs_engine.scene.bundle import load_bundle
    from .real_lift import score, subset_bundle

    if not (scene_path / "scene.json").is_file():
        raise InputError("not a fitted scene bundle (scene.json missing)", file=scene_path, field="--real-scene")
    if not masks.is_dir():
        raise InputError("mask folder does not exist", file=masks, field="--masks")
    cams = load_bundle(scene_path).cameras.cameras(0, "train")
    held_idx = set(np.linspace(0, len(cams) - 1, held_out + 2)[1:-1].round().astype(int).tolist())
    held = [c for i, c in enumerate(cams) if i in held_idx]
    pool = [c for i, c in enumerate(cams) if i not in held_idx]
    base = work / "real" / "_subset"
    if not (base / "scene.json").is_file():
        subset_bundle(scene_path, base, pool, held, timesteps)
    settings = {"scene": str(scene_path), "timesteps": timesteps, "held_out": held_out, "ae_epochs": ae_epochs,
                "view_scale": view_scale, "score_scale": score_scale,
                "autoencoder": "own" if own_autoencoder else "shared"}
    out = []
    for group, name, plan in rows:
        vdir = work / "real" / _slug(name)
        cached = _cached(vdir, plan, settings)
        if cached is not None:
            out.append(cached)
            continue
        if cached_only:
            continue
        bundle = linked_bundle(base, vdir / "bundle")
        scene = load_bundle(bundle)
        encoder = AnnotationMaskEncoder({REAL_PHRASE: str(masks)})
        config = plan.extract_config(scene)
        if progress:
            print(f"language-cost real: {name} ...", file=sys.stderr)
        built = build_field(bundle, encoder, config, ae_epochs=ae_epochs, view_scale=view_scale, progress=False,
                            shared_autoencoder=_shared_ae(work / "real", group, own_autoencoder))
        scene = load_bundle(bundle)
        vious, vaps = score(scene, REAL_PHRASE, masks, held, score_scale)
        row = {"proxy": "real", "group": group, "name": name, "plan": asdict(plan), "settings": settings,
               "config": config.knobs_dict(),
               **built, "clips_full": _full_clips(scene),
               "metrics": {"vAP": {"mean": float(np.mean(vaps)), "std": float(np.std(vaps))},
                           "vIoU": {"mean": float(np.mean(vious)), "std": float(np.std(vious))}},
               "vap_per_t": vaps, "viou_per_t": vious,
               "scene": {"name": scene.name, "cameras": len(pool), "timesteps": scene.num_timesteps,
                         "gaussians": scene.num_gaussians, "held_out": [c.name for c in held]}}
        _keep(vdir, row, keep_bundles)
        out.append(row)
        if progress:
            print(f"  clips {row['clips_encoded']:,} of {row['clips_full']:,}  vAP {row['metrics']['vAP']['mean']:.3f}"
                  f"  vIoU {row['metrics']['vIoU']['mean']:.3f}", file=sys.stderr)
    return out


def _shared_ae(proxy_work: Path, group: str, own: bool) -> Path | None:
    """The reference row's bundle, whose autoencoder every other row reuses (None: train one)."""
    if own or group == "reference":
        return None
    ref = proxy_work / _slug(knob_rows(1)[0][1]) / "bundle"
    if not (ref / "language" / "autoencoder.json").is_file():
        raise InputError("the reference row (full) must run first: the other rows reuse its autoencoder",
                         file=ref, field="--rows")
    return ref


def _full_clips(scene: Any) -> int:
    from fourlegs_engine.language.extract import camera_layouts
    from fourlegs_engine.language.pyramid import pyramid_ratios
    layouts, _ = camera_layouts(scene, 0, pyramid_ratios())
    return int(sum(l.num_crops for l in layouts) * scene.num_timesteps)


def _cached(vdir: Path, plan: ExtractPlan, settings: dict[str, Any]) -> dict[str, Any] | None:
    """The row kept in ``vdir`` when it was made with the same plan and settings."""
    path = vdir / "result.json"
    if not path.is_file():
        return None
    row = json.loads(path.read_text(encoding="utf-8"))
    same = row.get("plan") == json.loads(json.dumps(asdict(plan))) and row.get("settings") == settings
    return row if same else None


def _keep(vdir: Path, row: dict[str, Any], keep_bundle: bool = False) -> None:
    """Keep a scored row's result (what ``--cached-only`` and reruns read); unless ``keep_bundle``, drop its
    bundle's features and field (gigabytes per row on the ``bench`` scene), keeping the autoencoder the
    other rows reuse."""
    vdir.mkdir(parents=True, exist_ok=True)
    write_json_atomic(vdir / "result.json", row, overwrite=True)
    if not keep_bundle:
        prune_row_bundle(vdir / "bundle")


def prune_row_bundle(bundle: Path) -> None:
    """Delete a scored row's teacher features and lifted field; the scene and the autoencoder stay."""
    import shutil
    from fourlegs_engine.language.autoencoder import AE_REPORT, DECODER_FILE, ENCODER_FILE

    shutil.rmtree(bundle / "features", ignore_errors=True)
    kept = {bundle / rel for rel in (AE_REPORT, ENCODER_FILE, DECODER_FILE)}
    language = bundle / "language"
    for path in (language.iterdir() if language.is_dir() else ()):
        if path not in kept:
            shutil.rmtree(path) if path.is_dir() and not path.is_symlink() else path.unlink()


# ---------------------------------------------------------------------------------------- cost
def viclip_clip_seconds(path: Path | None) -> dict[str, Any] | None:
    """Seconds per clip from a plan JSON (``fourlegs extract --dry-run --plan-json``) or a device-check JSON
    (``{"clip_s": ..., "device": ..., ...}``)."""
    if path is None:
        return None
    data = json.loads(Path(path).read_text(encoding="utf-8"))
    cal = data.get("calibration", data)
    if "clip_s" not in cal:
        raise InputError("has no calibration.clip_s (seconds per clip)", file=path)
    return {"clip_s": float(cal["clip_s"]), "device": cal.get("device", "?"), "dtype": cal.get("dtype", "?"),
            "batch": cal.get("batch"), "source": str(path)}


def calibrate_viclip_cpu(scene_path: Path, *, size: str = "l", dtype: str = "bfloat16") -> dict[str, Any]:
    """ViCLIP (random weights) seconds per clip on this CPU through the planner's calibration, on a real
    camera-timestep of ``scene_path`` (the whole per-clip path: cut, resize, normalize, network)."""
    import torch
    from fourlegs_engine.language.budget import calibrate
    from fourlegs_engine.language.extract import ExtractOptions
    from fourlegs_engine.scene.bundle import load_bundle

    encoder = random_viclip(size, dtype=dtype, device="cpu")
    scene = load_bundle(scene_path)
    cal = calibrate(scene, encoder, ExtractOptions().check(), seconds=1.0)
    return {"clip_s": cal.clip_s, "clip_cpu_s": cal.clip_cpu_s, "device": "cpu", "dtype": dtype, "batch": cal.batch,
            "clips_timed": cal.clips_timed, "threads": torch.get_num_threads(),
            "source": f"measured here: calibrate() with ViCLIP-{size.upper()} random weights"}


def random_viclip(size: Any = "l", *, dtype: str = "bfloat16", device: str = "cpu", batch_size: int = 16,
                  seed: int = 0) -> Any:
    """A ViCLIP encoder with seeded random weights (the real network code; no trained weights exist here).
    ``size``: "l", "b" or a ``ViCLIPConfig``. Video only: its tokenizer is a stand-in that knows the
    vocabulary size and encodes no text."""
    import torch
    from fourlegs_engine.language.encoders import resolve_device, resolve_dtype
    from fourlegs_engine.language.viclip import ViCLIPConfig, ViCLIPEncoder, ViCLIPModel

    config = size if isinstance(size, ViCLIPConfig) else ViCLIPConfig.preset(size)
    torch.manual_seed(seed)
    model = ViCLIPModel(config).to(resolve_dtype(dtype)).to(resolve_device(device)).eval()

    class _NoText:
        vocab_size = config.vocab_size
        path = Path("(no vocabulary: random weights, video only)")

    return ViCLIPEncoder(model, _NoText(), batch_size=batch_size, name="viclip")


def panoptic_hours(row: dict[str, Any], clip_s: float, exit_share: float) -> dict[str, float]:
    """The row's plan on a Panoptic-sized rig: clips, reduction and hours at ``clip_s`` seconds per clip."""
    plan = ExtractPlan(**{**row["plan"], "levels": tuple(row["plan"]["levels"]) if row["plan"]["levels"] else None})
    if plan.cameras is not None:  # the row's share of its proxy's cameras, on the 27-camera rig
        plan = plan.with_(cameras=max(1, int(round(plan.cameras / row["scene"]["cameras"] * PANOPTIC["cameras"]))),
                          name=plan.name)
    clips = plan_clips(plan, PANOPTIC["cameras"], PANOPTIC["timesteps"], PANOPTIC["width"], PANOPTIC["height"],
                       exit_share=exit_share, fps=PANOPTIC["fps"])
    return {**clips, "hours": clips["expected"] * clip_s / 3600.0}


def plan_key(plan: dict[str, Any] | ExtractPlan) -> str:
    """A plan's knobs (not its name) as a key: rows of equal knobs share their early-exit share."""
    d = asdict(plan) if isinstance(plan, ExtractPlan) else dict(plan)
    d.pop("name", None)
    d.setdefault("timestep_seconds", None)
    return json.dumps({k: (list(v) if isinstance(v, tuple) else v) for k, v in sorted(d.items())})


def sequence_exit_shares(scene_path: Path, plans: Sequence[ExtractPlan], *, progress: bool = True) -> dict[str, Any]:
    """Each early-exit plan's copied share over a whole fitted sequence: every encoded timestep after the
    first, on every training camera (the rig a Panoptic projection prices), instead of the real proxy's
    first few timesteps, whose windows are shorter. Foreground plans only; each (frame, camera) is
    rendered once for all plans.

    Returns ``{"scene", "timesteps", "cameras", "shares": {plan_key: {"share", "camera_timesteps"}}}``."""
    import torch
    from fourlegs_engine.language.frames import frame_crop_means
    from fourlegs_engine.language.pyramid import crop_layout
    from fourlegs_engine.language.skipping import (comparison_frames, encoded_timesteps, foreground_values,
                                                   render_foreground, unchanged_crops)
    from fourlegs_engine.scene.bundle import load_bundle

    scene = load_bundle(scene_path)
    values = foreground_values(scene)
    if values is None:
        raise InputError("the scene has no foreground flags", file=scene_path, field="foreground")
    T, num_cams = scene.num_timesteps, scene.cameras.num_cameras("train")
    configs = {plan_key(p): p.extract_config(scene) for p in plans if p.early_exit == "foreground"}
    layouts = {(key, c): crop_layout(cam.width, cam.height, config.ratios, config.crop_stride)
               for key, config in configs.items() for c, cam in enumerate(scene.cameras.cameras(0, "train"))}
    signals: dict[tuple[str, int, int], torch.Tensor] = {}   # (plan, frame, camera) -> (num_crops,) coverage

    def signal(key: str, k: int, c: int) -> torch.Tensor:
        if (key, k, c) not in signals:               # one render of the frame serves every plan
            coverage = render_foreground(scene, scene.cameras.cameras(k, "train")[c], k, values)
            for other in configs:
                signals[(other, k, c)] = frame_crop_means(coverage, layouts[(other, c)])[:, 0]
        return signals[(key, k, c)]

    counts = {key: [0, 0, 0] for key in configs}     # copied crops, crops, camera-timesteps
    with torch.no_grad():
        for key, config in configs.items():
            grid = encoded_timesteps(T, config.timestep_stride)
            cams = range(num_cams) if config.cameras is None else config.cameras
            for i, t in enumerate(grid[1:], start=1):
                span = comparison_frames(t, grid[i - 1], T)
                for c in cams:
                    same = unchanged_crops(lambda k: signal(key, k, c), span, "foreground", config.unchanged_below)
                    counts[key][0] += int(same.sum())
                    counts[key][1] += int(same.numel())
                    counts[key][2] += 1
                if progress:
                    print(f"  exit share, timestep {t}: {counts[key][0] / max(counts[key][1], 1):.3f}", file=sys.stderr)
    shares = {key: {"share": copied / max(total, 1), "camera_timesteps": n} for key, (copied, total, n) in counts.items()}
    return {"scene": str(scene_path), "timesteps": T, "cameras": num_cams, "shares": shares}


def exit_share_of(row: dict[str, Any]) -> float:
    """Measured share of crops the row's early exit copied, over the timesteps that could copy."""
    copied, encoded = row.get("clips_copied", 0), row.get("clips_encoded", 0)
    steps = max(row.get("timesteps_encoded", 1), 1)
    if not copied:
        return 0.0
    per_step = (copied + encoded) / steps  # crops per encoded timestep (the first copies nothing)
    return float(copied / max(per_step * (steps - 1), 1e-9))


# -------------------------------------------------------------------------------------- report
def summarize(report: dict[str, Any]) -> dict[str, Any]:
    """Add each row's cost (L/14 seconds on this proxy, Panoptic-sized hours) and its loss against the
    reference row of its proxy."""
    cpu, gpu = report.get("clip_seconds", {}).get("cpu"), report.get("clip_seconds", {}).get("gpu")
    # the Panoptic projection takes each plan's early-exit share from the whole sequence when measured
    # (--exit-share-scene), else from the real capture's row of that plan
    real_shares = {plan_key(r["plan"]): exit_share_of(r) for r in report["rows"] if r["proxy"] == "real"}
    real_shares.update({k: v["share"] for k, v in (report.get("sequence_exit_shares") or {}).get("shares", {}).items()})
    for proxy in PROXIES:
        rows = [r for r in report["rows"] if r["proxy"] == proxy]
        ref = next((r for r in rows if r["group"] == "reference"), None)
        for r in rows:
            r["share_of_full"] = r["clips_encoded"] / max(r["clips_full"], 1)
            r["reduction"] = r["clips_full"] / max(r["clips_encoded"], 1)
            if cpu:
                r["l14_cpu_s"] = r["clips_encoded"] * cpu["clip_s"]
            if gpu:
                r["l14_gpu_s_derived"] = r["clips_encoded"] * gpu["clip_s"]
            share = real_shares.get(plan_key(r["plan"]), exit_share_of(r))
            if cpu:
                r["panoptic"] = panoptic_hours(r, cpu["clip_s"], share)
                if gpu:
                    r["panoptic"]["gpu_hours_derived"] = r["panoptic"]["expected"] * gpu["clip_s"] / 3600.0
            if ref is not None:
                r["loss_points"] = {k: 100 * (ref["metrics"][k]["mean"] - r["metrics"][k]["mean"]) for k in r["metrics"]}
    return report


def markdown(report: dict[str, Any]) -> str:
    cs = report.get("clip_seconds", {})
    lines = [f"Command: `{report.get('command', '')}`", ""]
    if cs.get("cpu"):
        c = cs["cpu"]
        lines.append(f"Seconds per clip (ViCLIP-L/14, {c['dtype']}, batch {c.get('batch')}) on this CPU: "
                     f"{c['clip_s']:.3g} s ({c['source']}).")
    if cs.get("gpu"):
        g = cs["gpu"]
        lines.append(f"GPU (derived: clips x the device check's {g['clip_s'] * 1000:.3g} ms per clip, {g['device']}, "
                     f"{g['dtype']}, batch {g.get('batch')}; {g['source']}).")
    for proxy in PROXIES:
        rows = [r for r in report["rows"] if r["proxy"] == proxy]
        if not rows:
            continue
        s = rows[0]["scene"]
        metrics = list(rows[0]["metrics"])
        lines += ["", f"### {proxy} proxy: {s['name']} ({s['cameras']} training cameras, {s['timesteps']} timesteps, "
                      f"{s['gaussians']:,} Gaussians)", ""]
        head = ["group", "variant", "clips encoded", "x fewer", "L/14 CPU h here", "L/14 GPU min here (derived)",
                "Panoptic 27x150: x fewer", "Panoptic L/14 CPU h", "Panoptic L/14 GPU h (derived)"]
        head += [f"{m}" for m in metrics] + [f"Δ{m} (points)" for m in metrics]
        lines += ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
        for r in rows:
            p = r.get("panoptic", {})
            cells = [r["group"], r["name"], f"{r['clips_encoded']:,}", f"{r['reduction']:.1f}",
                     _fmt(r.get("l14_cpu_s"), 3600), _fmt(r.get("l14_gpu_s_derived"), 60),
                     f"{p['reduction']:.1f}" if p else "", _fmt(p.get("hours"), 1),
                     _fmt(p.get("gpu_hours_derived"), 1)]
            cells += [f"{100 * r['metrics'][m]['mean']:.1f}" for m in metrics]
            cells += [f"{0.0 - r['loss_points'][m]:+.1f}" if "loss_points" in r else "" for m in metrics]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _fmt(value: float | None, unit: float) -> str:
    if value is None:
        return ""
    v = value / unit
    return f"{v:,.1f}" if v >= 10 else f"{v:.2f}"


def plot(report: dict[str, Any], path: Path) -> None:
    """vAP and tIoU (synthetic) / vAP and vIoU (real) against the Panoptic-sized L/14 hours (CPU, measured
    seconds per clip), Pareto front dashed, the default plan starred."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from .accuracy_time import _pareto

    panels = [(p, m) for p, m in (("synthetic", "vAP"), ("synthetic", "tIoU"), ("real", "vAP"), ("real", "vIoU"))
              if any(r["proxy"] == p for r in report["rows"])]
    if not panels:
        return
    fig, axes = plt.subplots(1, len(panels), figsize=(5 * len(panels), 4.2), dpi=100, squeeze=False)
    groups = list(dict.fromkeys(r["group"] for r in report["rows"]))
    colors = {g: plt.cm.tab10(i % 10) for i, g in enumerate(groups)}
    try:
        for ax, (proxy, metric) in zip(axes[0], panels):
            rows = [r for r in report["rows"] if r["proxy"] == proxy]
            key = "hours" if all("panoptic" in r for r in rows) else None
            xs = np.array([r["panoptic"]["hours"] if key else r["share_of_full"] for r in rows])
            ys = np.array([100 * r["metrics"][metric]["mean"] for r in rows])
            for r, x, y in zip(rows, xs, ys):
                ax.scatter(x, y, color=colors[r["group"]], s=80 if r["group"] == "default" else 28,
                           marker="*" if r["group"] == "default" else "o", zorder=3)
                ax.annotate(r["name"], (x, y), fontsize=6, xytext=(3, 3), textcoords="offset points")
            _pareto(ax, xs, ys)
            ax.set_xscale("log")
            ax.set_xlabel("ViCLIP-L/14 CPU hours, 27 cameras x 150 timesteps" if key else "share of the full clips")
            ax.set_ylabel(f"{metric} (%)")
            ax.set_title(f"{proxy} proxy: {metric}")
            for g in groups:
                ax.scatter([], [], color=colors[g], label=g)
            ax.legend(fontsize=6, loc="lower right")
        fig.suptitle("teacher features: cost knobs against accuracy")
        fig.tight_layout()
        with atomic_path(path, overwrite=True) as tmp:
            fig.savefig(tmp, format="png")
    finally:
        plt.close(fig)


# ------------------------------------------------------------------------------------------ CLI
def register_bench(bench_sub: Any) -> None:
    p = bench_sub.add_parser(
        "language-cost", help="teacher-feature cost knobs: clips and ViCLIP hours against vAP/tIoU (Pareto)",
        description="Extract, train the autoencoder, lift and score once per cost knob setting (camera subset, "
                    "timestep stride, pyramid levels, crop stride, early exits, the default plan) on the "
                    "synthetic proxy (simulated encoder, six metrics) and the real proxy (annotation masks of a "
                    "fitted capture, held-out cameras); cost = clips encoded x ViCLIP-L/14 seconds per clip.")
    p.add_argument("--proxies", default="synthetic,real", help="synthetic,real (default both)")
    p.add_argument("--scene", default="bench", choices=("tiny", "demo", "bench", "full"),
                   help="synthetic scene size (default bench)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--real-scene", default=None, help="fitted real scene bundle (`fourlegs fit`), read only")
    p.add_argument("--masks", default="../shared/data/panoptic-basketball/seg",
                   help="the real capture's masks {camera}/{t:06d}.png (default the Panoptic capture's seg/)")
    p.add_argument("--exit-share-scene", default=None, metavar="SCENE",
                   help="a fitted scene of the whole sequence (e.g. all 150 timesteps of the capture): the early-exit "
                        "share of each plan is measured on all of it, every camera, for the Panoptic projection "
                        "(default: the real proxy's row of the plan, over its first --timesteps)")
    p.add_argument("--held-out", type=int, default=4, help="real proxy: training cameras held out (default 4)")
    p.add_argument("--timesteps", type=int, default=9, help="real proxy: first timesteps used (default 9)")
    p.add_argument("--rows", default=None,
                   help="only the rows whose name contains one of these (separated by ';', or by ',' when the "
                        "text holds no ';')")
    p.add_argument("--ae-epochs", type=int, default=4, help="autoencoder epochs (default 4)")
    p.add_argument("--own-autoencoder", action="store_true",
                   help="train an autoencoder per row (default: every row reuses the reference row's, so the rows "
                        "differ only in their teacher features)")
    p.add_argument("--view-scale", type=float, default=0.5, help="lift views at this scale (default 0.5, the pipeline's)")
    p.add_argument("--score-scale", type=float, default=0.25, help="real proxy: held-out maps at this scale")
    p.add_argument("--cpu-clip-seconds", default=None, metavar="JSON",
                   help="ViCLIP-L/14 seconds per clip on the CPU from a plan JSON; default: calibrate here")
    p.add_argument("--gpu-clip-seconds", default=None, metavar="JSON",
                   help="the device check's seconds per clip (GPU rows are derived from it)")
    p.add_argument("--threads", type=int, default=None, help="torch threads")
    p.add_argument("--keep-bundles", action="store_true",
                   help="keep each scored row's features and lifted field in --work (default: dropped once the row "
                        "is scored; a row of the bench scene holds several GB)")
    p.add_argument("--cached-only", action="store_true",
                   help="tabulate only the rows already scored in --work (no new extraction)")
    p.add_argument("--out", default="docs/bench/language_cost", help="output folder (default docs/bench/language_cost)")
    p.add_argument("--work", default=None, help="working folder for the rows' bundles (default OUT/work)")
    p.set_defaults(func=run_cli)


def run_cli(args: argparse.Namespace) -> int:
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    proxies = [p.strip() for p in args.proxies.split(",") if p.strip()]
    bad = [p for p in proxies if p not in PROXIES]
    if bad:
        raise InputError(f"unknown proxy {bad[0]!r} (choose from {', '.join(PROXIES)})", field="--proxies")
    if "real" in proxies and not args.real_scene:
        raise InputError("the real proxy needs a fitted scene", field="--real-scene")
    if "real" in proxies:  # the inputs are checked before the output folder is made
        from fourlegs_engine.scene.bundle import load_bundle
        load_bundle(args.real_scene)
        if not Path(args.masks).is_dir():
            raise InputError("is not a folder of annotation masks", file=args.masks, field="--masks")
    out = Path(args.out)
    work = Path(args.work) if args.work else out / "work"
    out.mkdir(parents=True, exist_ok=True)
    json_path = out / "language_cost.json"
    report = json.loads(json_path.read_text(encoding="utf-8")) if json_path.is_file() else {"rows": []}
    wanted = row_patterns(args.rows)

    def pick(rows):
        return [r for r in rows if not wanted or any(w in r[1] for w in wanted)]

    start = time.perf_counter()
    new_rows = []
    if "synthetic" in proxies:
        from fourlegs_engine.scene.bundle import load_bundle
        from fourlegs_engine.demo.synthetic import ensure_demo_bundle
        cams = load_bundle(ensure_demo_bundle(args.scene, args.seed)).cameras.num_cameras("train")
        new_rows += run_synthetic(pick(knob_rows(cams)), size=args.scene, seed=args.seed, work=work,
                                  ae_epochs=args.ae_epochs, view_scale=args.view_scale, progress=True,
                                  own_autoencoder=args.own_autoencoder, cached_only=args.cached_only,
                                  keep_bundles=args.keep_bundles)
    if "real" in proxies:
        from fourlegs_engine.scene.bundle import load_bundle
        cams = load_bundle(args.real_scene).cameras.num_cameras("train") - args.held_out
        new_rows += run_real(pick(knob_rows(cams)), scene_path=Path(args.real_scene), masks=Path(args.masks).resolve(),
                             held_out=args.held_out, timesteps=args.timesteps, work=work, ae_epochs=args.ae_epochs,
                             view_scale=args.view_scale, score_scale=args.score_scale, progress=True,
                             own_autoencoder=args.own_autoencoder, cached_only=args.cached_only,
                             keep_bundles=args.keep_bundles)
    if args.exit_share_scene:
        plans = {plan_key(plan): plan for _, _, plan in pick(knob_rows(12)) if plan.early_exit == "foreground"}
        measured = report.get("sequence_exit_shares") or {}
        if measured.get("scene") != str(Path(args.exit_share_scene).resolve()):
            measured = {}
        missing = [plan for key, plan in plans.items() if key not in measured.get("shares", {})]
        if missing:
            got = sequence_exit_shares(Path(args.exit_share_scene).resolve(), missing)
            got["shares"] = {**measured.get("shares", {}), **got["shares"]}
            report["sequence_exit_shares"] = got
    keys = {(r["proxy"], r["name"]) for r in new_rows}
    report["rows"] = [r for r in report["rows"] if (r["proxy"], r["name"]) not in keys] + new_rows
    order = {name: i for i, (_, name, _) in enumerate(knob_rows(12))}
    report["rows"].sort(key=lambda r: (PROXIES.index(r["proxy"]), order.get(r["name"], _row_order(r["name"]))))
    clip = report.setdefault("clip_seconds", {})
    if args.cpu_clip_seconds:
        clip["cpu"] = viclip_clip_seconds(Path(args.cpu_clip_seconds))
    elif not clip.get("cpu"):
        scene_for_cal = Path(args.real_scene) if args.real_scene else None
        if scene_for_cal is not None:
            clip["cpu"] = calibrate_viclip_cpu(scene_for_cal)
    if args.gpu_clip_seconds:
        clip["gpu"] = viclip_clip_seconds(Path(args.gpu_clip_seconds))
    report["command"] = "fourlegs " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    report["torch_threads"] = torch.get_num_threads()
    report["seconds"] = time.perf_counter() - start
    summarize(report)
    write_json_atomic(json_path, report, overwrite=True)
    with atomic_path(out / "language_cost.md", overwrite=True) as tmp:
        tmp.write_text(markdown(report), encoding="utf-8")
    plot(report, out / "language_cost.png")
    print(markdown(report))
    print(f"wrote {json_path}, {out / 'language_cost.md'}, {out / 'language_cost.png'}")
    return 0


def row_patterns(text: str | None) -> list[str]:
    """The ``--rows`` patterns: separated by ';' when the text holds one (row names hold commas), else by ','."""
    sep = ";" if text and ";" in text else ","
    return [w.strip() for w in (text or "").split(sep) if w.strip()]


def _row_order(name: str) -> int:
    """Rows whose name changes with the camera count (cameras group) sort with the cameras rows."""
    return 1 if "cameras" in name else 99
