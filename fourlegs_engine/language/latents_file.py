"""The distilled field on disk: the per-timestep results merged into ``language/latents.npy`` and swapped
in so that ``scene.json`` always names a complete field (a reader, or a kill, sees the old or the new)."""
from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..fileio import atomic_path, read_json
from ..scene.scene import Scene
from .autoencoder import DECODER_FILE, load_decoder, weights_fingerprint
from .extract import feature_store
from .phrases import CANONICAL_PHRASES
from .store import StepStore

if TYPE_CHECKING:
    from .distill import DistillOptions

LANGUAGE_DIR = "language"
STEPS_DIR = "language/steps"
LATENTS_FILE = "language/latents.npy"
NEXT_LATENTS_NAME = "latents.next.npy"  # a merged field on its way in (see _swap_in_latents)


def merged_hash(scene: Scene, out: Path, default_out: bool) -> str | None:
    """The config hash of the merged field in ``out`` (None when there is none)."""
    if not (out / "latents.npy").is_file():
        return None
    if default_out:
        lang = read_json(Path(scene.root) / "scene.json").get("language") or {}
        return lang.get("config_hash")
    marker = out / "latents.json"
    return read_json(marker).get("config_hash") if marker.is_file() else None


def forget_merged(out: Path) -> None:
    """Drop the record of a merged field outside the bundle's own directory."""
    (out / "latents.json").unlink(missing_ok=True)


def merge_latents(scene: Scene, store: StepStore, out: Path, chash: str, config: DistillOptions, *,
                  update_bundle: bool) -> Path:
    """Assemble the per-timestep files into (T,N,d) float16 ``latents.npy`` atomically; then record it
    (scene.json ``language`` for the bundle's own field, ``latents.json`` elsewhere) and drop the parts."""
    from ..fileio import write_json_atomic
    first = store.load_verified(0)
    root = Path(scene.root)
    T = scene.num_timesteps
    path = out / "latents.npy"
    info = {"encoder": _encoder_name(store, scene),
            "encoder_config": feature_store(scene).config.get("encoder_config"), "latent_dim": int(first.shape[1]),
            "canonical_phrases": list(CANONICAL_PHRASES), "decoder": DECODER_FILE, "latents": LATENTS_FILE,
            "decoder_fingerprint": weights_fingerprint(load_decoder(root / DECODER_FILE)),
            "mode": config.mode, "config_hash": chash, "config": store.config}
    next_path = out / NEXT_LATENTS_NAME
    with atomic_path(next_path) as tmp:
        arr = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.float16, shape=(T,) + tuple(first.shape))
        for t in range(T):
            arr[t] = store.load_verified(t)
        arr.flush()
        del arr
    if update_bundle:
        _swap_in_latents(root, next_path, path, info)
    else:
        next_path.replace(path)
        write_json_atomic(out / "latents.json", {**info, "latents": str(path)})
    shutil.rmtree(store.root, ignore_errors=True)
    return path


def finish_swap(root: Path) -> None:
    """Complete a swap that a kill interrupted after scene.json named the new field's file."""
    lang = read_json(root / "scene.json").get("language") or {}
    next_path = root / LANGUAGE_DIR / NEXT_LATENTS_NAME
    if isinstance(lang, dict) and lang.get("latents") == next_path.relative_to(root).as_posix() \
            and next_path.is_file():
        _swap_in_latents(root, next_path, root / LATENTS_FILE, dict(lang))


def _swap_in_latents(root: Path, next_path: Path, path: Path, info: dict[str, Any]) -> None:
    """Make the complete ``next_path`` the bundle's field; ``scene.json`` always names a complete file
    whose description it holds, so a reader (or a kill) at any point sees the old or the new field.

    1. scene.json -> next_path (new description), 2. ``path`` replaced by a hard link to the new file,
    3. scene.json -> ``path``, 4. ``next_path`` removed.
    """
    from ..scene.bundle import read_bundle_meta, update_bundle_meta

    arrays = dict(read_bundle_meta(root)["arrays"])
    arrays["latents"] = info["latents"] = next_path.relative_to(root).as_posix()
    update_bundle_meta(root, language=dict(info), arrays=arrays)
    with atomic_path(path) as tmp:
        tmp.unlink()
        try:
            os.link(next_path, tmp)
        except OSError:  # no hard links on this file system: a copy
            shutil.copyfile(next_path, tmp)
    arrays["latents"] = info["latents"] = LATENTS_FILE
    update_bundle_meta(root, language=info, arrays=arrays)
    next_path.unlink(missing_ok=True)


def _encoder_name(store: StepStore, scene: Scene) -> str:
    """The name of the encoder the features were extracted with."""
    return str(feature_store(scene).config.get("encoder", "unknown"))
