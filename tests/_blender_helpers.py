"""Shared helpers for the Blender tests: a tiny dynamic scene and a hand-made plan (contract schema)."""
from __future__ import annotations

import math

import numpy as np

from fourlegs_engine.scene import Camera, CameraRig, GaussianSequence, Scene


def tiny_scene(T: int = 4, N: int = 64, seed: int = 0, width: int = 32, height: int = 24) -> Scene:
    """N Gaussians in a unit cube moving +x by 0.1 per timestep; colours change over time; 2 cameras."""
    rng = np.random.default_rng(seed)
    base = rng.uniform(-0.5, 0.5, (N, 3)).astype(np.float32)
    means = np.stack([base + np.float32([0.1 * t, 0, 0]) for t in range(T)])
    rot = np.zeros((T, N, 4), np.float32)
    rot[..., 0] = 1
    colors = np.stack([np.tile(np.float32([t / max(T - 1, 1), 0.5, 1 - t / max(T - 1, 1)]), (N, 1))
                       for t in range(T)])
    g = GaussianSequence(means=means, rotations=rot, log_scales=np.full((N, 3), math.log(0.05), np.float32),
                         opacity_logits=np.full(N, 2.0, np.float32), colors=colors)
    cams = [Camera.look_at((3, -3, 1.5), (0, 0, 0), width=width, height=height, name="cam00"),
            Camera.look_at((-3, -2, 2.0), (0, 0, 0), width=width, height=height, focal=40.0, name="cam01")]
    return Scene(gaussians=g, cameras=CameraRig.static(cams, [], T), name="tiny", fps=10.0)


def orbit_key(frame: int, angle: float, radius: float = 4.0, height: float = 1.0, focal: float = 30.0,
              width: int = 32, height_px: int = 24) -> dict:
    cam = Camera.look_at((radius * math.cos(angle), radius * math.sin(angle), height), (0, 0, 0),
                         width=width, height=height_px, focal=focal)
    return {"frame": frame, "c2w": cam.c2w.tolist(), "focal_px": focal, "lens_mm": focal * 36.0 / width,
            "sensor_width_mm": 36.0}


def hand_plan(desaturate: bool = True, width: int = 32, height: int = 24) -> dict:
    """A 12-frame plan: 'context' play (frames 1-6, dense keys) then a bullet-time orbit (7-12)."""
    shots = [
        {"name": "context", "effect": "play", "frame_start": 1, "frame_end": 6,
         "camera_keys": [orbit_key(f, 0.0, width=width, height_px=height) for f in range(1, 7)],
         "time_keys": [{"frame": 1, "timestep": 0.0}, {"frame": 6, "timestep": 2.5}],
         "interpolation": "linear", "params": {}},
        {"name": "bullet", "effect": "bullet_time_orbit", "frame_start": 7, "frame_end": 12,
         "camera_keys": [orbit_key(f, math.radians(30.0 * (f - 6)), width=width, height_px=height)
                         for f in range(7, 13)],
         "time_keys": [{"frame": 7, "timestep": 2.0}, {"frame": 12, "timestep": 2.0}],
         "interpolation": "linear", "params": {"orbit_degrees": 180}},
    ]
    return {"format": "fourlegs-highlight-plan", "version": 1,
            "scene": {"name": "tiny", "path": None, "num_timesteps": 4, "fps": 10.0},
            "query": "the cube", "localization": {"found": True, "message": "", "segment": [1, 3], "peak": 2,
                                                  "segments": [[1, 3]], "scores": [0.1, 0.3, 0.4, 0.2],
                                                  "action_centre": [0.0, 0.0, 0.0], "best_view": "cam00"},
            "fps": 12, "resolution": [width, height], "frame_start": 1, "frame_end": 12, "shots": shots,
            "passes": {"rgb": [[1, 12]], "depth": [[1, 12]], "relevancy": [[7, 12]] if desaturate else []},
            "desaturate": ({"ranges": [[7, 12]], "fade_in": 2, "fade_out": 2, "strength": 1.0, "weights": {}}
                           if desaturate else None),
            "messages": []}


# --------------------------------------------------------------------------------------------------
# Blender session helpers (bpy is imported once per test process, by the first fixture that needs it)
import importlib.util
import os
import sys
import tempfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def child_env(**extra: str) -> dict:
    """Environment for a child Python that must import fourlegs_addon (installed by pip with the project)."""
    return dict(os.environ, **extra)


@pytest.fixture(scope="module")
def bpy_addon():
    """bpy with the development add-on registered (once per process)."""
    bpy = pytest.importorskip("bpy")
    import fourlegs_addon
    from fourlegs_addon import registration

    if not hasattr(bpy.types.Scene, "fourlegs"):
        registration.register()
    return bpy


@pytest.fixture
def bl(bpy_addon):
    """An empty Blender file for each test."""
    bpy_addon.ops.wm.read_factory_settings(use_empty=True)
    return bpy_addon


def language_bundle(path: Path, T: int = 6, N: int = 200, query_label: str = "red cube") -> Path:
    """A tiny bundle with a real, hand-built language field whose answer is known.

    The decoder maps latent e0 to the (simulated) text embedding of ``query_label`` and e1 to that of
    "floor" (first Linear [I; -I] + ReLU keeps the sign, the last Linear holds the embeddings). The
    first half of the Gaussians carries e0 at timesteps 2-3 only, so the query is found there.
    """
    import torch

    from fourlegs_engine.language.autoencoder import FeatureDecoder
    from fourlegs_engine.demo.simulated import SimulatedTextEncoder
    from fourlegs_engine.scene import write_bundle
    from fourlegs_engine.scene.bundle import update_bundle_meta

    scene = tiny_scene(T=T, N=N)
    scene.metadata = {"labels": ["floor", query_label]}
    write_bundle(scene, path)
    emb = SimulatedTextEncoder().encode_text([query_label, "floor"]).double()  # (2, 768)
    dec = FeatureDecoder((2, 4, 768))
    with torch.no_grad():
        lin1, bn, lin2 = dec.net[0], dec.net[1], dec.net[3]
        lin1.weight.copy_(torch.tensor([[1.0, 0], [0, 1], [-1, 0], [0, -1]]))
        lin1.bias.zero_()
        bn.running_mean.zero_()
        bn.running_var.fill_(1.0 - bn.eps)
        lin2.weight.copy_(torch.cat([emb.T, -emb.T], dim=1).float())
        lin2.bias.zero_()
    (path / "language").mkdir()
    torch.save(dec.state_dict(), path / "language" / "decoder.pt")
    lat = np.zeros((T, N, 2), np.float16)
    lat[:, :, 1] = 1.0
    lat[2:4, : N // 2] = [1.0, 0.0]
    np.save(path / "language" / "latents.npy", lat)
    update_bundle_meta(path, language={"encoder": "simulated", "latent_dim": 2, "decoder": "language/decoder.pt",
                                       "latents": "language/latents.npy", "mode": "lift",
                                       "canonical_phrases": ["object", "things", "stuff", "texture"],
                                       "config_hash": "test"})
    return path
