"""Open (or, once per scene, build) the distilled language field a query needs.

``ensure_language_field`` runs the language pipeline of :mod:`fourlegs_engine.language` (feature
extraction, autoencoder, distillation in the learning-free ``lift`` mode) when the bundle has no field
yet, then opens it. Every stage resumes where it stopped.
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, Optional

from ..errors import InputError
from ..scene.bundle import load_bundle
from ..scene.scene import Scene


def default_text_encoder(scene: Scene, name: Optional[str] = None, **kwargs: Any):
    """The encoder the scene's field was (or will be) distilled with: its recorded name, else
    "simulated" for synthetic scenes (they carry ``metadata["labels"]``), else "viclip"."""
    from ..language.encoders import get_encoder

    if name in (None, "auto"):
        name = (scene.language or {}).get("encoder") or (
            "simulated" if (scene.metadata or {}).get("labels") else "viclip")
    if name == "simulated":
        kwargs.setdefault("scene", scene)
    return get_encoder(name, **kwargs)


def ensure_language_field(scene: Scene, encoder: Any = None, *, progress: bool = False,
                          mode: str = "lift") -> tuple[Scene, Any, Any]:
    """Return ``(scene, field, encoder)``, distilling the field first if the bundle has none.

    Args:
        scene: a bundle scene (``scene.root`` set).
        encoder: the video-text encoder (default: :func:`default_text_encoder`).
    """
    from ..language.field import LanguageField

    if scene.root is None:
        raise InputError("the scene must be a bundle on disk to hold its language field", field="scene")
    encoder = encoder if encoder is not None else default_text_encoder(scene)
    if not scene.language or not (Path(scene.root) / str(scene.language.get("latents", ""))).is_file():
        from ..language.autoencoder import train_autoencoder
        from ..language.distill import distill_scene
        from ..language.extract import extract_features

        if progress:
            print(f"{scene.name}: no language field yet; extracting features, training the autoencoder and "
                  f"distilling ({mode}) — once per scene", file=sys.stderr)
        extract_features(scene, encoder, progress=progress)
        train_autoencoder(scene, progress=progress)
        distill_scene(scene, mode=mode, progress=progress)
        scene = load_bundle(scene.root)
    return scene, LanguageField.open(scene.root), encoder
