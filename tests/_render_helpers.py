"""Shared fixtures of the render tests: random scenes and cameras (deterministic per seed)."""
from __future__ import annotations

import numpy as np
import torch

from fourlegs_engine.scene import Camera


def random_scene(n: int, seed: int, *, channels: int = 4, spread: float = 0.6, log_scale: float = -2.3,
                 dtype: torch.dtype = torch.float64) -> dict[str, torch.Tensor]:
    """n Gaussians around the origin: means, rotations, log_scales, opacity_logits, colors, features."""
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    out = {
        "means": torch.randn(n, 3, generator=g, dtype=f64) * spread,
        "rotations": torch.randn(n, 4, generator=g, dtype=f64),
        "log_scales": log_scale + 0.5 * torch.randn(n, 3, generator=g, dtype=f64),
        "opacity_logits": 1.0 + 2.0 * torch.randn(n, generator=g, dtype=f64),
        "colors": torch.rand(n, 3, generator=g, dtype=f64),
        "features": torch.randn(n, channels, generator=g, dtype=f64),
    }
    return {k: v.to(dtype) for k, v in out.items()}


def view_cameras(width: int = 32, height: int = 24) -> list[Camera]:
    """Several views of the random scenes: ordinary, oblique, off-centre principal point, a near plane
    that cuts through the cloud, and a camera inside the cloud (Gaussians behind it)."""
    cams = [
        Camera.look_at((0.3, -3.0, 1.0), (0, 0, 0), width=width, height=height, name="front"),
        Camera.look_at((2.5, 1.5, 0.4), (0, 0, 0.1), width=width, height=height, fov_y=0.9, name="side"),
        Camera.look_at((0.0, 0.5, 3.0), (0, 0, 0), width=width, height=height, name="top"),
        Camera.look_at((0.2, -2.6, 0.3), (0, 0, 0), width=width, height=height, near=2.4, name="near_cut"),
        Camera.look_at((0.05, -0.2, 0.1), (0, 3, 0), width=width, height=height, name="inside"),
    ]
    off = cams[0]
    K = off.K.copy()
    K[0, 2] += 5.0
    K[1, 2] -= 3.0
    cams.append(Camera(K=K, w2c=off.w2c, width=width, height=height, name="off_centre"))
    return cams


def as_numpy(scene: dict[str, torch.Tensor]) -> dict[str, np.ndarray]:
    return {k: v.detach().double().numpy() for k, v in scene.items()}
