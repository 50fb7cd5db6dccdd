"""``fourlegs bench real-lift``: the 4D lift of annotation masks on a real capture, scored on held-out cameras.

The teacher is the annotation-mask encoder (``--encoder masks``: per-pixel masks, no network). From a
fitted real scene (``fourlegs fit``) the bench keeps ``--held-out`` training cameras aside, lifts the
field of ``--phrase`` from subsets of the remaining training cameras (``--sizes``) with each distillation
mode (lift, lift+refine, optimize; short iteration counts), renders the relevancy of the phrase from the
held-out cameras and scores it against their masks, per timestep:

- vIoU: box IoU between the box of the relevancy > 0.5 pixels and the box of the mask (every timestep
  of the capture holds the phrase, so S_i = S_u = all timesteps and vIoU is the mean box IoU);
- vAP: pixel-level average precision of the relevancy map against the mask.

Each is averaged over the held-out cameras; the table gives the mean over timesteps and seconds of
extraction, autoencoder training and distillation. Writes Markdown, JSON and a plot.
"""
from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

DEFAULT_MASKS = "../shared/data/panoptic-basketball/seg"
MODES = ("lift", "lift+refine", "optimize")


def register_bench(bench_sub: Any) -> None:
    p = bench_sub.add_parser(
        "real-lift", help="lift annotation masks on a real fitted scene: vIoU/vAP on held-out cameras vs cameras used",
        description="Annotation masks (not a language model) lifted into a per-Gaussian field from subsets of "
                    "the training cameras of a fitted real scene; the rendered relevancy is scored against the "
                    "masks of held-out training cameras (vIoU, vAP per timestep and mean), per mode, with seconds.")
    p.add_argument("--scene", required=True, help="fitted scene bundle of the capture (`fourlegs fit`), read only")
    p.add_argument("--masks", default=DEFAULT_MASKS, help=f"mask folder {{camera}}/{{t:06d}}.png (default {DEFAULT_MASKS})")
    p.add_argument("--phrase", default="a person", help="the masks' phrase (default 'a person')")
    p.add_argument("--sizes", default="4,8,16,23", help="training-camera subset sizes (default 4,8,16,23)")
    p.add_argument("--held-out", type=int, default=4, help="training cameras kept for scoring (default 4)")
    p.add_argument("--timesteps", type=int, default=3, help="timesteps of the scene used (default 3)")
    p.add_argument("--first-timestep", type=int, default=0,
                   help="the first of them (default 0; e.g. 56 for the ball's flight in the basketball capture)")
    p.add_argument("--evidence", choices=("train", "train+held-out", "both"), default="train",
                   help="lift from the training subset's masks, also from the held-out cameras' own masks (more "
                        "evidence: their score must not drop), or both rows (default train)")
    p.add_argument("--ae-balance", default="auto", choices=("auto", "directions", "none"),
                   help="the autoencoder's training sample (AETrainOptions.balance; comma lists not taken)")
    p.add_argument("--modes", default="lift,lift+refine,optimize", help="distillation modes (default all three)")
    p.add_argument("--iterations", type=int, default=20, help="refine/optimize iterations per timestep (default 20)")
    p.add_argument("--view-scale", type=float, default=0.5, help="distillation views at this scale (default 0.5)")
    p.add_argument("--score-scale", type=float, default=0.25, help="held-out maps at this scale (default 0.25)")
    p.add_argument("--ae-epochs", type=int, default=2, help="autoencoder epochs (default 2)")
    p.add_argument("--out", default="bench-out/real_lift", help="output directory (default bench-out/real_lift)")
    p.add_argument("--work", default=None, help="working directory for the subset bundles (default OUT/work)")
    p.set_defaults(func=run)


def shifted_masks(masks: Path, first: int, count: int, target: Path) -> Path:
    """``masks`` ({camera}/{t:06d}.png) seen from timestep ``first`` on: links named from 0 in ``target``."""
    if first == 0:
        return masks
    for cam in sorted(p for p in masks.iterdir() if p.is_dir()):
        (target / cam.name).mkdir(parents=True, exist_ok=True)
        for t in range(count):
            src, dst = cam / f"{first + t:06d}.png", target / cam.name / f"{t:06d}.png"
            if src.is_file() and not dst.exists():
                dst.symlink_to(src.resolve())
    return target


