"""Package attributes imported on first use (PEP 562): importing a package costs only what is used.

A package ``__init__`` names what it exports and the module each name lives in::

    __getattr__, __dir__, __all__ = lazy_exports(__name__, {"Camera": "camera", "load_scene": "loaders"})

``from package import Camera`` then imports ``package.camera`` alone, so a command that only needs the
scene loaders never pays for torch. A name mapped to None is a submodule of the package.
"""
from __future__ import annotations

import importlib
import sys
from typing import Any, Callable, Mapping, Optional


def lazy_exports(package: str, exports: Mapping[str, Optional[str]], *, base: Optional[str] = None
                 ) -> tuple[Callable[[str], Any], Callable[[], list[str]], list[str]]:
    """``(__getattr__, __dir__, __all__)`` for the module ``package``: each name of ``exports`` is read from
    the module it maps to, relative to ``base`` (default: ``package`` itself; None: the name is itself a
    module there), when first asked for, then cached on ``package``."""
    exports = dict(exports)
    base = base or package

    def __getattr__(name: str) -> Any:
        if name not in exports:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        module = exports[name]
        if module is None:
            value = importlib.import_module(f"{base}.{name}")
        else:
            value = getattr(importlib.import_module(f"{base}.{module}"), name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(exports))

    return __getattr__, __dir__, sorted(exports)
