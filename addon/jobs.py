"""The add-on's one runner for long work: a worker thread polled by a modal operator.

A :class:`Job` holds the state the worker and the UI share (plain attributes, no bpy): ``progress``,
``stage``, ``cancelled``, ``done`` and the one-line ``error``. :class:`JobOperator` starts it in a
worker thread; with a UI a timer polls it (status, progress bar, redraw) and Esc or the panel's Cancel
button asks it to stop, without one (``blender -b``, the bpy module) the operator waits for it. Blender
data is touched only on the main thread, when the operator collects the result (``finish_job``).

Everything running (worker jobs, and main-thread work such as Render Video that registers a
:class:`Cancellable`) is listed by :func:`active`; :func:`cancel_all` is the Cancel button.
"""
from __future__ import annotations

import threading
import traceback
from typing import Optional

import bpy

from .messages import error_line

POLL_SECONDS = 0.2


def interactive() -> bool:
    """Whether Blender runs with a UI (operators must not block it); False for ``blender -b`` and bpy."""
    return not bpy.app.background


def has_event_loop(context) -> bool:
    """Whether a modal operator gets timer events here (a window and no background mode)."""
    return context.window is not None and not bpy.app.background


class Cancellable:
    """Something running that the Cancel button can stop: it looks at ``cancelled`` between its steps."""

    cancelled = False


class Job(Cancellable):
    """A unit of background work; subclasses implement :meth:`work` (no bpy in it)."""

    def __init__(self) -> None:
        self.progress, self.stage = 0.0, "starting"
        self.cancelled = self.done = False
        self.error: Optional[str] = None

    def work(self) -> None:
        raise NotImplementedError

    def run(self) -> None:
        """The worker thread's body: :meth:`work`, its error as one line (none once cancelled), then ``done``."""
        try:
            self.work()
        except Exception as exc:  # reported on the main thread
            if not self.cancelled:
                self.error = error_line(exc)
                traceback.print_exc()
        finally:
            self.done = True


_ACTIVE: list[Cancellable] = []


def track(item: Cancellable) -> Cancellable:
    """List ``item`` as running (the Cancel button reaches it) until :func:`untrack`."""
    _ACTIVE.append(item)
    return item


def untrack(item: Cancellable) -> None:
    if item in _ACTIVE:
        _ACTIVE.remove(item)


def active() -> list[Cancellable]:
    """Everything running now, oldest first."""
    return list(_ACTIVE)


def cancel_all() -> None:
    for item in _ACTIVE:
        item.cancelled = True


def redraw(context, area_types: tuple[str, ...] = ("VIEW_3D",)) -> None:
    for area in context.screen.areas if context.screen else []:
        if area.type in area_types:
            area.tag_redraw()


class JobOperator:
    """Mixin of the operators that run a :class:`Job`: :meth:`start_job` from ``invoke``/``execute``;
    subclasses implement ``finish_job(context)`` (the job ended without error or cancel) and may
    override :meth:`job_cancelled`. ``job_label`` names the operator in messages."""

    job_label = "job"
    _timer = None
    _job: Optional[Job] = None

    def start_job(self, context, job: Job, thread_name: str, status: str) -> set[str]:
        """Run ``job`` in a worker thread: modal with a timer in the UI, waited for in background mode."""
        self._job = track(job)
        threading.Thread(target=job.run, name=thread_name, daemon=True).start()
        props = context.scene.fourlegs
        props.running, props.progress, props.status = True, 0.0, status
        if has_event_loop(context):
            wm = context.window_manager
            self._timer = wm.event_timer_add(POLL_SECONDS, window=context.window)
            wm.modal_handler_add(self)
            return {"RUNNING_MODAL"}
        while not job.done:  # background mode has no event loop
            threading.Event().wait(0.05)
        return self._job_ended(context)

    def refuse(self, context, problem: str) -> set[str]:
        """Do not start: ``problem`` (one line) in the panel's status and the operator's report."""
        context.scene.fourlegs.status = f"error: {problem}"
        self.report({"ERROR"}, f"4-LEGS {self.job_label}: {problem}")
        return {"CANCELLED"}

    def modal(self, context, event):
        job = self._job
        if event.type == "ESC":
            job.cancelled = True
        if event.type == "TIMER":
            props = context.scene.fourlegs
            props.progress = job.progress
            props.status = "cancelling" if job.cancelled and not job.done else job.stage
            redraw(context)
            if job.done:
                return self._job_ended(context)
        return {"PASS_THROUGH"}

    def _job_ended(self, context) -> set[str]:
        if self._timer is not None:
            context.window_manager.event_timer_remove(self._timer)
            self._timer = None
        untrack(self._job)
        props = context.scene.fourlegs
        props.running = False
        if self._job.cancelled:
            return self.job_cancelled(context)
        if self._job.error is not None:
            props.status = f"error: {self._job.error}"
            self.report({"ERROR"}, f"4-LEGS {self.job_label}: {self._job.error}")
            return {"CANCELLED"}
        return self.finish_job(context)

    def job_cancelled(self, context) -> set[str]:
        context.scene.fourlegs.status = "cancelled"
        self.report({"WARNING"}, f"4-LEGS {self.job_label} cancelled")
        return {"CANCELLED"}

    def finish_job(self, context) -> set[str]:
        raise NotImplementedError


class FOURLEGS_OT_cancel_query(bpy.types.Operator):
    """Stop what is running (query, language field, scene ranking, render); finished steps are kept"""

    bl_idname = "fourlegs.cancel_query"
    bl_label = "Cancel"

    def execute(self, context):
        cancel_all()
        return {"FINISHED"}


classes = (FOURLEGS_OT_cancel_query,)
