"""Data for ``fourlegs bench device``: a subset of a real capture small enough to send to a GPU machine,
and a tiny synthetic capture for the CPU dry run.

``fourlegs bench device-data`` copies every camera of the first N timesteps of a Dynamic 3D Gaussians
capture (``ims/``, ``seg/`` and both metadata files trimmed to those timesteps) into a git-ignored
folder (``.device_data/`` by default) that the device call carries. The source capture is benchmark
data: the subset never enters the repository or the product.
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from fourlegs_engine.errors import InputError

DEFAULT_SOURCE = "../shared/data/panoptic-basketball"
DEFAULT_OUT = ".device_data"
DEFAULT_TIMESTEPS = 25
META_KEYS = ("k", "w2c", "fn", "cam_id")
#: what the device call may carry in all (tree + wheels + data); the subset alone should stay well below
CARRY_LIMIT_MB = 64


def register_bench(bench_sub: Any) -> None:
    p = bench_sub.add_parser(
        "device-data", help="copy the first N timesteps of a capture (all cameras) for `fourlegs bench device`",
        description="Copy every camera of the first N timesteps of a Dynamic 3D Gaussians capture (frames, "
                    "masks, metadata trimmed to those timesteps) into a git-ignored folder that the GPU "
                    "machine's call carries.")
    p.add_argument("--source", default=DEFAULT_SOURCE, help=f"capture directory (default {DEFAULT_SOURCE})")
    p.add_argument("-o", "--out", default=DEFAULT_OUT, help=f"subset directory (default {DEFAULT_OUT})")
    p.add_argument("--timesteps", type=int, default=DEFAULT_TIMESTEPS,
                   help=f"first N timesteps to copy (default {DEFAULT_TIMESTEPS})")
    p.add_argument("--overwrite", action="store_true", help="replace an existing subset")
    p.set_defaults(func=_device_data_cli)


def _device_data_cli(args: argparse.Namespace) -> int:
    summary = build_device_data(args.source, args.out, args.timesteps, overwrite=args.overwrite)
    print(f"wrote {summary['out']}: {summary['cameras']} cameras x {summary['timesteps']} timesteps, "
          f"{summary['files']} files, {summary['bytes'] / 2**20:.1f} MiB")
    return 0


def _trimmed_meta(path: Path, timesteps: int) -> dict[str, Any]:
    from fourlegs_engine.fileio import read_json

    meta = read_json(path)
    if not isinstance(meta, dict):
        raise InputError("is not a JSON object", file=path)
    for key in ("w", "h", *META_KEYS):
        if key not in meta:
            raise InputError("is missing", file=path, field=key)
    available = len(meta["fn"])
    if timesteps > available:
        raise InputError(f"has {available} timesteps, {timesteps} were asked for", file=path, field="fn")
    return {**meta, **{key: meta[key][:timesteps] for key in META_KEYS}}


def build_device_data(source: str | Path, out: str | Path, timesteps: int = DEFAULT_TIMESTEPS, *,
                      overwrite: bool = False) -> dict[str, Any]:
    """Copy every camera of timesteps ``0..timesteps-1`` of ``source`` into ``out`` (atomically).

    Returns a summary: out, timesteps, cameras, files, bytes.
    Raises:
        InputError: not a capture, too few timesteps, a listed frame missing.
        OutputExistsError: ``out`` exists and ``overwrite`` is False.
    """
    from fourlegs_engine.fileio import atomic_directory, write_json_atomic

    source, out = Path(source), Path(out)
    if timesteps < 1:
        raise InputError(f"must be at least 1, got {timesteps}", field="--timesteps")
    if not (source / "train_meta.json").is_file():
        raise InputError("is not a Dynamic 3D Gaussians capture (no train_meta.json)", file=source)
    from fourlegs_engine.fit.dataset import Capture
    Capture(source)  # the metadata as `fourlegs fit` checks it: cameras, sizes, frame names inside the capture
    metas = {"train": _trimmed_meta(source / "train_meta.json", timesteps)}
    if (source / "test_meta.json").is_file():
        metas["test"] = _trimmed_meta(source / "test_meta.json", timesteps)
    files, total = 0, 0
    with atomic_directory(out, overwrite=overwrite) as tmp:
        for split, meta in metas.items():
            for row in meta["fn"]:
                for name in row:
                    jobs = [("ims", name)]
                    if split == "train" and (source / "seg").is_dir():
                        jobs.append(("seg", str(Path(name).with_suffix(".png"))))
                    for folder, rel in jobs:
                        src = source / folder / rel
                        if not src.is_file():
                            raise InputError("listed in the metadata but missing", file=src, field="fn")
                        dst = tmp / folder / rel
                        dst.parent.mkdir(parents=True, exist_ok=True)
                        shutil.copyfile(src, dst)
                        files += 1
                        total += dst.stat().st_size
            write_json_atomic(tmp / f"{split}_meta.json", meta)
            total += (tmp / f"{split}_meta.json").stat().st_size
        cameras = sum(len(m["fn"][0]) for m in metas.values())
        summary = {"source": str(source.resolve()), "timesteps": timesteps, "cameras": cameras,
                   "files": files, "bytes": total}
        write_json_atomic(tmp / "SUBSET.json", summary)
    return {**summary, "out": str(out)}


# ------------------------------------------------------------------------------- synthetic capture
#: world axes as in Panoptic: y points down, the floor is the plane y = 0
SYNTHETIC_TRAIN_IDS = ("1", "2", "3", "4", "5", "6", "7", "8")
SYNTHETIC_TEST_IDS = ("0", "10", "15", "30")


def _synthetic_gaussians(seed: int) -> dict[str, np.ndarray]:
    """A dome, a floor disc and a foreground box (N ≈ 1.2k): means (N,3), colors (N,3), log_scales (N,3),
    fg (N,) bool, in Panoptic axes."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(600, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[:, 1] = -np.abs(d[:, 1])
    dome = 4.0 * d
    dome_col = 0.5 + 0.4 * np.stack([np.sin(3 * d[:, 0]), np.cos(2 * d[:, 2]), np.sin(2 * d[:, 0] + d[:, 2])], 1)
    r, a = 3.8 * np.sqrt(rng.random(350)), 2 * np.pi * rng.random(350)
    floor = np.stack([r * np.cos(a), np.zeros(350), r * np.sin(a)], 1)
    floor_col = 0.3 + 0.3 * np.stack([np.floor(floor[:, 0]) % 2, np.full(350, 0.5), np.floor(floor[:, 2]) % 2], 1)
    box = rng.uniform(-0.25, 0.25, size=(300, 3)) * np.array([1.0, 2.0, 1.0]) + np.array([0.0, -0.6, 0.0])
    box_col = np.clip(0.5 + 1.5 * (box - box.mean(0)) * np.array([1.0, 0.5, -1.0]), 0.05, 0.95)
    scales = np.concatenate([np.full(600, 0.22), np.full(350, 0.16), np.full(300, 0.06)])
    return {"means": np.concatenate([dome, floor, box]), "colors": np.concatenate([dome_col, floor_col, box_col]),
            "log_scales": np.log(scales)[:, None].repeat(3, 1),
            "fg": np.concatenate([np.zeros(950, bool), np.ones(300, bool)])}


