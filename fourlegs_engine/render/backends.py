"""Backend selection: the pure-torch rasterizer everywhere, gsplat on CUDA when installed."""
from __future__ import annotations

import importlib.util
from typing import Callable

import torch

from ..errors import InputError

BACKENDS = ("auto", "torch", "gsplat")
#: outputs the gsplat backend can produce
GSPLAT_OUTPUTS = frozenset({"rgb", "features", "depth", "alpha"})


def gsplat_available() -> bool:
    """True when the gsplat package can be imported (it is not imported here)."""
    return importlib.util.find_spec("gsplat") is not None


def select_backend(name: str, device: torch.device, outputs: tuple[str, ...]) -> Callable:
    """The rasterize implementation for ``name`` ("auto", "torch", "gsplat")."""
    if name not in BACKENDS:
        raise InputError(f"unknown backend {name!r}; choose from {BACKENDS}", field="backend")
    cuda = torch.device(device).type == "cuda"
    if name == "gsplat" or (name == "auto" and cuda and gsplat_available()
                            and set(outputs) <= GSPLAT_OUTPUTS):
        if not cuda:
            raise InputError("the gsplat backend needs CUDA tensors", field="backend")
        if not gsplat_available():
            raise InputError("gsplat is not installed (pip install 'fourlegs[cuda]')", field="backend")
        unsupported = sorted(set(outputs) - GSPLAT_OUTPUTS)
        if unsupported:
            raise InputError(f"gsplat cannot produce {unsupported}; use backend='torch'", field="backend")
        from .gsplat_backend import rasterize_gsplat
        return rasterize_gsplat
    from .torch_backend import rasterize_torch
    return rasterize_torch
