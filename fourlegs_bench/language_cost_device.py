"""Device check of the extraction plan: ViCLIP (random weights) seconds per clip on a GPU, and the dry-run
estimate against a measured extraction of a few camera-timesteps there.

    python -m fourlegs_bench.language_cost_device SCENE_BUNDLE OUT.json [--device cuda] [--size l]

1. ``calibrate`` (the planner's own calibration: cut, resize, normalize, network) for each precision and
   batch size: seconds per clip, network seconds per clip, seconds per rendered frame.
2. For two plans (the full pyramid on a few cameras, the default plan on a few cameras), the estimate of
   ``estimate_plan`` for a few timesteps, then ``extract_features`` of exactly those, timed: the ratio.

Writes OUT.json (the figures ``fourlegs bench language-cost --gpu-clip-seconds`` reads: the best
``clip_s`` row is copied to the top level) and prints a summary. Random weights: seconds depend only on
the shapes; nothing here measures retrieval quality.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import torch

from fourlegs_bench.language_cost import random_viclip
from fourlegs_engine.language.budget import calibrate, estimate_plan
from fourlegs_engine.language.plans import PLANS
from fourlegs_engine.language.extract import ExtractOptions, extract_features
from fourlegs_engine.scene.bundle import load_bundle


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("scene")
    p.add_argument("out")
    p.add_argument("--device", default="cuda")
    p.add_argument("--size", default="l")
    p.add_argument("--dtypes", default="bfloat16,float16,float32")
    p.add_argument("--batches", default="16,32,64")
    p.add_argument("--seconds", type=float, default=2.0)
    p.add_argument("--cameras", type=int, default=3, help="cameras of the measured extractions")
    p.add_argument("--timesteps", default="3:5", help="timesteps of the measured extractions")
    p.add_argument("--ratios", default=None, help="pyramid ratios of the measured extractions (default the paper's)")
    args = p.parse_args()
    if args.size == "small":  # a quick run of this script anywhere (not a ViCLIP size)
        from fourlegs_engine.language.viclip import ViCLIPConfig
        args.size = ViCLIPConfig.base().with_(image_size=64, vision_width=128, vision_layers=2, vision_heads=2)

    work = Path(tempfile.mkdtemp(prefix="langcost-"))
    bundle = work / "scene"
    shutil.copytree(args.scene, bundle)
    scene = load_bundle(bundle)
    info = {"device": args.device, "torch": torch.__version__, "threads": torch.get_num_threads(),
            "gpu": torch.cuda.get_device_name(0) if args.device.startswith("cuda") else None,
            "scene": str(args.scene), "size": str(getattr(args.size, "size_name", args.size)), "rows": [],
            "checks": []}
    started = time.perf_counter()
    for dtype in args.dtypes.split(","):
        enc = random_viclip(args.size, dtype=dtype, device=args.device)
        for batch in (int(b) for b in args.batches.split(",")):
            enc.batch_size = batch
            cal = calibrate(scene, enc, ExtractOptions(batch_size=batch).check(), seconds=args.seconds)
            # ``batch`` asked for; the calibration's ``clips_per_call`` may be smaller (what fits its seconds)
            row = {**cal.to_dict(), "dtype": dtype, "batch": batch, "clips_per_call": cal.batch}
            info["rows"].append(row)
            print(f"{dtype:9s} batch {batch:3d}: {cal.clip_s * 1000:8.2f} ms/clip (network {cal.network_s * 1000:8.2f}),"
                  f" {cal.frame_s:.3f} s/frame, {cal.clips_timed} clips", flush=True)
        del enc
        if args.device.startswith("cuda"):
            torch.cuda.empty_cache()
    best = min(info["rows"], key=lambda r: r["clip_s"])
    info.update({"clip_s": best["clip_s"], "dtype": best["dtype"], "batch": best["batch"], "network_s": best["network_s"]})
    enc = random_viclip(args.size, dtype=best["dtype"], device=args.device, batch_size=best["batch"])
    base = ExtractOptions(batch_size=best["batch"])
    if args.ratios:
        base = ExtractOptions(batch_size=best["batch"], ratios=tuple(float(r) for r in args.ratios.split(",")))
    for name, plan in (("full", PLANS["full"].with_(cameras=args.cameras, name="full")),
                       ("default", PLANS["default"].with_(cameras=args.cameras, name="default"))):
        est = estimate_plan(scene, enc, plan, base, timesteps=args.timesteps)
        rep = extract_features(scene, enc, est.config, timesteps=args.timesteps, overwrite=True)
        check = {"plan": name, "timesteps": args.timesteps, "cameras": args.cameras,
                 "estimate_s": est.seconds, "measured_s": rep.seconds, "ratio": est.seconds / rep.seconds,
                 "estimate_cpu_s": est.cpu_seconds, "measured_cpu_s": rep.cpu_seconds,
                 "clips_estimated": est.counts.clips_expected, "clips_encoded": rep.clips_encoded,
                 "clips_copied": rep.clips_copied, "lines": est.lines()}
        info["checks"].append(check)
        print("\n".join(est.lines()))
        print(f"  measured {rep.seconds:.1f} s ({rep.clips_encoded} clips encoded, {rep.clips_copied} copied); "
              f"estimate / measured = {check['ratio']:.2f}", flush=True)
    info["seconds"] = time.perf_counter() - started
    Path(args.out).write_text(json.dumps(info, indent=1))
    shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
