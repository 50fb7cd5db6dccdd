"""Reading and writing ViCLIP weights in the official key layout, strictly and without pickle.

Accepted inputs (nothing is ever downloaded):

- ``ViClip-InternVid-10M-FLT.pth`` (and other ``.pth``/``.pt``/``.bin`` files): read with
  ``torch.load(weights_only=True)``, so no pickled code can run; the state dict is the ``"model"``
  entry (a bare state dict is accepted too). A run configuration stored beside it as an
  ``easydict.EasyDict`` (InternVideo training checkpoints) is read as a plain OrderedDict.
- ``model.safetensors`` of ``OpenGVLab/ViCLIP-L-14-hf`` / ``ViCLIP-B-16-hf`` (or the directory that
  holds it): the same keys, stored flat.

The keys must match the model exactly: missing keys, unexpected keys and shape mismatches are all
listed in one :class:`InputError` that names the file. A ``module.`` prefix on every key (weights
saved from a DistributedDataParallel wrapper) is removed first; nothing else is renamed.
"""
from __future__ import annotations

import pickle
import warnings
import zipfile
from collections import OrderedDict
from pathlib import Path
from typing import Mapping

import torch

from ...errors import InputError
from ...fileio import TORCH_LOAD_ERRORS, atomic_path
from .model import ViCLIPConfig, ViCLIPModel, expected_shapes, infer_config

SAFETENSORS_NAME = "model.safetensors"
_LISTED = 12  # keys listed per category in an error message


def resolve_checkpoint_path(path: str | Path) -> Path:
    """A checkpoint file, or a ``-hf`` model directory holding ``model.safetensors``."""
    path = Path(path)
    if path.is_dir():
        candidate = path / SAFETENSORS_NAME
        if candidate.is_file():
            return candidate
        raise InputError(f"directory holds no {SAFETENSORS_NAME}", file=path)
    if not path.is_file():
        raise InputError("checkpoint file is missing", file=path)
    return path


def read_state_dict(path: str | Path) -> dict[str, torch.Tensor]:
    """Load a checkpoint's tensors on the CPU (``.safetensors``, else ``torch.load(weights_only=True)``)."""
    path = resolve_checkpoint_path(path)
    if path.suffix == ".safetensors":
        state = _read_safetensors(path)
    else:
        state = _read_torch(path)
    if not state:
        raise InputError("the checkpoint holds no tensors", file=path)
    odd_keys = [repr(key) for key in state if not isinstance(key, str)]
    if odd_keys:
        raise InputError(f"keys that are not strings: {_listing(odd_keys)}", file=path, field="model")
    bad = [key for key, value in state.items() if not isinstance(value, torch.Tensor)]
    if bad:
        raise InputError(f"entries that are not tensors: {_listing(bad)}", file=path, field="model")
    if all(key.startswith("module.") for key in state):
        state = {key[len("module."):]: value for key, value in state.items()}
    return state


def _read_safetensors(path: Path) -> dict[str, torch.Tensor]:
    from safetensors import SafetensorError
    from safetensors.torch import load_file
    try:
        return dict(load_file(str(path), device="cpu"))
    except (SafetensorError, OSError, ValueError) as exc:
        raise InputError(f"not a readable safetensors file ({exc})", file=path) from None


# Training checkpoints of the InternVideo family keep their run configuration next to the weights as
# an ``easydict.EasyDict``. Its pickle only creates the object, fills its items and sets its
# attributes; a plain OrderedDict accepts exactly those steps, so the name is mapped to OrderedDict
# (no code from the easydict package, installed or not, is ever involved).
_INERT_STAND_INS = [(OrderedDict, "easydict.EasyDict")]


def _torch_load(path: Path):
    """``torch.load(weights_only=True)``, memory-mapped for zip archives (reading them costs nothing)."""
    mmap = zipfile.is_zipfile(path)
    safe_globals = getattr(torch.serialization, "safe_globals", None)
    with warnings.catch_warnings():  # a raw pickle of another protocol is refused or read all the same
        warnings.filterwarnings("ignore", message="Detected pickle protocol", category=UserWarning)
        if safe_globals is None:  # torch < 2.5: no stand-ins, EasyDict entries are refused
            return torch.load(path, map_location="cpu", weights_only=True, mmap=mmap)
        with safe_globals(_INERT_STAND_INS):
            return torch.load(path, map_location="cpu", weights_only=True, mmap=mmap)


def _read_torch(path: Path) -> dict[str, torch.Tensor]:
    try:
        obj = _torch_load(path)
    except pickle.UnpicklingError as exc:
        detail = _unpickler_detail(str(exc))
        if "global" in detail.lower():
            raise InputError("refused: the file holds pickled Python objects beyond tensors, and pickled "
                             f"objects are refused, never executed ({detail}). If the file comes "
                             "from a source you trust, re-save its 'model' entry alone with torch.save "
                             "once and load that", file=path) from None
        raise InputError(f"not a readable torch checkpoint ({detail})", file=path) from None
    except TORCH_LOAD_ERRORS as exc:
        raise InputError(f"not a readable torch checkpoint ({type(exc).__name__}: {str(exc)[:200]})",
                         file=path) from None
    if isinstance(obj, Mapping) and "model" in obj and isinstance(obj["model"], Mapping):
        return dict(obj["model"])
    if isinstance(obj, Mapping) and obj and all(isinstance(k, str) for k in obj):
        return dict(obj)
    keys = sorted(map(str, obj.keys()))[:_LISTED] if isinstance(obj, Mapping) else []
    raise InputError(f"expected a state dict under 'model' (found {type(obj).__name__} with keys {keys})",
                     file=path, field="model")


