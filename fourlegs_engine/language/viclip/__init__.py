"""ViCLIP (InternVid) video-text encoder written in plain torch, loading the official weights.

- :mod:`.model`: the architecture (``ViCLIPModel``, ``ViCLIPConfig.large()`` / ``.base()``).
- :mod:`.tokenizer`: CLIP's BPE tokenizer over ``bpe_simple_vocab_16e6.txt.gz``.
- :mod:`.checkpoint`: strict, pickle-free loading (``.pth`` and ``-hf`` safetensors) and saving.
- :mod:`.encoder`: ``ViCLIPEncoder``, the ``VideoTextEncoder`` the rest of the engine uses.
``fourlegs viclip-info`` lives in :mod:`fourlegs_engine.commands.viclip`, ``fourlegs bench viclip`` in ``fourlegs_bench.viclip``.
"""
from .checkpoint import check_state_dict, load_viclip, read_state_dict, save_viclip
from .encoder import ViCLIPEncoder
from .model import CLIP_MEAN, CLIP_STD, IMAGENET_MEAN, IMAGENET_STD, ViCLIPConfig, ViCLIPModel, infer_config
from .tokenizer import BPETokenizer

__all__ = ["BPETokenizer", "CLIP_MEAN", "CLIP_STD", "IMAGENET_MEAN", "IMAGENET_STD", "ViCLIPConfig", "ViCLIPEncoder",
           "ViCLIPModel", "check_state_dict", "infer_config", "load_viclip", "read_state_dict", "save_viclip"]
