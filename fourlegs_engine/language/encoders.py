"""Video-text encoders: the shared interface, the canonical phrases and a registry by name.

Every encoder maps 8-frame clips and texts into one joint space:

- ``encode_video(clips (B, 8, C, h, w)) -> (B, D)`` and ``encode_text(list[str]) -> (n, D)``, both
  L2-normalized, batched, without gradients.
- ``input_kind`` says what the clips hold: ``"rgb"`` (ViCLIP: C=3, h=w=224, pixels already
  normalized with the CLIP mean/std, see ``ViCLIPEncoder.normalize``) or
  ``"labels"`` (the simulated encoder: per-pixel label coverage in [0, 1], any h, w).

Names: ``"viclip"`` (needs ``checkpoint=`` and ``vocab=``; the size is read off the checkpoint),
``"viclip-b16"`` (the same, insisting on the B/16 size) and ``"simulated"`` (implemented in
``language/simulated.py``, imported only when asked for). Heavy modules are imported lazily so
``fourlegs --help`` stays fast.
"""
from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any, Callable, Protocol, Sequence, runtime_checkable

from ..errors import InputError
from .phrases import CANONICAL_PHRASES

if TYPE_CHECKING:  # torch is imported only when an encoder is built (keeps `fourlegs --help` fast)
    import torch

__all__ = ["CANONICAL_PHRASES", "VideoTextEncoder", "add_encoder_arguments", "encoder_names", "get_encoder",
           "register_encoder", "resolve_device", "resolve_dtype"]


@runtime_checkable
class VideoTextEncoder(Protocol):
    """What the feature extractor and the query engine need from an encoder."""

    name: str
    dim: int
    input_kind: str  # "rgb" | "labels"

    def encode_video(self, clips: torch.Tensor) -> torch.Tensor:
        """clips (B, 8, C, h, w) -> (B, dim) L2-normalized."""
        ...

    def encode_text(self, texts: Sequence[str]) -> torch.Tensor:
        """n strings -> (n, dim) L2-normalized."""
        ...


def _viclip(size: str | None) -> Callable[..., VideoTextEncoder]:
    def factory(*, checkpoint=None, vocab=None, device="cpu", dtype="float32", batch_size=16,
                normalization="clip", size_override=None, **unused) -> VideoTextEncoder:
        if unused:
            raise InputError(f"unknown option(s) for the ViCLIP encoder: {', '.join(sorted(unused))}",
                             field="encoder")
        if checkpoint is None:
            raise InputError("the ViCLIP encoder needs a checkpoint (--checkpoint "
                             "ViClip-InternVid-10M-FLT.pth or a ViCLIP-*-hf directory); "
                             "weights are never downloaded", field="checkpoint")
        if vocab is None:
            raise InputError("the ViCLIP encoder needs the BPE vocabulary (--vocab "
                             "bpe_simple_vocab_16e6.txt.gz)", field="vocab")
        from .viclip import ViCLIPEncoder
        return ViCLIPEncoder.from_files(checkpoint, vocab, size=size_override or size,
                                        device=resolve_device(device), dtype=resolve_dtype(dtype),
                                        batch_size=batch_size, normalization=normalization)
    return factory


def _simulated(**kwargs: Any) -> VideoTextEncoder:
    """``language/simulated.py``'s ``create_encoder`` (labels= or scene=, see there)."""
    from .simulated import create_encoder
    return create_encoder(**kwargs)


_REGISTRY: dict[str, Callable[..., VideoTextEncoder]] = {
    "viclip": _viclip("auto"),
    "viclip-b16": _viclip("b"),
    "simulated": _simulated,
}


def register_encoder(name: str, factory: Callable[..., VideoTextEncoder], *, replace: bool = False) -> None:
    """Add an encoder factory under ``name`` (``replace=True`` to override an existing one)."""
    if name in _REGISTRY and not replace:
        raise ValueError(f"an encoder named {name!r} is already registered")
    _REGISTRY[name] = factory


