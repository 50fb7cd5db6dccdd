"""Register / unregister every Blender class, property and handler of the add-on (bpy only here)."""
from __future__ import annotations

import bpy

from . import (importer, jobs, native_render, operators, panels, preferences, properties, render_engine,
               retime)

classes = (
    *preferences.classes,
    *properties.classes,
    *operators.classes,
    *panels.ui_lists,
    *panels.classes,
    *render_engine.classes,
)


def register() -> None:
    preferences.register()
    for cls in classes:
        bpy.utils.register_class(cls)
    properties.register()
    render_engine.register()
    importer.register()
    native_render.register()
    retime.register()


def unregister() -> None:
    jobs.cancel_all()
    preferences.unregister()
    native_render.unregister()
    retime.unregister()
    importer.unregister()
    render_engine.unregister()
    properties.unregister()
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
