"""``ViCLIPEncoder``: the ``VideoTextEncoder`` backed by a ViCLIP model and the CLIP BPE tokenizer."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import torch

from ...errors import InputError
from .checkpoint import load_viclip, resolve_checkpoint_path
from .model import CLIP_MEAN, CLIP_STD, IMAGENET_MEAN, IMAGENET_STD, ViCLIPModel
from .tokenizer import BPETokenizer

NORMALIZATIONS = {"clip": (CLIP_MEAN, CLIP_STD), "imagenet": (IMAGENET_MEAN, IMAGENET_STD)}


class ViCLIPEncoder:
    """Video and text embeddings in ViCLIP's joint space, L2-normalized, batched, without gradients.

    ``encode_video`` takes clips normalized with the CLIP statistics (``pixel_mean``/``pixel_std``;
    ``normalize`` does that for clips in [0, 1]), as the contract of ``language`` says.
    ``normalization`` chooses what the model then sees: ``"clip"`` (default) feeds them unchanged, as
    the 4-LEGS feature pipeline describes; ``"imagenet"`` re-expresses them with the ImageNet
    statistics that ViCLIP itself was trained and demonstrated with (an exact per-channel affine map).
    """

    input_kind = "rgb"

    def __init__(self, model: ViCLIPModel, tokenizer: BPETokenizer, *, batch_size: int = 16,
                 normalization: str = "clip", name: str | None = None, source: dict | None = None):
        config = model.config
        if tokenizer.vocab_size != config.vocab_size:
            raise InputError(f"the vocabulary has {tokenizer.vocab_size} ids but the model's text tower "
                             f"has {config.vocab_size}: wrong bpe_simple_vocab file?", file=tokenizer.path)
        if normalization not in NORMALIZATIONS:
            raise InputError(f"unknown normalization {normalization!r} (choose from {sorted(NORMALIZATIONS)})",
                             field="normalization")
        if batch_size < 1:
            raise InputError(f"batch size must be at least 1, got {batch_size}", field="batch_size")
        self.model = model.eval().requires_grad_(False)
        self.tokenizer = tokenizer
        self.model_config = config
        self.batch_size = int(batch_size)
        self.normalization = normalization
        self.pixel_mean = torch.tensor(CLIP_MEAN)
        self.pixel_std = torch.tensor(CLIP_STD)
        # model input = clips * scale + shift, per channel (identity for "clip")
        mean, std = (torch.tensor(v, dtype=torch.float64) for v in NORMALIZATIONS[normalization])
        clip_mean, clip_std = self.pixel_mean.double(), self.pixel_std.double()
        self._scale = (clip_std / std).float()
        self._shift = ((clip_mean - mean) / std).float()
        self.dim = config.embed_dim
        self.num_frames = config.num_frames
        self.image_size = config.image_size
        self.context_length = config.context_length
        self.source = dict(source or {})
        # a registry name of language.encoders, so the same encoder can be rebuilt from scene.json
        self.name = name or ("viclip-b16" if config.size_name == "B/16" else "viclip")

    def config(self) -> dict:
        """JSON-serializable settings that change the embeddings (for config hashes of cached features)."""
        return {"encoder": self.name, "size": self.model_config.size_name, "dim": self.dim,
                "num_frames": self.num_frames, "image_size": self.image_size,
                "context_length": self.context_length, "normalization": self.normalization,
                "dtype": str(self.model.temp.dtype).replace("torch.", ""), **self.source}

    @classmethod
    def from_files(cls, checkpoint: str | Path, vocab: str | Path, *, size: str | None = "auto",
                   device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32,
                   batch_size: int = 16, normalization: str = "clip") -> "ViCLIPEncoder":
        """Tokenizer first (cheap, fails fast on a wrong path), then the strict checkpoint load."""
        tokenizer = BPETokenizer(vocab)
        checkpoint_file = resolve_checkpoint_path(checkpoint)
        model = load_viclip(checkpoint_file, size=size, device=device, dtype=dtype)
        source = {"checkpoint": checkpoint_file.name, "checkpoint_bytes": checkpoint_file.stat().st_size,
                  "vocab": tokenizer.path.name}
        return cls(model, tokenizer, batch_size=batch_size, normalization=normalization, source=source)

    @property
    def device(self) -> torch.device:
        return self.model.temp.device

    def normalize(self, clips: torch.Tensor) -> torch.Tensor:
        """clips (..., 3, H, W) in [0, 1] -> CLIP-normalized (``pixel_mean``/``pixel_std``)."""
        mean = self.pixel_mean.to(clips.device, clips.dtype)[:, None, None]
        std = self.pixel_std.to(clips.device, clips.dtype)[:, None, None]
        return (clips - mean) / std

    def _check_clips(self, clips: torch.Tensor) -> None:
        if not isinstance(clips, torch.Tensor):
            raise InputError(f"clips must be a tensor, got {type(clips).__name__}", field="clips")
        size, frames = self.image_size, self.num_frames
        if clips.ndim != 5 or clips.shape[2] != 3 or clips.shape[3:] != (size, size) \
                or clips.shape[1] not in (frames, 1):
            raise InputError(f"clips must be (B, {frames}, 3, {size}, {size}), got {tuple(clips.shape)}",
                             field="clips")
        if not clips.is_floating_point():
            raise InputError(f"clips must be floating point (normalized pixels), got {clips.dtype}",
                             field="clips")
        if not bool(torch.isfinite(clips).all()):
            raise InputError("clips contain NaN or Inf", field="clips")

    @torch.inference_mode()
    def encode_video(self, clips: torch.Tensor) -> torch.Tensor:
        """clips (B, 8, 3, 224, 224) CLIP-normalized -> (B, D) float32, on the clips' device."""
        self._check_clips(clips)
        if clips.shape[0] == 0:
            return torch.zeros(0, self.dim, device=clips.device)
        model_dtype = self.model.temp.dtype
        out = []
        for chunk in clips.split(self.batch_size):
            chunk = chunk.to(self.device, non_blocking=True)
            if self.normalization != "clip":
                scale = self._scale.to(chunk.device, chunk.dtype)[:, None, None]
                shift = self._shift.to(chunk.device, chunk.dtype)[:, None, None]
                chunk = chunk * scale + shift
            out.append(self.model.encode_video(chunk.to(model_dtype)).float())
        return torch.cat(out).to(clips.device)

    @torch.inference_mode()
    def encode_text(self, texts: Sequence[str]) -> torch.Tensor:
        """texts (n strings) -> (n, D) float32 on the encoder's device."""
        if isinstance(texts, str):
            texts = [texts]
        if len(texts) == 0:
            return torch.zeros(0, self.dim, device=self.device)
        tokens = self.tokenizer.tokenize(list(texts), context_length=self.context_length)
        out = [self.model.encode_tokens(chunk.to(self.device)).float()
               for chunk in tokens.split(self.batch_size)]
        return torch.cat(out)

    def __repr__(self) -> str:
        return (f"ViCLIPEncoder({self.model_config.size_name}, dim={self.dim}, device={self.device}, "
                f"normalization={self.normalization!r})")