def _synthetic_cameras(width: int, height: int) -> dict[str, list]:
    from fourlegs_engine.scene import Camera

    focal = 0.9 * width
    def look(angle: float, radius: float, y: float, name: str):
        eye = (radius * math.cos(angle), y, radius * math.sin(angle))
        return Camera.look_at(eye, (0.0, -0.7, 0.0), up=(0.0, -1.0, 0.0), width=width, height=height, focal=focal,
                              near=1.0, far=100.0, name=name)
    train = [look(2 * math.pi * i / len(SYNTHETIC_TRAIN_IDS), 3.0 - 0.2 * (i % 2), -1.4 - (i % 2), name)
             for i, name in enumerate(SYNTHETIC_TRAIN_IDS)]
    test = [look(0.4 + 2 * math.pi * i / len(SYNTHETIC_TEST_IDS), 2.9, -1.9, name)
            for i, name in enumerate(SYNTHETIC_TEST_IDS)]
    return {"train": train, "test": test}


def write_synthetic_capture(root: str | Path, *, timesteps: int = 4, width: int = 64, height: int = 36,
                            seed: int = 0, overwrite: bool = False) -> Path:
    """A tiny capture in the Dynamic 3D Gaussians layout rendered by the engine: 8 training cameras with
    masks, test cameras 0, 10, 15, 30, a foreground box sliding along x (PNG frames)."""
    import torch
    from PIL import Image

    from fourlegs_engine.fileio import atomic_directory, write_json_atomic
    from fourlegs_engine.render import RasterOptions, rasterize
    from fourlegs_engine.threads import torch_threads

    g = _synthetic_gaussians(seed)
    cams = _synthetic_cameras(width, height)
    f32 = lambda a: torch.as_tensor(a, dtype=torch.float32)  # noqa: E731
    # one thread: a thousand Gaussians per view are all overhead for a thread pool
    with torch_threads(1), atomic_directory(Path(root), overwrite=overwrite) as tmp:
        for split, split_cams in cams.items():
            meta: dict[str, Any] = {"w": width, "h": height, "k": [], "w2c": [], "fn": [], "cam_id": []}
            for t in range(timesteps):
                means = g["means"].copy()
                means[g["fg"], 0] += 0.05 * t
                meta["k"].append([c.K.tolist() for c in split_cams])
                meta["w2c"].append([c.w2c.tolist() for c in split_cams])
                meta["fn"].append([f"{c.name}/{t:06d}.png" for c in split_cams])
                meta["cam_id"].append([int(c.name) for c in split_cams])
                for cam in split_cams:
                    with torch.no_grad():
                        out = rasterize(f32(means), f32(np.tile([1.0, 0, 0, 0], (len(means), 1))),
                                        f32(g["log_scales"]), torch.full((len(means),), 3.0),
                                        cam, colors=f32(g["colors"]), outputs=("rgb",),
                                        options=RasterOptions(tile_size="auto"))
                    image = (out["rgb"].clamp(0, 1).numpy() * 255).round().astype(np.uint8)
                    (tmp / "ims" / cam.name).mkdir(parents=True, exist_ok=True)
                    Image.fromarray(image).save(tmp / "ims" / cam.name / f"{t:06d}.png")
                    if split == "train":
                        fg = np.flatnonzero(g["fg"])
                        with torch.no_grad():
                            alpha = rasterize(f32(means[fg]), f32(np.tile([1.0, 0, 0, 0], (len(fg), 1))),
                                              f32(g["log_scales"][fg]), torch.full((len(fg),), 3.0), cam,
                                              colors=f32(g["colors"][fg]), outputs=("alpha",),
                                              options=RasterOptions(tile_size="auto"))["alpha"][..., 0].numpy()
                        (tmp / "seg" / cam.name).mkdir(parents=True, exist_ok=True)
                        Image.fromarray(((alpha > 0.5) * 255).astype(np.uint8)).save(
                            tmp / "seg" / cam.name / f"{t:06d}.png")
            write_json_atomic(tmp / f"{split}_meta.json", meta)
        (tmp / "SUBSET.json").write_text(json.dumps({"synthetic": True, "timesteps": timesteps, "seed": seed}))
    return Path(root)
