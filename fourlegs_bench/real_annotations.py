"""``fourlegs bench real-annotations``: honest annotation masks of the ball and of ball actions on a real capture.

Nothing here is a language model: each phrase is a folder of per-pixel masks (``{camera}/{t:06d}.png``)
that the annotation-mask encoder (``fourlegs language --encoder masks``) lifts into a 4D field.

- **"the ball"**: the basketball is the only orange object of the Panoptic basketball capture, so a
  colour threshold (hue within 25 degrees of red-orange, saturation > 0.5, value > 0.25) finds it;
  holes (the ball's dark seams) are filled and stray pixels (skin highlights) dropped by keeping the
  connected components of at least a third of the largest one. On training cameras the result is
  checked against the capture's foreground masks (the ball is foreground): the share of ball pixels
  inside them is reported.
- **the ball's 3D centre** per timestep: the mask centroids of every camera that sees enough of it,
  triangulated (linear least squares), with views whose reprojection error exceeds a bound dropped.
- **"the ball in the air"** and **"a person holding the ball"**, from the fitted geometry: at each
  timestep, the fitted scene's opaque foreground Gaussians farther than a ball radius (plus margin)
  from the ball centre are the people; the ball is *in the air* when fewer than ``min_people_gaussians``
  of them lie within a hand's reach of the ball's surface. Where it is in the air its masks are the
  ball's; where it is held they are the foreground components that touch the ball (the person and the
  ball). The other phrase's masks are empty there (an empty mask says "not in this view").

Masks are written for the training cameras with foreground masks (the phrases built on them) and, for
"the ball" and "the ball in the air", for every camera, so held-out cameras can be scored.
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

BALL_PHRASE = "the ball"
IN_AIR_PHRASE = "the ball in the air"
HOLDING_PHRASE = "a person holding the ball"
#: a basketball's radius in metres (size 7: 0.749 m circumference)
BALL_RADIUS_M = 0.119
#: a hand's length from the ball's surface: more people Gaussians that close mean the ball is held
DEFAULT_REACH_M = 0.15
DEFAULT_MIN_PEOPLE_GAUSSIANS = 8
#: the smallest ball mask (pixels) whose centroid is used for triangulation
MIN_TRIANGULATION_PIXELS = 60
MAX_REPROJECTION_PX = 6.0


def ball_mask(rgb: np.ndarray, *, min_pixels: int = 12) -> np.ndarray:
    """(H, W) bool mask of the orange ball in an (H, W, 3) uint8 RGB image (module docstring)."""
    from PIL import Image
    from scipy import ndimage

    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) image, got {rgb.shape}")
    hsv = np.asarray(Image.fromarray(rgb).convert("HSV"), dtype=np.float32)
    hue = hsv[..., 0] * (360.0 / 255.0)
    sat, val = hsv[..., 1] / 255.0, hsv[..., 2] / 255.0
    orange = ((hue < 25.0) | (hue > 345.0)) & (sat > 0.5) & (val > 0.25)
    if not orange.any():
        return orange
    closed = ndimage.binary_closing(orange, structure=np.ones((3, 3), bool), iterations=1)
    filled = ndimage.binary_fill_holes(closed | orange)
    labels, count = ndimage.label(filled)
    if count == 0:
        return np.zeros_like(orange)
    sizes = np.bincount(labels.ravel(), minlength=count + 1)[1:]
    keep = np.flatnonzero((sizes >= max(min_pixels, sizes.max() / 3.0))) + 1
    return np.isin(labels, keep)


def holding_mask(foreground: np.ndarray, ball: np.ndarray, *, touch_px: int = 3) -> np.ndarray:
    """(H, W) bool: the foreground components that touch the ball (within ``touch_px``), ball included."""
    from scipy import ndimage

    fg = np.asarray(foreground, bool) | ball
    if not ball.any():
        return np.zeros_like(fg)
    labels, _ = ndimage.label(fg)
    near_ball = ndimage.binary_dilation(ball, iterations=max(1, int(touch_px)))
    touching = np.unique(labels[near_ball & fg])
    touching = touching[touching > 0]
    return np.isin(labels, touching)


def triangulate(points_2d: np.ndarray, projections: np.ndarray, *, max_error_px: float = MAX_REPROJECTION_PX,
                min_views: int = 3) -> tuple[np.ndarray | None, np.ndarray]:
    """Least-squares 3D point from 2D observations, dropping the worst view while its error exceeds a bound.

    Args:
        points_2d: (V, 2) pixel observations (x, y; pixel centres at +0.5).
        projections: (V, 3, 4) camera matrices K [R | t].
    Returns:
        ((3,) point or None when fewer than ``min_views`` consistent views remain, (V,) bool views used).
    """
    pts = np.asarray(points_2d, np.float64)
    P = np.asarray(projections, np.float64)
    used = np.ones(len(pts), bool)
    while used.sum() >= min_views:
        rows = []
        for (x, y), Pv in zip(pts[used], P[used]):
            rows += [x * Pv[2] - Pv[0], y * Pv[2] - Pv[1]]
        A = np.asarray(rows)
        scale = np.linalg.norm(A[:, :3], axis=1, keepdims=True).clip(1e-12)
        A = A / scale
        _, _, vt = np.linalg.svd(A)
        h = vt[-1]
        if abs(h[3]) < 1e-12:
            return None, used
        X = h[:3] / h[3]
        proj = P @ np.append(X, 1.0)
        depth = proj[:, 2]
        err = np.full(len(pts), np.inf)
        ok = depth > 1e-9
        err[ok] = np.linalg.norm(proj[ok, :2] / depth[ok, None] - pts[ok], axis=1)
        worst = int(np.argmax(np.where(used, err, -np.inf)))
        if err[worst] <= max_error_px:
            return X, used
        used[worst] = False
    return None, used


def projection_matrix(camera: Any) -> np.ndarray:
    """(3, 4) K [R | t] of a :class:`~fourlegs_engine.scene.camera.Camera`."""
    return np.asarray(camera.K, np.float64) @ np.asarray(camera.w2c, np.float64)[:3]


@dataclass
class BallTrack:
    """The ball's triangulated centre per timestep.

    Attributes:
        centres: (T, 3) world positions, NaN where fewer than three cameras agreed.
        views: (T,) number of cameras used per timestep.
    """

    centres: np.ndarray
    views: np.ndarray


def in_air_flags(track: BallTrack, foreground_means: Sequence[np.ndarray], *, reach_m: float = DEFAULT_REACH_M,
                 min_people_gaussians: int = DEFAULT_MIN_PEOPLE_GAUSSIANS,
                 ball_radius_m: float = BALL_RADIUS_M) -> tuple[np.ndarray, np.ndarray]:
    """Per timestep: whether the ball is in the air, and how many people Gaussians lie within reach.

    Args:
        foreground_means: per timestep, (N_t, 3) centres of the opaque foreground Gaussians.
    Returns:
        ((T,) bool in the air (False where the ball was not found), (T,) int people Gaussians within reach).
    """
    T = len(track.centres)
    in_air = np.zeros(T, bool)
    near = np.zeros(T, np.int64)
    for t in range(T):
        c = track.centres[t]
        if not np.all(np.isfinite(c)):
            continue
        d = np.linalg.norm(np.asarray(foreground_means[t], np.float64) - c, axis=1)
        people = d > ball_radius_m * 1.5
        near[t] = int(np.count_nonzero(people & (d < ball_radius_m + reach_m)))
        in_air[t] = near[t] < min_people_gaussians
    return in_air, near


def register_bench(bench_sub: Any) -> None:
    p = bench_sub.add_parser(
        "real-annotations", help="mask folders of the ball and ball actions on a real capture (colour + fitted geometry)",
        description="Writes annotation-mask folders for 'the ball' (colour threshold, checked against the "
                    "foreground masks), 'the ball in the air' and 'a person holding the ball' (from the ball's "
                    "triangulated centre and the fitted scene's foreground Gaussians), with a JSON report.")
    p.add_argument("dataset", help="the capture (train_meta.json, test_meta.json, ims/, seg/)")
    p.add_argument("--scene", required=True, help="the capture's fitted scene bundle (`fourlegs fit`)")
    p.add_argument("-o", "--out", required=True, help="output folder: one sub-folder per phrase, plus report.json")
    p.add_argument("--reach", type=float, default=DEFAULT_REACH_M,
                   help=f"a hand's reach from the ball's surface, metres (default {DEFAULT_REACH_M})")
    p.add_argument("--min-people-gaussians", type=int, default=DEFAULT_MIN_PEOPLE_GAUSSIANS,
                   help="people Gaussians within reach that make the ball held (default %(default)s)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output folder's masks")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fourlegs_engine.errors import InputError, OutputExistsError

    out = Path(args.out)
    if (out / "report.json").exists() and not args.overwrite:
        raise OutputExistsError(f"{out / 'report.json'} exists (use --overwrite)")
    if not args.reach > 0 or args.min_people_gaussians < 1:
        raise InputError("--reach must be > 0 and --min-people-gaussians >= 1", field="--reach")
    report = write_annotations(Path(args.dataset), Path(args.scene), out, reach_m=args.reach,
                               min_people_gaussians=args.min_people_gaussians)
    print(json.dumps({k: v for k, v in report.items() if k not in ("per_timestep",)}, indent=1))
    return 0


def write_annotations(dataset: Path, scene_path: Path, out: Path, *, reach_m: float = DEFAULT_REACH_M,
                      min_people_gaussians: int = DEFAULT_MIN_PEOPLE_GAUSSIANS,
                      timesteps: Sequence[int] | None = None, progress: bool = True) -> dict[str, Any]:
    """Write the three phrases' mask folders under ``out`` and ``out/report.json``; returns the report."""
    from PIL import Image
    from tqdm import tqdm

    from fourlegs_engine.fileio import write_json_atomic
    from fourlegs_engine.fit.dataset import Capture
    from fourlegs_engine.scene.bundle import load_bundle

    started = time.perf_counter()
    capture = Capture(dataset)
    scene = load_bundle(scene_path)
    T = min(capture.num_timesteps, scene.num_timesteps)
    steps = list(range(T)) if timesteps is None else [int(t) for t in timesteps]
    splits = [("train", c) for c in range(len(capture.train.cam_ids[0]))]
    splits += [("test", c) for c in range(len(capture.test.cam_ids[0]))]

    def write_png(phrase: str, cam: str, t: int, mask: np.ndarray) -> None:
        path = out / phrase / cam / f"{t:06d}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.part")
        Image.fromarray(mask.astype(np.uint8) * 255).save(tmp, format="PNG")
        tmp.replace(path)

    balls: dict[tuple[str, int, int], np.ndarray] = {}
    inside_fg = [0, 0]
    track = BallTrack(np.full((T, 3), np.nan), np.zeros(T, np.int64))
    for t in tqdm(steps, desc="ball masks", unit="timestep", disable=not progress):
        obs, mats = [], []
        for split, c in splits:
            with Image.open(capture.image_path(split, t, c)) as im:
                mask = ball_mask(np.asarray(im.convert("RGB")))
            balls[(split, c, t)] = mask
            cam_name = (capture.train if split == "train" else capture.test).cam_ids[t][c]
            write_png(BALL_PHRASE, cam_name, t, mask)
            if split == "train" and capture.has_masks and mask.any():
                fg = capture.load_mask(split, t, c, (capture.width, capture.height)) > 0.5
                inside_fg[0] += int(np.count_nonzero(mask & fg))
                inside_fg[1] += int(np.count_nonzero(mask))
            if np.count_nonzero(mask) >= MIN_TRIANGULATION_PIXELS:
                ys, xs = np.nonzero(mask)
                obs.append((xs.mean() + 0.5, ys.mean() + 0.5))
                camera = (capture.train if split == "train" else capture.test).cameras[t][c]
                mats.append(projection_matrix(camera))
        if len(obs) >= 3:
            X, used = triangulate(np.asarray(obs), np.asarray(mats))
            if X is not None:
                track.centres[t], track.views[t] = X, int(used.sum())

    fg_flags = np.asarray(scene.gaussians.foreground, bool) if scene.gaussians.foreground is not None else None
    if fg_flags is None:
        raise ValueError(f"{scene_path}: the scene has no foreground flags (fit it with masks)")
    opacity = 1.0 / (1.0 + np.exp(-np.asarray(scene.gaussians.opacity_logits, np.float64).reshape(-1)))
    people = fg_flags & (opacity > 0.5)
    fg_means = [np.asarray(scene.gaussians.means[t])[people] if t in set(steps) else np.zeros((0, 3))
                for t in range(T)]
    in_air, near = in_air_flags(track, fg_means, reach_m=reach_m, min_people_gaussians=min_people_gaussians)

    for t in tqdm(steps, desc="action masks", unit="timestep", disable=not progress):
        for split, c in splits:
            cam_name = (capture.train if split == "train" else capture.test).cam_ids[t][c]
            ball = balls[(split, c, t)]
            write_png(IN_AIR_PHRASE, cam_name, t, ball if in_air[t] else np.zeros_like(ball))
            if split == "train" and capture.has_masks:
                fg = capture.load_mask(split, t, c, (capture.width, capture.height)) > 0.5
                held = holding_mask(fg, ball) if (not in_air[t] and np.isfinite(track.centres[t]).all()) \
                    else np.zeros_like(ball)
                write_png(HOLDING_PHRASE, cam_name, t, held)

    air_steps = [t for t in steps if in_air[t]]
    report = {
        "dataset": str(dataset), "scene": str(scene_path), "timesteps": len(steps),
        "phrases": {BALL_PHRASE: str(out / BALL_PHRASE), IN_AIR_PHRASE: str(out / IN_AIR_PHRASE),
                    HOLDING_PHRASE: str(out / HOLDING_PHRASE)},
        "ball_pixels_inside_foreground": round(inside_fg[0] / max(inside_fg[1], 1), 4),
        "ball_found_timesteps": int(np.count_nonzero(np.isfinite(track.centres[steps]).all(axis=1))),
        "in_air_timesteps": len(air_steps), "in_air_runs": _runs(air_steps),
        "reach_m": reach_m, "min_people_gaussians": min_people_gaussians,
        "seconds": round(time.perf_counter() - started, 1),
        "per_timestep": [{"t": t, "centre": None if not np.isfinite(track.centres[t]).all()
                          else [round(float(v), 4) for v in track.centres[t]],
                          "views": int(track.views[t]), "people_gaussians_within_reach": int(near[t]),
                          "in_air": bool(in_air[t])} for t in steps],
    }
    write_json_atomic(out / "report.json", report)
    return report


def _runs(steps: Sequence[int]) -> list[list[int]]:
    """Sorted timesteps -> inclusive [start, end] runs."""
    runs: list[list[int]] = []
    for t in steps:
        if runs and t == runs[-1][1] + 1:
            runs[-1][1] = t
        else:
            runs.append([t, t])
    return runs
