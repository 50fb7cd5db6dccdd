"""A micro dynamic scene with labels for the language-stage tests (a few hundred Gaussians, 32x18 px)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from fourlegs_engine.scene.bundle import write_bundle
from fourlegs_engine.scene.camera import Camera, CameraRig
from fourlegs_engine.scene.gaussians import GaussianSequence
from fourlegs_engine.scene.scene import Scene

MICRO_LABELS = ["floor", "person jumping", "ball flying in the air"]


def micro_scene(T: int = 4, width: int = 32, height: int = 18, cameras: int = 3, seed: int = 0) -> Scene:
    """A floor, a jumping 'person' blob and a flying 'ball' blob seen by a ring of cameras."""
    rng = np.random.default_rng(seed)
    gx, gy = np.meshgrid(np.linspace(-1.2, 1.2, 12), np.linspace(-1.2, 1.2, 12))
    floor = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1)
    person = rng.normal(size=(60, 3)) * [0.15, 0.15, 0.3]
    ball = rng.normal(size=(30, 3)) * 0.08
    N = len(floor) + len(person) + len(ball)
    means = np.empty((T, N, 3), np.float32)
    for t in range(T):
        u = t / max(T - 1, 1)
        means[t, :len(floor)] = floor
        means[t, len(floor):len(floor) + len(person)] = person + [-0.4, 0.0, 0.45 + 0.3 * math.sin(math.pi * u)]
        means[t, len(floor) + len(person):] = ball + [0.5 - 0.3 * u, 0.2, 0.9 + 0.2 * u]
    labels = np.concatenate([np.zeros(len(floor)), np.ones(len(person)), np.full(len(ball), 2)]).astype(np.int32)
    log_scales = np.log(np.concatenate([np.full((len(floor), 3), [0.12, 0.12, 0.02]),
                                        np.full((len(person) + len(ball), 3), 0.07)])).astype(np.float32)
    rotations = np.zeros((T, N, 4), np.float32)
    rotations[..., 0] = 1.0
    colors = rng.uniform(0.2, 0.9, size=(N, 3)).astype(np.float32)
    g = GaussianSequence(means=means, rotations=rotations, log_scales=log_scales,
                         opacity_logits=np.full(N, 3.0, np.float32), colors=colors,
                         labels=np.repeat(labels[None], T, 0))
    train = []
    for i in range(cameras):
        a = 2 * math.pi * i / cameras
        train.append(Camera.look_at((3.0 * math.cos(a), 3.0 * math.sin(a), 1.6), (0, 0, 0.4), width=width,
                                    height=height, fov_y=math.radians(45), name=f"cam{i:02d}"))
    test = [Camera.look_at((0.3, -3.2, 1.4), (0, 0, 0.4), width=width, height=height, fov_y=math.radians(45),
                           name="test00")]
    return Scene(gaussians=g, cameras=CameraRig.static(train, test, T), name="micro",
                 metadata={"labels": list(MICRO_LABELS)})


def micro_bundle(path: Path, **kw) -> Path:
    return write_bundle(micro_scene(**kw), path)


@pytest.fixture(autouse=True)
def one_thread():
    """One torch thread for the test (autouse where imported): bit-identical resumes and quieter timings."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


def kill_after_first_step(argv: list, env: dict, steps: Path, timeout: float = 240) -> None:
    """Start ``argv`` and SIGKILL it as soon as ``steps`` holds a finished per-timestep ``.npy`` (an
    interrupted distillation); fails if the run ends before it could be killed."""
    import signal
    import subprocess
    import time

    proc = subprocess.Popen(argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + timeout
    try:
        while time.time() < deadline and proc.poll() is None:
            if steps.is_dir() and any(p.suffix == ".npy" and not p.name.startswith(".") for p in steps.iterdir()):
                break
            time.sleep(0.01)
        assert proc.poll() is None, "the run finished before it could be killed"
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
