"""The benchmark scene: N Gaussians spread like a Panoptic-Sports capture, deterministic per seed.

Layout (world up = +z, metres), chosen to match what the renderer meets in the paper's data:

- 35 % floor: a 10 m × 10 m ground plane at z = 0, Gaussians flattened along z (discs);
- 15 % background: a cylindrical wall of radius 6 m, 0–3 m high (the dome's far side);
- 50 % people: 8 person-sized clusters (ellipsoids 0.45 × 0.3 × 1.75 m standing on the floor, within
  2.5 m of the centre), Gaussians on and just inside the body surface.

Scales are log-normal around 1 cm (median 1 cm, σ_log = 0.6; floor discs 3× wider, 10× thinner),
rotations uniform, opacities from logits ~ N(2, 1.5) (most splats nearly opaque, as after 3DGS
training), colours per cluster with jitter, features (N, C) random unit vectors. The camera sits
6.5 m from the centre at 2.2 m height, 640×360, focal 470 px (a Panoptic HD camera at a third of its
resolution), looking at (0, 0, 0.9).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from fourlegs_engine.scene.camera import Camera

WIDTH, HEIGHT, FOCAL = 640, 360, 470.0


@dataclass
class BenchScene:
    """Tensors of one benchmark timestep (all (N, …), on one device, float32 unless asked)."""

    means: torch.Tensor
    rotations: torch.Tensor
    log_scales: torch.Tensor
    opacity_logits: torch.Tensor
    colors: torch.Tensor
    features: torch.Tensor
    camera: Camera

    @property
    def n(self) -> int:
        return int(self.means.shape[0])


def bench_camera(width: int = WIDTH, height: int = HEIGHT, azimuth_deg: float = 20.0) -> Camera:
    """The benchmark view (focal scaled with the width)."""
    a = math.radians(azimuth_deg)
    eye = (6.5 * math.sin(a), -6.5 * math.cos(a), 2.2)
    return Camera.look_at(eye, (0.0, 0.0, 0.9), width=width, height=height, focal=FOCAL * width / WIDTH,
                          near=0.05, far=100.0, name="bench")


def make_bench_scene(n: int, *, feature_dim: int = 128, seed: int = 0, device: str | torch.device = "cpu",
                     dtype: torch.dtype = torch.float32, width: int = WIDTH, height: int = HEIGHT) -> BenchScene:
    """Build the documented benchmark scene with ``n`` Gaussians."""
    g = torch.Generator().manual_seed(seed)
    n_floor = int(0.35 * n)
    n_wall = int(0.15 * n)
    n_people = n - n_floor - n_wall
    f64 = torch.float64

    def rand(*shape):
        return torch.rand(*shape, generator=g, dtype=f64)

    def randn(*shape):
        return torch.randn(*shape, generator=g, dtype=f64)

    floor = torch.stack([(rand(n_floor) - 0.5) * 10, (rand(n_floor) - 0.5) * 10, 0.005 * randn(n_floor)], -1)
    theta = rand(n_wall) * 2 * math.pi
    wall = torch.stack([6 * torch.cos(theta), 6 * torch.sin(theta), rand(n_wall) * 3], -1)
    n_clusters = 8
    centres = torch.stack([(rand(n_clusters) - 0.5) * 5, (rand(n_clusters) - 0.5) * 5], -1)
    who = torch.randint(0, n_clusters, (n_people,), generator=g)
    direction = randn(n_people, 3)
    direction = direction / direction.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    radius = 1.0 - 0.15 * rand(n_people) ** 2  # on and just inside the surface
    half = torch.tensor([0.225, 0.15, 0.875], dtype=f64)
    people = direction * radius[:, None] * half
    people[:, :2] += centres[who]
    people[:, 2] += 0.875
    means = torch.cat([floor, wall, people])

    log_s = math.log(0.01) + 0.6 * randn(n, 3)
    log_s[:n_floor, :2] += math.log(3.0)
    log_s[:n_floor, 2] -= math.log(10.0)
    rotations = randn(n, 4)
    rotations = rotations / rotations.norm(dim=-1, keepdim=True)
    rotations[:n_floor] = torch.tensor([1.0, 0, 0, 0], dtype=f64) + 0.05 * randn(n_floor, 4)
    logits = 2.0 + 1.5 * randn(n)

    palette = rand(n_clusters + 2, 3)
    group = torch.cat([torch.full((n_floor,), n_clusters), torch.full((n_wall,), n_clusters + 1), who])
    colors = (palette[group] + 0.08 * randn(n, 3)).clamp(0, 1)
    features = randn(n, feature_dim)
    features = features / features.norm(dim=-1, keepdim=True)

    perm = torch.randperm(n, generator=g)  # no accidental depth or cluster order in memory
    to = dict(device=device, dtype=dtype)
    return BenchScene(means=means[perm].to(**to), rotations=rotations[perm].to(**to),
                      log_scales=log_s[perm].to(**to), opacity_logits=logits[perm].to(**to),
                      colors=colors[perm].to(**to), features=features[perm].to(**to),
                      camera=bench_camera(width, height))
