"""``fourlegs bench fit-background``: where a fitted capture's test-camera error comes from.

For each fitted bundle of the same capture: the background Gaussians rendered alone from every test
camera against that camera's clean plate (the per-pixel median of its frames over timesteps spread
across the bundle's range; the people move, the studio does not), and the test-camera squared error
of the first and last k timesteps split into moving pixels (where the frame differs from the clean
plate: people, ball) and static ones, with the background rendered alone on the static ones. Writes
``fit_background.md``/``.json`` and a picture: one test camera at chosen timesteps, ground truth | all
Gaussians | foreground only | background only, one block of rows per bundle.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

DEFAULT_DATASET = "../shared/data/panoptic-basketball"


def register_bench(bench_sub: Any) -> None:
    p = bench_sub.add_parser(
        "fit-background", help="fitted capture: background vs clean plates, error on moving vs static pixels",
        description="Split each fitted bundle's test-camera error into the background (against clean plates) "
        "and the moving foreground; table, JSON and a picture.")
    p.add_argument("bundles", nargs="+", help="NAME=BUNDLE_DIR (or BUNDLE_DIR) fitted from --dataset")
    p.add_argument("--dataset", default=DEFAULT_DATASET, help=f"capture directory (default {DEFAULT_DATASET})")
    p.add_argument("--out", default="bench-fit-background", help="output directory")
    p.add_argument("--k", type=int, default=10, help="first/last timesteps compared (default 10)")
    p.add_argument("--plate-samples", type=int, default=15, help="frames in each test camera's clean plate")
    p.add_argument("--picture-camera", default="15", help="test camera of the picture (default 15)")
    p.add_argument("--picture-timesteps", default="0,75", help="bundle timestep positions in the picture")
    p.add_argument("--resolution-scale", type=float, default=0.5)
    p.set_defaults(func=bench_fit_background)


def bench_fit_background(args) -> int:
    import torch
    from PIL import Image
    from scipy.ndimage import binary_dilation

    from fourlegs_engine.errors import InputError
    from fourlegs_engine.fileio import atomic_path, write_json_atomic
    from fourlegs_engine.fit import Capture
    from fourlegs_engine.fit.clean_plate import sample_timesteps
    from fourlegs_engine.render import rasterize
    from fourlegs_engine.render.options import RasterOptions
    from fourlegs_engine.scene.bundle import load_bundle

    capture = Capture(args.dataset)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    test_idx = capture.camera_indices("test", None)
    names = [capture.test.cam_ids[0][c] for c in test_idx]
    if args.picture_camera not in names:
        raise InputError(f"{args.picture_camera!r} is not a test camera ({', '.join(names)})", field="--picture-camera")
    opts = RasterOptions(tile_size="auto", validate=False)
    records, picture_rows = [], []
    for spec in args.bundles:
        name, _, path = spec.rpartition("=")
        name = name or Path(path).name
        started = time.process_time()
        scene = load_bundle(path)
        g = scene.gaussians
        first = int(scene.metadata.get("first_timestep", 0))
        T = g.num_timesteps
        k = max(1, min(args.k, T // 2))
        fg = torch.from_numpy(np.array(g.foreground))
        log_scales = torch.from_numpy(np.array(g.log_scales, np.float32))
        opacity = torch.from_numpy(np.array(g.opacity_logits, np.float32))
        only = {"all": opacity, "fg": opacity.masked_fill(~fg, -30.0), "bg": opacity.masked_fill(fg, -30.0)}

        def render(i, cam, which):
            with torch.no_grad():
                o = rasterize(torch.from_numpy(np.array(g.means[i], np.float32)),
                              torch.from_numpy(np.array(g.rotations[i], np.float32)), log_scales, only[which], cam,
                              colors=torch.from_numpy(np.array(g.rgb(i), np.float32)), options=opts)
            return o["rgb"].clamp(0, 1).numpy()

        plate_steps = sample_timesteps(range(first, first + T), args.plate_samples)
        per_camera = {}
        sums = {"first": np.zeros(4), "last": np.zeros(4)}  # moving SE, static SE, static bg-only SE, pixels
        for c, cam_name in zip(test_idx, names):
            cam = capture.test.cameras[first][c].scaled(args.resolution_scale)
            size = (cam.width, cam.height)
            plate = np.median(np.stack([capture.load_image("test", t, c, size) for t in plate_steps]), 0)
            bg = render(0, cam, "bg")
            per_camera[cam_name] = {"background_vs_plate_psnr": _psnr(((bg - plate) ** 2).mean())}
            for part, positions in (("first", range(k)), ("last", range(T - k, T))):
                for i in positions:
                    gt = capture.load_image("test", first + i, c, size)
                    se = ((render(i, cam, "all") - gt) ** 2).mean(-1)
                    se_bg = ((bg - gt) ** 2).mean(-1)
                    moving = binary_dilation(np.abs(gt - plate).mean(-1) > 0.1, iterations=2)
                    sums[part] += [se[moving].sum(), se[~moving].sum(), se_bg[~moving].sum(), se.size]
        rec = {"run": name, "bundle": str(Path(path).resolve()), "timesteps": [first, first + T], "k": k,
               "plate_timesteps": plate_steps, "cameras": per_camera,
               "background_vs_plate_psnr_mean": float(np.mean([v["background_vs_plate_psnr"] for v in per_camera.values()]))}
        for part, s in sums.items():
            n = s[3]
            rec[part] = {"psnr": _psnr((s[0] + s[1]) / n), "mse_moving": s[0] / n, "mse_static": s[1] / n,
                         "mse_static_background_only": s[2] / n}
        rec["cpu_s"] = time.process_time() - started
        records.append(rec)
        c = test_idx[names.index(args.picture_camera)]
        for i in (int(x) for x in args.picture_timesteps.split(",")):
            i = min(max(i, 0), T - 1)
            cam = capture.test.cameras[first + i][c].scaled(args.resolution_scale)
            gt = capture.load_image("test", first + i, c, (cam.width, cam.height))
            picture_rows.append(np.concatenate([gt] + [render(i, cam, w) for w in ("all", "fg", "bg")], 1))
    write_json_atomic(out / "fit_background.json", {"command": _command(args), "records": records})
    lines = [f"`{_command(args)}`", "",
             "| run | background vs clean plate PSNR (mean; per camera) | first-k PSNR | last-k PSNR | "
             "MSE moving first → last | MSE static first → last | static, background only, first → last |",
             "|---|---|---|---|---|---|---|"]
    for r in records:
        cams = ", ".join(f"{n} {v['background_vs_plate_psnr']:.2f}" for n, v in r["cameras"].items())
        f, l_ = r["first"], r["last"]
        lines.append(f"| {r['run']} | {r['background_vs_plate_psnr_mean']:.2f} ({cams}) | {f['psnr']:.2f} | "
                     f"{l_['psnr']:.2f} | {f['mse_moving']:.5f} → {l_['mse_moving']:.5f} | "
                     f"{f['mse_static']:.5f} → {l_['mse_static']:.5f} | "
                     f"{f['mse_static_background_only']:.5f} → {l_['mse_static_background_only']:.5f} |")
    with atomic_path(out / "fit_background.md", overwrite=True) as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n")
    with atomic_path(out / "fit_background.png", overwrite=True) as tmp:
        Image.fromarray((np.concatenate(picture_rows, 0) * 255).round().astype(np.uint8)).save(tmp, format="PNG")
    print("\n".join(lines))
    print(f"[bench fit-background] picture: {out / 'fit_background.png'} (rows: "
          + "; ".join(f"{r['run']} t={args.picture_timesteps}" for r in records)
          + "; columns: ground truth | all | foreground only | background only)")
    return 0


def _psnr(mse: float) -> float:
    return float(-10.0 * np.log10(max(float(mse), 1e-12)))


def _command(args) -> str:
    return ("fourlegs bench fit-background " + " ".join(args.bundles) + f" --dataset {args.dataset} --out {args.out} "
            f"--k {args.k} --picture-camera {args.picture_camera} --picture-timesteps {args.picture_timesteps}")