def _unpickler_detail(message: str) -> str:
    """The one informative sentence of torch's long weights-only error, e.g. 'Unsupported global: ...'."""
    from ...fileio import unpickling_detail
    return unpickling_detail(Exception(message))


def _listing(keys: list[str]) -> str:
    shown = ", ".join(keys[:_LISTED])
    more = len(keys) - _LISTED
    return f"{shown}, and {more} more" if more > 0 else shown


def check_state_dict(state: Mapping[str, torch.Tensor], config: ViCLIPConfig, *, file: str | Path) -> None:
    """Raise one :class:`InputError` listing missing keys, unexpected keys and shape mismatches."""
    expected = expected_shapes(config)
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    mismatched = sorted(f"{key} (file {tuple(state[key].shape)}, model {expected[key]})"
                        for key in set(expected) & set(state) if tuple(state[key].shape) != expected[key])
    not_float = sorted(f"{key} ({str(state[key].dtype).removeprefix('torch.')})" for key in set(expected) & set(state)
                       if not state[key].is_floating_point())
    problems = []
    if missing:
        problems.append(f"missing keys ({len(missing)}): {_listing(missing)}")
    if unexpected:
        problems.append(f"unexpected keys ({len(unexpected)}): {_listing(unexpected)}")
    if mismatched:
        problems.append(f"shape mismatches ({len(mismatched)}): {_listing(mismatched)}")
    if not_float:
        problems.append(f"not floating-point ({len(not_float)}): {_listing(not_float)}")
    if problems:
        raise InputError(f"does not match ViCLIP {config.size_name}: " + "; ".join(problems), file=file,
                         field="state dict")


def config_for(state: Mapping[str, torch.Tensor], size: str | ViCLIPConfig | None, *,
               file: str | Path) -> ViCLIPConfig:
    """The architecture to build: a preset/explicit config, or (``size`` None/'auto') read off the file."""
    if isinstance(size, ViCLIPConfig):
        return size
    if size not in (None, "auto"):
        try:
            return ViCLIPConfig.preset(size)
        except ValueError as exc:
            raise InputError(str(exc), field="size") from None
    shapes = {key: tuple(value.shape) for key, value in state.items()}
    try:
        config = infer_config(shapes)
        return config.validate()
    except KeyError as exc:
        raise InputError(f"not a ViCLIP checkpoint: key {exc.args[0]} is missing "
                         f"(found {_listing(sorted(state))})", file=file, field="state dict") from None
    except (ValueError, IndexError) as exc:
        raise InputError(f"not a ViCLIP checkpoint: {exc}", file=file, field="state dict") from None


def load_viclip(path: str | Path, *, size: str | ViCLIPConfig | None = "auto",
                device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32) -> ViCLIPModel:
    """Build a ViCLIP model from a checkpoint, strictly, in eval mode with gradients off.

    The model is created on the meta device and the checkpoint tensors are assigned to it, so the
    full ViT-L is never allocated twice.
    """
    file = resolve_checkpoint_path(path)
    state = read_state_dict(file)
    config = config_for(state, size, file=file)
    check_state_dict(state, config, file=file)
    with torch.device("meta"):
        model = ViCLIPModel(config)
    target = torch.device(device)
    # copy=True: never keep a view of the (memory-mapped) file inside the model
    converted = {key: value.to(device=target, dtype=dtype if value.is_floating_point() else value.dtype,
                               copy=True)
                 for key, value in state.items()}
    not_finite = sorted(key for key, value in converted.items() if not bool(torch.isfinite(value).all()))
    if not_finite:
        raise InputError(f"weights contain NaN or Inf: {_listing(not_finite)}", file=file, field="state dict")
    model.load_state_dict(converted, strict=True, assign=True)
    model.requires_grad_(False)
    return model.eval()


def official_state_dict(model: ViCLIPModel) -> dict[str, torch.Tensor]:
    """The model's tensors under the official names, detached, contiguous and on the CPU."""
    return {key: value.detach().cpu().contiguous() for key, value in model.state_dict().items()}


def save_viclip(model: ViCLIPModel, path: str | Path, *, overwrite: bool = False) -> Path:
    """Write the weights in the official layout: ``.safetensors`` flat, otherwise ``{"model": ...}``.

    Written to a temporary file and renamed, so no half-written checkpoint is ever left behind.
    """
    path = Path(path)
    state = official_state_dict(model)
    with atomic_path(path, overwrite=overwrite) as tmp:
        if path.suffix == ".safetensors":
            from safetensors.torch import save_file
            save_file(state, str(tmp), metadata={"format": "pt", "viclip_size": model.config.size_name})
        else:
            torch.save({"model": state}, tmp)
    return path
