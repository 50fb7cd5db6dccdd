"""CPU milliseconds per step of a later timestep's fit, continued from a fitted bundle, on one thread.

    OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python scripts/fit_step_time.py BUNDLE CAPTURE \
        [--timestep 100] [--steps 40] [--preset accurate] [--profile]

The bundle's timesteps t − 1 and t − 2 are the previous ones, its first timestep the static model (with its
colour correction), so the step is the one `fourlegs fit` would take at timestep t with that preset.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("bundle")
    p.add_argument("capture")
    p.add_argument("--timestep", type=int, default=100)
    p.add_argument("--steps", type=int, default=40)
    p.add_argument("--preset", default="accurate")
    p.add_argument("--profile", action="store_true", help="also print torch.profiler's table")
    args = p.parse_args()
    torch.set_num_threads(1)
    from fourlegs_engine.fit.dataset import Capture
    from fourlegs_engine.fit.fitter import _generator, rig_radius
    from fourlegs_engine.fit.model import TrainingFrames, model_from_arrays
    from fourlegs_engine.fit.optimize import Tracker, fit_later_timestep
    from fourlegs_engine.fit.options import FitOptions
    from fourlegs_engine.fit.presets import FIT_PRESETS

    bundle = Path(args.bundle)
    meta = json.loads((bundle / "scene.json").read_text())["metadata"]
    first = int(meta.get("first_timestep", 0))
    i = args.timestep - first
    means = np.load(bundle / "means.npy", mmap_mode="r", allow_pickle=False)
    rots = np.load(bundle / "rotations.npy", mmap_mode="r", allow_pickle=False)
    static = {k: np.load(bundle / f"{k}.npy", allow_pickle=False)
              for k in ("log_scales", "opacity_logits", "colors", "foreground")}
    static["cam_m"] = np.asarray(meta["color_correction"]["cam_m"], np.float32)
    static["cam_c"] = np.asarray(meta["color_correction"]["cam_c"], np.float32)
    opts = FitOptions(**FIT_PRESETS[args.preset]).check()
    capture = Capture(args.capture)
    cams_idx = capture.camera_indices("train", opts.cameras)
    full = [capture.train.cameras[first][c] for c in cams_idx]
    cameras = [c.scaled(opts.resolution_scale) for c in full]
    radius = rig_radius(full)
    model = model_from_arrays(np.array(means[0]), np.array(rots[0]), static, "cpu")
    tracker = Tracker(model, cameras, opts, meta["fit"]["floor_y"])
    prev2 = (torch.from_numpy(np.array(means[i - 2])), torch.from_numpy(np.array(rots[i - 2])))
    prev = (torch.from_numpy(np.array(means[i - 1])), torch.from_numpy(np.array(rots[i - 1])))
    frames = TrainingFrames(capture, args.timestep, cams_idx, (cameras[0].width, cameras[0].height), "cpu")

    def run(steps: int) -> float:
        return fit_later_timestep(model, tracker, frames, cameras, opts, radius, prev, prev2,
                                  _generator(opts.seed, args.timestep), lambda ev: None, args.timestep, steps)[3]

    run(3)  # compile and warm up
    start = time.process_time()
    if args.profile:
        from torch.profiler import ProfilerActivity, profile

        with profile(activities=[ProfilerActivity.CPU]) as prof:
            last = run(args.steps)
    else:
        last = run(args.steps)
    cpu = time.process_time() - start
    print(f"{cpu / args.steps * 1e3:.0f} CPU ms per step over {args.steps} steps (timestep {args.timestep}, "
          f"{int(tracker.fg_idx.numel())} foreground Gaussians, {cameras[0].width}x{cameras[0].height}), "
          f"training PSNR {last:.2f} dB")
    if args.profile:
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=15))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
