"""A synthetic capture in the Dynamic 3D Gaussians layout, rendered from its own Gaussians.

World axes as in Panoptic: y points down, the floor is the plane y = 0. A dome of background
Gaussians (radius 4 m) with a floor disc, and a foreground box of Gaussians that moves rigidly
(translation along x and a turn about y every timestep). Eight training cameras on two rings and one
test camera, 64×48 pixels, lossless PNG frames and masks.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from fourlegs_engine.render import RasterOptions, rasterize
from fourlegs_engine.scene import Camera

WIDTH, HEIGHT = 64, 48
#: first-timestep colour and scale rates for fits of these captures in 60–80 steps (the defaults are the
#: paper's, for thousands of steps on a real capture)
FEW_STEP_RATES = {"lr_colors": 0.01, "lr_scales": 0.005}
STEP_TRANSLATION = np.array([0.04, 0.0, 0.0])
STEP_ANGLE = math.radians(4.0)
FG_CENTER = np.array([0.0, -0.6, 0.0])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _quat_from_matrix(R: np.ndarray) -> np.ndarray:
    w = math.sqrt(max(1e-12, 1 + R[0, 0] + R[1, 1] + R[2, 2])) / 2
    return np.array([w, (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w)])


def rigid_motion(t: int) -> tuple[np.ndarray, np.ndarray]:
    """(R, translation) of the foreground at timestep t about its own centre."""
    return _rot_y(STEP_ANGLE * t), STEP_TRANSLATION * t


def scene_gaussians(seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    # dome: directions on the upper hemisphere-ish shell around (0, -1, 0)
    n_dome = 900
    d = rng.normal(size=(n_dome, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[:, 1] = -np.abs(d[:, 1])
    dome = np.array([0.0, -0.2, 0.0]) + 4.0 * d
    dome_col = 0.5 + 0.4 * np.stack([np.sin(3 * d[:, 0]), np.cos(2 * d[:, 2]), np.sin(2 * d[:, 0] + d[:, 2])], 1)
    n_floor = 500
    r = 3.8 * np.sqrt(rng.random(n_floor))
    a = 2 * np.pi * rng.random(n_floor)
    floor = np.stack([r * np.cos(a), np.zeros(n_floor), r * np.sin(a)], 1)
    floor_col = 0.35 + 0.25 * np.stack([(np.floor(floor[:, 0]) % 2), 0.5 * np.ones(n_floor), (np.floor(floor[:, 2]) % 2)], 1)
    n_fg = 400
    box = rng.uniform(-0.25, 0.25, size=(n_fg, 3)) * np.array([1.0, 2.0, 1.0])
    fg_col = np.clip(0.5 + 1.5 * box[:, [0, 1, 2]] * np.array([1.0, 0.5, -1.0]), 0.05, 0.95)
    fg = FG_CENTER + box
    means = np.concatenate([dome, floor, fg])
    colors = np.concatenate([dome_col, floor_col, fg_col]).clip(0, 1)
    scales = np.concatenate([np.full(n_dome, 0.22), np.full(n_floor, 0.16), np.full(n_fg, 0.06)])
    is_fg = np.concatenate([np.zeros(n_dome + n_floor, bool), np.ones(n_fg, bool)])
    return {"means": means, "colors": colors, "log_scales": np.log(scales)[:, None].repeat(3, 1), "fg": is_fg}


def cameras() -> tuple[list[Camera], list[Camera]]:
    def ring(n, radius, height, offset, first_id):
        out = []
        for i in range(n):
            a = offset + 2 * np.pi * i / n
            eye = (radius * math.cos(a), height, radius * math.sin(a))
            out.append(Camera.look_at(eye, (0.0, -0.7, 0.0), up=(0.0, -1.0, 0.0), width=WIDTH, height=HEIGHT,
                                      focal=58.0, near=1.0, far=100.0, name=str(first_id + i)))
        return out
    train = ring(4, 3.0, -1.4, 0.0, 1) + ring(4, 2.8, -2.4, np.pi / 4, 5)
    test = [Camera.look_at((3.0 * math.cos(0.4), -1.9, 3.0 * math.sin(0.4)), (0.0, -0.7, 0.0), up=(0.0, -1.0, 0.0),
                           width=WIDTH, height=HEIGHT, focal=58.0, near=1.0, far=100.0, name="0")]
    return train, test


def frame_at(g: dict[str, np.ndarray], t: int) -> tuple[np.ndarray, np.ndarray]:
    """(N,3) means and (N,4) rotations at timestep t."""
    R, tr = rigid_motion(t)
    means = g["means"].copy()
    fg = g["fg"]
    means[fg] = (g["means"][fg] - FG_CENTER) @ R.T + FG_CENTER + tr
    rots = np.tile([1.0, 0, 0, 0], (len(means), 1))
    rots[fg] = _quat_from_matrix(R)
    return means, rots


def colors_at(g: dict[str, np.ndarray], t: int) -> np.ndarray:
    """(N,3) colours at timestep t: the foreground darkens by ``g["fg_darkening"]`` per timestep (if set)."""
    colors = g["colors"].copy()
    colors[g["fg"]] *= 1.0 - float(g.get("fg_darkening", 0.0)) * t
    return colors


def render(g, t, cam, subset=None):
    means, rots = frame_at(g, t)
    sel = slice(None) if subset is None else subset
    tt = lambda a: torch.as_tensor(a[sel], dtype=torch.float64)  # noqa: E731
    with torch.no_grad():
        out = rasterize(tt(means), tt(rots), tt(g["log_scales"]), torch.full((len(means[sel]),), 3.0, dtype=torch.float64),
                        cam, colors=tt(colors_at(g, t)), outputs=("rgb", "alpha"), options=RasterOptions(tile_size="auto"))
    return out["rgb"].numpy(), out["alpha"][..., 0].numpy()


def capture_meta(cams, num_timesteps: int, width: int, height: int) -> dict:
    """A Dynamic 3D Gaussians ``*_meta.json`` for static ``cams``: intrinsics, poses, frame names
    (``CAM/TTTTTT.png``) and camera ids per timestep."""
    return {"w": width, "h": height, "k": [[c.K.tolist() for c in cams]] * num_timesteps,
            "w2c": [[c.w2c.tolist() for c in cams]] * num_timesteps,
            "fn": [[f"{c.name}/{t:06d}.png" for c in cams] for t in range(num_timesteps)],
            "cam_id": [[int(c.name) for c in cams]] * num_timesteps}


def write_capture(root: Path, num_timesteps: int = 3, seed: int = 0, fg_darkening: float = 0.0) -> Path:
    """The synthetic capture under ``root``; ``fg_darkening``: the foreground's colours lose this fraction
    of their t = 0 value per timestep (a person turning into shadow)."""
    g = scene_gaussians(seed)
    g["fg_darkening"] = fg_darkening
    train, test = cameras()
    for split, cams in (("train", train), ("test", test)):
        meta = capture_meta(cams, num_timesteps, WIDTH, HEIGHT)
        for t in range(num_timesteps):
            for c in cams:
                rgb, _ = render(g, t, c)
                (root / "ims" / c.name).mkdir(parents=True, exist_ok=True)
                Image.fromarray((rgb.clip(0, 1) * 255).round().astype(np.uint8)).save(root / "ims" / c.name / f"{t:06d}.png")
                if split == "train":
                    _, alpha = render(g, t, c, subset=g["fg"])
                    (root / "seg" / c.name).mkdir(parents=True, exist_ok=True)
                    Image.fromarray(((alpha > 0.5) * 255).astype(np.uint8)).save(root / "seg" / c.name / f"{t:06d}.png")
        (root / f"{split}_meta.json").write_text(json.dumps(meta))
    return root


def load_images(root: Path, split: str, t: int) -> dict[str, np.ndarray]:
    meta = json.loads((root / f"{split}_meta.json").read_text())
    return {str(cid): np.asarray(Image.open(root / "ims" / fn), np.float64) / 255.0
            for cid, fn in zip(meta["cam_id"][t], meta["fn"][t])}


def write_tiny_capture(root: Path, num_timesteps: int = 2, num_train: int = 3, width: int = 32,
                       height: int = 18) -> Path:
    """A capture small enough to fit in about a second: ``num_train`` training cameras and one test camera
    on a ring, frames of a moving bright box over a colour ramp (no rendering), the box as the mask."""
    yy, xx = np.mgrid[0:height, 0:width]
    for split, count, first_id, offset in (("train", num_train, 1, 0.0), ("test", 1, 0, 0.4)):
        cams = [Camera.look_at((3.0 * math.cos(offset + 2 * np.pi * i / count), -1.5,
                                3.0 * math.sin(offset + 2 * np.pi * i / count)), (0.0, -0.7, 0.0), up=(0.0, -1.0, 0.0),
                               width=width, height=height, focal=30.0, near=1.0, far=100.0, name=str(first_id + i))
                for i in range(count)]
        meta = capture_meta(cams, num_timesteps, width, height)
        for t in range(num_timesteps):
            box = (abs(xx - width / 2 - t) < 4) & (abs(yy - height / 2) < 5)
            rgb = np.stack([xx * 7 % 256, yy * 13 % 256, np.where(box, 230, 40)], -1).astype(np.uint8)
            for c in cams:
                (root / "ims" / c.name).mkdir(parents=True, exist_ok=True)
                Image.fromarray(rgb).save(root / "ims" / c.name / f"{t:06d}.png")
                if split == "train":
                    (root / "seg" / c.name).mkdir(parents=True, exist_ok=True)
                    Image.fromarray((box * 255).astype(np.uint8)).save(root / "seg" / c.name / f"{t:06d}.png")
        (root / f"{split}_meta.json").write_text(json.dumps(meta))
    return root


def fit_straight_and_resumed(capture: Path, root: Path, options, kill_after: int) -> tuple[Path, Path]:
    """Fit ``capture`` twice under ``root`` on one intra-op thread (multi-threaded reductions may sum in
    another order run to run): straight through, and killed after timestep ``kill_after`` then resumed.
    Returns the two bundle folders."""
    import pytest

    from fourlegs_engine.fit import fit_capture

    def kill(ev):
        if ev.kind == "timestep" and ev.timestep == kill_after:
            raise KeyboardInterrupt

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        fit_capture(capture, root / "straight", options, progress=False)
        with pytest.raises(KeyboardInterrupt):
            fit_capture(capture, root / "resumed", options, progress=kill)
        fit_capture(capture, root / "resumed", options, progress=False)
    finally:
        torch.set_num_threads(threads)
    return root / "straight", root / "resumed"
