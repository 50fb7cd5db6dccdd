"""ViCLIP (InternVid) video-text encoder written in plain torch, loading the official weights.

- :mod:`.model`: the architecture (``ViCLIPModel``, ``ViCLIPConfig.large()`` / ``.base()``).
- :mod:`.tokenizer`: CLIP's BPE tokenizer over ``bpe_simple_vocab_16e6.txt.gz``.
- :mod:`.checkpoint`: strict, pickle-free loading (``.pth`` and ``-hf`` safetensors) and saving.
- :mod:`.encoder`: ``ViCLIPEncoder``, the ``VideoTextEncoder`` the rest of the engine uses.
``fourlegs viclip-info`` lives in :mod:`fourlegs_engine.commands.viclip`, ``fourlegs bench viclip`` in ``fourlegs_bench.viclip``.
"""
from ...lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "check_state_dict": "checkpoint", "load_viclip": "checkpoint", "read_state_dict": "checkpoint",
    "save_viclip": "checkpoint", "ViCLIPEncoder": "encoder", "CLIP_MEAN": "model", "CLIP_STD": "model",
    "IMAGENET_MEAN": "model", "IMAGENET_STD": "model", "ViCLIPConfig": "model", "ViCLIPModel": "model",
    "infer_config": "model", "BPETokenizer": "tokenizer"
})
