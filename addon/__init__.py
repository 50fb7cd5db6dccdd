"""4-LEGS Highlights for Blender: type a query, get the shots, render the highlight video.

A thin Blender layer over ``fourlegs_engine`` (pure Python + torch). ``bpy`` is imported only when
Blender registers the add-on, so ``fourlegs_addon.commands`` and the pure helpers (``convert``,
``build``) stay importable from the engine's command line without Blender.
"""
from __future__ import annotations


def register() -> None:
    from . import registration

    registration.register()


def unregister() -> None:
    from . import registration

    registration.unregister()