def encoder_names() -> list[str]:
    return sorted(_REGISTRY)


def get_encoder(name: str, **kwargs: Any) -> VideoTextEncoder:
    """Build the encoder registered as ``name`` with the factory's keyword arguments."""
    factory = _REGISTRY.get(name)
    if factory is None:
        raise InputError(f"unknown encoder {name!r} (choose from {', '.join(encoder_names())})",
                         field="encoder")
    return factory(**kwargs)


def resolve_device(device: "str | torch.device | None") -> "torch.device":
    """``"auto"``/None -> CUDA when available, else CPU; a named device must exist."""
    import torch
    if device in (None, "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        resolved = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise InputError(f"not a device: {device!r} ({exc})", field="device") from None
    if resolved.type == "cuda" and not torch.cuda.is_available():
        raise InputError("CUDA was asked for but no CUDA device is available", field="device")
    return resolved


_DTYPES = ("float32", "float16", "bfloat16")


def resolve_dtype(dtype: "str | torch.dtype") -> "torch.dtype":
    """A torch dtype from its name ('float32', 'float16', 'bfloat16') or itself."""
    import torch
    if isinstance(dtype, torch.dtype):
        return dtype
    if dtype not in _DTYPES:
        raise InputError(f"unknown dtype {dtype!r} (choose from {', '.join(_DTYPES)})", field="dtype")
    return getattr(torch, dtype)


def add_encoder_arguments(parser: argparse.ArgumentParser, *, default: str = "viclip") -> None:
    """The encoder options shared by every command that encodes video or text."""
    group = parser.add_argument_group("encoder")
    group.add_argument("--encoder", default=default, choices=encoder_names(),
                       help=f"video-text encoder (default: {default})")
    group.add_argument("--checkpoint", default=None,
                       help="ViCLIP weights: ViClip-InternVid-10M-FLT.pth, a .safetensors file or a "
                            "ViCLIP-*-hf directory (never downloaded)")
    group.add_argument("--vocab", default=None, help="CLIP BPE vocabulary bpe_simple_vocab_16e6.txt.gz")
    group.add_argument("--viclip-size", default="auto", choices=("auto", "l", "b"),
                       help="ViCLIP size; 'auto' reads it off the checkpoint (default)")
    group.add_argument("--device", default="auto", help="cpu, cuda, cuda:1 or auto (default)")
    group.add_argument("--encoder-dtype", default="float32", choices=sorted(_DTYPES),
                       help="ViCLIP weights precision (float16/bfloat16 only on GPU; default float32)")
    group.add_argument("--encoder-batch-size", type=int, default=16,
                       help="clips or texts per encoder forward pass (default 16)")
    group.add_argument("--pixel-normalization", default="clip", choices=("clip", "imagenet"),
                       help="pixel statistics ViCLIP sees: 'clip' (as the 4-LEGS pipeline describes, "
                            "default) or 'imagenet' (the statistics ViCLIP was trained with)")


def load_encoder_from_args(args: argparse.Namespace, **extra: Any) -> VideoTextEncoder:
    """Build the encoder named by ``args.encoder`` from the options of :func:`add_encoder_arguments`.

    ``extra`` goes to the factory as well (the simulated encoder takes e.g. the scene). Options that
    a parser did not define fall back to their defaults.
    """
    name = getattr(args, "encoder", None) or "viclip"
    if name.startswith("viclip"):
        size = getattr(args, "viclip_size", "auto")
        kwargs: dict[str, Any] = dict(
            checkpoint=getattr(args, "checkpoint", None),
            vocab=getattr(args, "vocab", None),
            device=getattr(args, "device", "auto"),
            dtype=getattr(args, "encoder_dtype", "float32"),
            batch_size=getattr(args, "encoder_batch_size", 16),
            normalization=getattr(args, "pixel_normalization", "clip"),
        )
        if size not in (None, "auto"):
            kwargs["size_override"] = size
        kwargs.update(extra)
        return get_encoder(name, **kwargs)
    return get_encoder(name, **extra)
