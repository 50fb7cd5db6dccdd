"""``Scene``: Gaussians + cameras + metadata, the unit every stage reads and writes."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np

from .camera import CameraRig
from .gaussians import GaussianSequence


@dataclass
class Scene:
    """A dynamic Gaussian scene.

    Attributes:
        gaussians: the T x N Gaussians.
        cameras: per-timestep train/test cameras.
        name: human-readable scene name.
        fps: capture frame rate (timesteps per second).
        root: the bundle directory when the scene lives on disk (stages write their results there).
        language: description of the distilled language field, or None. Keys written by the language
            stage: ``encoder`` (str), ``latent_dim`` (int), ``canonical_phrases`` (list[str]),
            ``decoder`` (path relative to ``root``), plus stage-specific entries.
        metadata: free-form JSON-serializable information (source format, generator settings, ...).
    """

    gaussians: GaussianSequence
    cameras: CameraRig
    name: str = "scene"
    fps: float = 30.0
    root: Optional[Path] = None
    language: Optional[dict[str, Any]] = None
    metadata: dict[str, Any] = field(default_factory=dict)

    @property
    def num_timesteps(self) -> int:
        return self.gaussians.num_timesteps

    @property
    def num_gaussians(self) -> int:
        return self.gaussians.num_gaussians

    @property
    def has_language_field(self) -> bool:
        return self.gaussians.latents is not None

    def summary(self) -> dict[str, Any]:
        """Facts printed by ``fourlegs info`` (JSON-serializable)."""
        g = self.gaussians
        lo, hi = g.bounds()
        fg = None if g.foreground is None or g.num_gaussians == 0 else float(np.mean(g.foreground))
        nbytes = g.nbytes()
        return {
            "name": self.name,
            "num_timesteps": g.num_timesteps,
            "num_gaussians": g.num_gaussians,
            "num_train_cameras": self.cameras.num_cameras("train"),
            "num_test_cameras": self.cameras.num_cameras("test"),
            "image_size": _image_size(self.cameras),
            "fps": self.fps,
            "bounds_min": [round(float(v), 4) for v in lo],
            "bounds_max": [round(float(v), 4) for v in hi],
            "foreground_share": fg,
            "memory_bytes": int(sum(v for k, v in nbytes.items() if k != "latents")),
            "latents_bytes_on_disk": int(nbytes.get("latents", 0)),
            "language_field": self.has_language_field,
            "latent_dim": g.latent_dim,
            "color_model": "rgb" if g.colors is not None else f"sh{int(np.sqrt(g.sh.shape[-2])) - 1}",
            "root": str(self.root) if self.root else None,
        }


def _image_size(rig: CameraRig) -> Optional[list[int]]:
    cams = rig.cameras(0, "all") if rig.num_timesteps else []
    return [cams[0].width, cams[0].height] if cams else None
