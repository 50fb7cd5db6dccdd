"""Video-text encoders: the shared interface, the canonical phrases and a registry by name.

Every encoder maps 8-frame clips and texts into one joint space:

- ``encode_video(clips (B, 8, C, h, w)) -> (B, D)`` and ``encode_text(list[str]) -> (n, D)``, both
  L2-normalized, batched, without gradients.
- ``input_kind`` says what the clips hold: ``"rgb"`` (ViCLIP: C=3, h=w=224, pixels already
  normalized with the CLIP mean/std, see ``ViCLIPEncoder.normalize``) or
  ``"labels"`` (the simulated encoder: per-pixel label coverage in [0, 1], any h, w).

Names: ``"viclip"`` (needs ``checkpoint=`` and ``vocab=``; the size is read off the checkpoint),
``"viclip-b16"`` (the same, insisting on the B/16 size) and ``"masks"`` (per-pixel annotation masks read
from folders, not a network: ``language/annotations.py``). The demo package registers ``"simulated"``
(:mod:`fourlegs_engine.demo`, the demo scenes' simulated encoder) when it is imported. Heavy modules are
imported lazily so ``fourlegs --help`` stays fast.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, Protocol, Sequence, runtime_checkable

from ..errors import InputError
from .phrases import CANONICAL_PHRASES

if TYPE_CHECKING:  # torch is imported only when an encoder is built (keeps `fourlegs --help` fast)
    import torch

__all__ = ["CANONICAL_PHRASES", "VideoTextEncoder", "encoder_names", "get_encoder",
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


def _annotation_masks(**kwargs: Any) -> VideoTextEncoder:
    """``language/annotations.py``'s ``create_encoder`` (masks=, see there): annotation masks, no network."""
    from .annotations import create_encoder
    return create_encoder(**kwargs)


_REGISTRY: dict[str, Callable[..., VideoTextEncoder]] = {
    "viclip": _viclip("auto"),
    "viclip-b16": _viclip("b"),
    "masks": _annotation_masks,
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


DTYPES = ("float32", "float16", "bfloat16")


def resolve_dtype(dtype: "str | torch.dtype") -> "torch.dtype":
    """A torch dtype from its name ('float32', 'float16', 'bfloat16') or itself."""
    import torch
    if isinstance(dtype, torch.dtype):
        return dtype
    if dtype not in DTYPES:
        raise InputError(f"unknown dtype {dtype!r} (choose from {', '.join(DTYPES)})", field="dtype")
    return getattr(torch, dtype)