def subset_bundle(source: Path, target: Path, train: list[Any], held_out: list[Any], timesteps: int,
                  first: int = 0) -> Any:
    """Write ``timesteps`` of ``source`` from ``first`` on with ``train`` as training and ``held_out`` as test
    cameras."""
    from fourlegs_engine.scene.bundle import load_bundle, write_bundle
    from fourlegs_engine.scene.camera import CameraRig
    from fourlegs_engine.scene.gaussians import GaussianSequence
    from fourlegs_engine.scene.scene import Scene

    scene = load_bundle(source)
    g = scene.gaussians
    a = min(max(0, int(first)), g.num_timesteps - 1)
    T = min(int(timesteps), g.num_timesteps - a)
    span = slice(a, a + T)

    seq = GaussianSequence(means=np.asarray(g.means[span]), rotations=np.asarray(g.rotations[span]),
                           log_scales=np.asarray(g.log_scales[span]) if np.ndim(g.log_scales) == 3 else np.asarray(g.log_scales),
                           opacity_logits=np.asarray(g.opacity_logits),
                           colors=None if g.colors is None else (np.asarray(g.colors[span]) if np.ndim(g.colors) == 3
                                                                 else np.asarray(g.colors)),
                           sh=None if g.sh is None else (np.asarray(g.sh[span]) if np.ndim(g.sh) == 4 else np.asarray(g.sh)),
                           foreground=None if g.foreground is None else np.asarray(g.foreground))
    sub = Scene(gaussians=seq, cameras=CameraRig.static(train, held_out, T), name=scene.name, fps=scene.fps)
    return load_bundle(write_bundle(sub, target, overwrite=True))


def score(scene: Any, phrase: str, masks: Path, held_out: list[Any], scale: float) -> tuple[list[float], list[float]]:
    """Per-timestep (vIoU, vAP) of the scene's field, averaged over the held-out cameras."""
    import torch.nn.functional as F
    import torch

    from fourlegs_bench.metrics import average_precision, box_iou, mask_to_box
    from fourlegs_engine.language.annotations import read_mask
    from fourlegs_engine.pipeline import QueryOptions, open_query_engine

    engine = open_query_engine(scene, options=QueryOptions.exact(spatial="fast"))
    vious, vaps = [], []
    for t in range(scene.num_timesteps):
        ious, aps = [], []
        for cam in held_out:
            rel = engine.relevancy_map(phrase, cam, t, fast=True, outputs=("relevancy",), scale=scale)["relevancy"]
            mask = read_mask(masks / cam.name / f"{t:06d}.png").astype(np.float32)
            gt = F.interpolate(torch.from_numpy(mask)[None, None], size=rel.shape, mode="area")[0, 0].numpy() >= 0.5
            pred_box, gt_box = mask_to_box(rel > 0.5), mask_to_box(gt)
            ious.append(0.0 if pred_box is None or gt_box is None
                        else float(box_iou(pred_box[None], gt_box[None])[0]))
            aps.append(average_precision(rel.ravel(), gt.ravel()))
        vious.append(float(np.mean(ious)))
        vaps.append(float(np.mean(aps)))
    return vious, vaps


