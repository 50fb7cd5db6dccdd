"""What the query benchmarks share: a geometry-free scene, memory figures of this process, page-cache warming."""
from __future__ import annotations

import resource
import time
from pathlib import Path

import numpy as np

from fourlegs_engine.scene.camera import CameraRig
from fourlegs_engine.scene.gaussians import GaussianSequence
from fourlegs_engine.scene.scene import Scene


def resident_mb(kind: str) -> float:
    """One memory figure of this process from /proc/self/status in MB ("VmHWM": peak resident memory of
    this address space, "RssAnon": the process's own allocations, "RssFile": pages of mapped files,
    shared with the page cache); NaN where /proc is unavailable."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(kind + ":"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def peak_rss_mb() -> float:
    """Peak resident memory of this process image in MB: ``VmHWM`` on Linux (``ru_maxrss`` would carry
    the forking parent's peak over into a spawned child), else ``getrusage``."""
    peak = resident_mb("VmHWM")
    return peak if peak == peak else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def flat_scene(T: int, N: int) -> Scene:
    """Geometry-free stand-in for the temporal timings (temporal queries never touch geometry); its
    (T,N) arrays are broadcast views, so it adds nothing to the measured memory."""
    z = np.broadcast_to(np.zeros((1, 1, 3), np.float32), (T, N, 3))
    rot = np.broadcast_to(np.array([[[1, 0, 0, 0]]], np.float32), (T, N, 4))
    g = GaussianSequence(means=z, rotations=rot, log_scales=np.zeros((N, 3), np.float32),
                         opacity_logits=np.zeros(N, np.float32), colors=np.zeros((N, 3), np.float32))
    return Scene(gaussians=g, cameras=CameraRig(), name=f"random-{N}x{T}")


def warm_page_cache(path: Path, chunk: int = 64 << 20) -> float:
    """Read ``path`` once, sequentially, so its pages are in the page cache; returns the seconds taken."""
    start = time.perf_counter()
    buf = bytearray(chunk)
    with open(path, "rb", buffering=0) as f:
        while f.readinto(buf):
            pass
    return time.perf_counter() - start


def scene_with_field(scene: Scene, encoder=None, *, progress: bool = False):
    """``(scene, field, encoder)``: the scene with its language field (built once through the pipeline)."""
    from fourlegs_engine import pipeline
    from fourlegs_engine.language.field import LanguageField

    encoder = encoder if encoder is not None else pipeline.text_encoder(scene)
    scene = pipeline.ensure_language_field(scene, encoder, progress=progress)
    return scene, LanguageField.open(scene.root), encoder
