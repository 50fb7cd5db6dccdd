"""Add-on Preferences: what is missing, and an installer for PyTorch (CPU or CUDA build) into the
extension's own site-packages, running pip in the background with progress and a clear outcome."""
from __future__ import annotations

from typing import Optional

import bpy
from bpy.props import EnumProperty, StringProperty

from . import torch_install

PACKAGE = __package__

_JOB: Optional[torch_install.InstallJob] = None


def preferences(context=None) -> Optional["FourlegsPreferences"]:
    addon = (context or bpy.context).preferences.addons.get(PACKAGE)
    return addon.preferences if addon is not None else None


def missing_line() -> str:
    """One line for the panel naming what is missing (empty when nothing is)."""
    missing = torch_install.missing_modules()
    if not missing:
        return ""
    return torch_install.missing_message(missing) + (" - install it in Edit > Preferences > Add-ons > "
                                                     "4-LEGS Highlights" if "torch" in missing else "")


class FourlegsPreferences(bpy.types.AddonPreferences):
    bl_idname = PACKAGE

    torch_variant: EnumProperty(
        name="PyTorch build",
        items=[(key, label, f"Install the {label} build of PyTorch") for key, (label, _) in
               torch_install.VARIANTS.items()],
        default="CPU")
    install_status: StringProperty(name="Outcome", default="")

    def draw(self, context):
        layout = self.layout
        missing = torch_install.missing_modules()
        box = layout.box()
        if missing:
            for name in missing:
                box.label(text=torch_install.missing_message([name]), icon="ERROR")
        else:
            box.label(text="Everything the add-on needs is installed", icon="CHECKMARK")
        box.label(text=f"Packages installed here go to: {torch_install.site_packages(PACKAGE, create=False)}")
        col = layout.column()
        col.prop(self, "torch_variant")
        if _JOB is not None and not _JOB.done:
            row = col.row(align=True)
            row.progress(factor=_JOB.progress, type="BAR", text=f"{_JOB.stage}: {_JOB.last_line[:60]}")
            row.operator("fourlegs.cancel_install_torch", text="", icon="CANCEL")
        else:
            col.operator("fourlegs.install_torch", icon="IMPORT")
        if self.install_status:
            col.label(text=self.install_status, icon="INFO")


class FOURLEGS_OT_install_torch(bpy.types.Operator):
    """Install PyTorch into the add-on's own folder with pip (downloads; runs in the background)"""

    bl_idname = "fourlegs.install_torch"
    bl_label = "Install PyTorch"

    requirement: StringProperty(default="torch", options={"HIDDEN", "SKIP_SAVE"})
    extra_args: StringProperty(default="", options={"HIDDEN", "SKIP_SAVE"},
                               description="extra pip arguments, space separated (tests, local indexes)")

    _timer = None

    def execute(self, context):
        global _JOB
        if _JOB is not None and not _JOB.done:
            self.report({"WARNING"}, "a PyTorch installation is already running")
            return {"CANCELLED"}
        prefs = preferences(context)
        variant = prefs.torch_variant if prefs is not None else "CPU"
        target = torch_install.site_packages(PACKAGE)
        command = torch_install.pip_install_command(target, variant, self.requirement, self.extra_args.split())
        _JOB = torch_install.InstallJob(command, target).start()
        if prefs is not None:
            prefs.install_status = f"installing {self.requirement} ({variant}) ..."
        self._timer = context.window_manager.event_timer_add(0.25, window=context.window)
        context.window_manager.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type == "ESC":
            _JOB.cancel()
        if event.type != "TIMER" and event.type != "ESC":
            return {"PASS_THROUGH"}
        for area in context.screen.areas if context.screen else ():
            area.tag_redraw()
        if not _JOB.done:
            return {"PASS_THROUGH"}
        context.window_manager.event_timer_remove(self._timer)
        return finish(self, context)


def finish(op, context) -> set[str]:
    """Report the finished job's outcome and make what it installed importable."""
    prefs = preferences(context)
    if _JOB.ok:
        torch_install.add_to_sys_path(_JOB.target)
        message = f"PyTorch {_JOB.message}"
        op.report({"INFO"}, message)
    else:
        message = f"PyTorch not installed: {_JOB.message}"
        op.report({"ERROR"}, message)
    if prefs is not None:
        prefs.install_status = message
    return {"FINISHED"} if _JOB.ok else {"CANCELLED"}


class FOURLEGS_OT_cancel_install_torch(bpy.types.Operator):
    """Stop the PyTorch installation"""

    bl_idname = "fourlegs.cancel_install_torch"
    bl_label = "Cancel PyTorch Installation"

    def execute(self, context):
        if _JOB is not None:
            _JOB.cancel()
        return {"FINISHED"}


def register() -> None:
    torch_install.add_to_sys_path(torch_install.site_packages(PACKAGE))


def unregister() -> None:
    if _JOB is not None:
        _JOB.cancel()


classes = (FourlegsPreferences, FOURLEGS_OT_install_torch, FOURLEGS_OT_cancel_install_torch)
