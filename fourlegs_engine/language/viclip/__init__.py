"""ViCLIP (InternVid) video-text encoder written in plain torch, loading the official weights.

- :mod:`.model`: the architecture (``ViCLIPModel``, ``ViCLIPConfig.large()`` / ``.base()``).
- :mod:`.tokenizer`: CLIP's BPE tokenizer over ``bpe_simple_vocab_16e6.txt.gz``.
- :mod:`.checkpoint`: strict, pickle-free loading (``.pth`` and ``-hf`` safetensors) and saving.
- :mod:`.encoder`: ``ViCLIPEncoder``, the ``VideoTextEncoder`` the rest of the engine uses.
- :mod:`.commands`: ``fourlegs viclip-info`` (``fourlegs bench viclip`` lives in ``benchmarks.viclip``).

Names are imported on first use, so the CLI can register its commands without importing torch.
"""
from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "BPETokenizer": ".tokenizer",
    "CLIP_MEAN": ".model", "CLIP_STD": ".model", "IMAGENET_MEAN": ".model", "IMAGENET_STD": ".model",
    "ViCLIPConfig": ".model", "ViCLIPModel": ".model", "infer_config": ".model",
    "ViCLIPEncoder": ".encoder",
    "check_state_dict": ".checkpoint", "load_viclip": ".checkpoint", "read_state_dict": ".checkpoint",
    "save_viclip": ".checkpoint",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(_EXPORTS[name], __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