def run(args: argparse.Namespace) -> int:
    from fourlegs_engine.errors import InputError
    from fourlegs_engine.language.annotations import AnnotationMaskEncoder
    from fourlegs_engine.language.autoencoder import AETrainOptions, train_autoencoder
    from fourlegs_engine.language.distill import distill_scene
    from fourlegs_engine.language.extract import extract_features
    from fourlegs_engine.scene.bundle import load_bundle

    source, masks = Path(args.scene), Path(args.masks).resolve()
    if not (source / "scene.json").is_file():
        raise InputError("not a fitted scene bundle (scene.json missing)", file=source, field="--scene")
    if not masks.is_dir():
        raise InputError("mask folder does not exist", file=masks, field="--masks")
    sizes = [int(s) for s in args.sizes.split(",") if s.strip()]
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    out = Path(args.out)
    work = Path(args.work) if args.work else out / "work"
    out.mkdir(parents=True, exist_ok=True)
    cams = load_bundle(source).cameras.cameras(0, "train")
    # held-out cameras spread over the ring; subsets evenly spaced over the rest
    held_idx = set(np.linspace(0, len(cams) - 1, args.held_out + 2)[1:-1].round().astype(int).tolist())
    held_out = [c for i, c in enumerate(cams) if i in held_idx]
    pool = [c for i, c in enumerate(cams) if i not in held_idx]
    if max(sizes) > len(pool):
        raise InputError(f"largest subset {max(sizes)} > {len(pool)} cameras left after holding out "
                         f"{len(held_out)}", field="--sizes")
    rows: list[dict[str, Any]] = []
    masks = shifted_masks(masks, args.first_timestep, args.timesteps, work / f"masks_from_{args.first_timestep}")
    evidences = ("train", "train+held-out") if args.evidence == "both" else (args.evidence,)
    for size, evidence in ((s_, e) for s_ in sizes for e in evidences):
        train = [pool[i] for i in np.linspace(0, len(pool) - 1, size).round().astype(int)]
        lifted_from = train + (held_out if evidence == "train+held-out" else [])
        scene = subset_bundle(source, work / f"cams{size}_{evidence}", lifted_from, held_out, args.timesteps,
                              args.first_timestep)
        encoder = AnnotationMaskEncoder({args.phrase: str(masks)})
        s = time.perf_counter()
        extract_features(scene, encoder, overwrite=True)
        extract_s = time.perf_counter() - s
        s = time.perf_counter()
        ae = train_autoencoder(scene, AETrainOptions(epochs=args.ae_epochs, balance=args.ae_balance), overwrite=True)
        ae_s = time.perf_counter() - s
        for mode in modes:
            s = time.perf_counter()
            distill_scene(scene, mode=mode, iterations=None if mode == "lift" else args.iterations,
                          view_scale=args.view_scale, overwrite=True)
            distill_s = time.perf_counter() - s
            scene = load_bundle(scene.root)
            vious, vaps = score(scene, args.phrase, masks, held_out, args.score_scale)
            row = {"cameras": size, "evidence": evidence, "ae_balance": ae.get("balance", "none"),
                   "mode": mode, "iterations": 0 if mode == "lift" else args.iterations,
                   "viou_per_t": vious, "vap_per_t": vaps, "viou": float(np.mean(vious)), "vap": float(np.mean(vaps)),
                   "extract_s": extract_s, "train_ae_s": ae_s, "distill_s": distill_s,
                   "distill_s_per_t": distill_s / scene.num_timesteps}
            rows.append(row)
            print(f"{size:3d} cameras ({evidence}) {mode:12s} vIoU {row['viou']:.3f} vAP {row['vap']:.3f} "
                  f"distill {distill_s:.1f} s", file=sys.stderr)
    command = "fourlegs bench real-lift " + " ".join(shlex.quote(a) for a in sys.argv[3:])
    result = {"command": command, "scene": str(source), "masks": str(masks), "phrase": args.phrase,
              "held_out": [c.name for c in held_out], "timesteps": args.timesteps,
              "first_timestep": args.first_timestep,
              "view_scale": args.view_scale, "score_scale": args.score_scale, "rows": rows}
    (out / "real_lift.json").write_text(json.dumps(result, indent=1))
    (out / "real_lift.md").write_text(markdown(result))
    plot(rows, out / "real_lift.png")
    print(markdown(result))
    return 0


def markdown(result: dict[str, Any]) -> str:
    first = result.get("first_timestep", 0)
    lines = [f"Held-out cameras {', '.join(result['held_out'])}; phrase {result['phrase']!r}; "
             f"{result['timesteps']} timesteps from t={first}.", "",
             "| cameras | evidence | AE sample | mode | iterations | vIoU mean | vAP mean | vIoU per t | vAP per t | "
             "extract s | train-ae s | distill s/timestep |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        lines.append(f"| {r['cameras']} | {r.get('evidence', 'train')} | {r.get('ae_balance', 'none')} | "
                     f"{r['mode']} | {r['iterations']} | {r['viou']:.3f} | {r['vap']:.3f} | "
                     f"{' '.join(f'{v:.2f}' for v in r['viou_per_t'])} | {' '.join(f'{v:.2f}' for v in r['vap_per_t'])} | "
                     f"{r['extract_s']:.1f} | {r['train_ae_s']:.1f} | {r['distill_s_per_t']:.1f} |")
    return "\n".join(lines) + "\n"


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
    for mode, evidence in dict.fromkeys((r["mode"], r.get("evidence", "train")) for r in rows):
        sel = [r for r in rows if r["mode"] == mode and r.get("evidence", "train") == evidence]
        label = mode if evidence == "train" else f"{mode}, {evidence}"
        for ax, key in zip(axes, ("viou", "vap")):
            ax.plot([r["cameras"] for r in sel], [r[key] for r in sel], "o-" if evidence == "train" else "s--",
                    label=label)
    for ax, name in zip(axes, ("vIoU", "vAP")):
        ax.set_xlabel("training cameras lifted from")
        ax.set_ylabel(f"{name} on held-out cameras")
        ax.set_ylim(0, 1)
        ax.grid(alpha=0.3)
    axes[0].legend()
    fig.suptitle("annotation masks lifted to 4D (real capture)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
