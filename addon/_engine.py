"""Where the engine comes from: the copy bundled inside the extension zip, else the installed package.

The Blender extension ships ``fourlegs_engine`` as a sub-package of the add-on (the engine uses
relative imports only, so it works at any package depth); a developer checkout has it installed as
the top-level ``fourlegs_engine``.
"""
from __future__ import annotations

import importlib
from types import ModuleType

try:  # inside the extension zip
    from . import fourlegs_engine as engine  # type: ignore[attr-defined]
except ImportError:  # pip-installed / editable checkout
    import fourlegs_engine as engine  # noqa: F401


def engine_module(name: str) -> ModuleType:
    """Import ``fourlegs_engine.<name>`` from whichever engine copy is in use (e.g. ``"render"``)."""
    return importlib.import_module(f"{engine.__name__}.{name}")
