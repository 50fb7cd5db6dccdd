"""Task bodies for the Ray tests; a module of its own so Ray workers can import them (tests/ is put
on the workers' PYTHONPATH by the test fixture)."""
from __future__ import annotations

import os
import signal
from pathlib import Path
from typing import Any

import fourlegs_engine.demo  # noqa: F401 (registers the "simulated" encoder, in Ray's workers too)
from fourlegs_engine.language.encoders import get_encoder


class KillOnceEncoder:
    """The simulated encoder, except that the first call of any worker kills that worker's process
    (SIGKILL, as an out-of-memory killer or a lost node would) while ``marker`` does not exist yet."""

    def __init__(self, inner: Any, marker: Path):
        self.inner, self.marker = inner, Path(marker)
        self.name, self.dim, self.input_kind = inner.name, inner.dim, inner.input_kind

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def bind_camera(self, camera: str) -> "KillOnceEncoder":
        return KillOnceEncoder(self.inner.bind_camera(camera), self.marker)

    def encode_coverage(self, clips: Any) -> Any:
        if not self.marker.exists():
            self.marker.write_text(str(os.getpid()))
            os.kill(os.getpid(), signal.SIGKILL)
        return self.inner.encode_coverage(clips)


class KillOnceFactory:
    def __init__(self, marker: Path):
        self.marker = Path(marker)

    def __call__(self, scene: Any) -> KillOnceEncoder:
        return KillOnceEncoder(get_encoder("simulated", scene=scene), self.marker)


def simulated_factory(scene: Any) -> Any:
    return get_encoder("simulated", scene=scene)


def count_then_fail(job: Any, chunk: tuple[int, ...], payload: Any) -> int:
    """Appends one line per attempt to ``job`` (a file); chunk (2,) raises a retryable error, chunk
    (3,) bad input (not retried); the others return their timestep."""
    with open(job, "a") as fh:
        fh.write(f"{chunk[0]}\n")
    if chunk == (2,):
        raise RuntimeError("transient failure that never clears")
    if chunk == (3,):
        raise ValueError("bad input in timestep 3")
    return chunk[0] * 10
