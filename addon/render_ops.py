"""Render Video: the timeline one frame per timer tick, then the MP4 encoded in a background process."""
from __future__ import annotations

import threading
from typing import Optional

import bpy

from . import jobs, render_engine, retime, video
from .messages import error_line, missing_for


def output_path(scene) -> str:
    """The panel's output as an absolute path: ``//`` is the .blend's folder; an unsaved file has none,
    so a relative output is refused rather than written into whatever the working directory is."""
    path = scene.fourlegs.output_path
    if path.startswith("//") and not bpy.data.filepath:
        raise ValueError(f"the output {path} is relative to the .blend, which is not saved yet: save the file "
                         "or choose an absolute output path")
    return bpy.path.abspath(path)


class FOURLEGS_OT_render_video(bpy.types.Operator):
    """Render the timeline through the 4-LEGS Splats engine and the compositor to a video or image sequence
    (one frame per timer tick, the MP4 encoded in a background process, so the UI stays responsive; Esc
    or Cancel stops it)"""

    bl_idname = "fourlegs.render_video"
    bl_label = "Render Video"
    bl_options = {"REGISTER"}

    _timer = None
    _job: Optional[video.RenderJob] = None
    _ticket: Optional[jobs.Cancellable] = None
    _cancel = False
    _error: Optional[str] = None

    @classmethod
    def poll(cls, context):
        return not context.scene.fourlegs.running

    def execute(self, context):
        return self.invoke(context, None)

    def invoke(self, context, event):
        props = context.scene.fourlegs
        retime.sync(context.scene)  # a shot marker moved since the last frame change
        if render_engine.plan_of(context.scene) is None:
            self.report({"ERROR"}, "4-LEGS Render Video: no highlight in this scene; run Generate Highlight first")
            return {"CANCELLED"}
        problem = missing_for(("torch",)) if context.scene.render.engine == render_engine.ENGINE_ID else None
        try:
            if problem is None:
                self._job = video.RenderJob(context.scene, output_path(context.scene), fmt=props.output_format,
                                            overwrite=props.overwrite)
        except video.OutputExists as exc:
            problem = f"{exc.path} already exists; tick Overwrite (4-LEGS panel, Render) to replace it"
        except Exception as exc:
            problem = error_line(exc)
        if problem is not None:
            props.status = f"error: {problem}"
            self.report({"ERROR"}, f"4-LEGS Render Video: {problem}")
            return {"CANCELLED"}
        self._ticket = jobs.track(jobs.Cancellable())
        props.running, props.progress, props.status = True, 0.0, f"rendering frame 1/{self._job.total}"
        if jobs.has_event_loop(context):
            wm = context.window_manager
            wm.progress_begin(0, self._job.total)
            self._timer = wm.event_timer_add(0.01, window=context.window)
            wm.modal_handler_add(self)
            return {"RUNNING_MODAL"}
        # background mode has no event loop: render every frame here
        while self._advance(context):
            if self._job.encoding:
                threading.Event().wait(0.05)
        return self._end(context)

    def _advance(self, context) -> bool:
        """Render one frame; False when the job is over (done, failed or cancelled)."""
        props = context.scene.fourlegs
        job = self._job
        if self._ticket.cancelled:  # the Cancel button
            self._cancel = True
            return False
        try:
            more = job.step()
        except BaseException as exc:
            self._error = "cancelled" if isinstance(exc, KeyboardInterrupt) else error_line(exc)
            return False
        if job.encoder is None:
            props.progress = job.done / job.total
            props.status = f"rendering frame {min(job.done + 1, job.total)}/{job.total}" if more else "writing"
        else:  # the MP4 encodes in a child process: the last tenth of the bar
            props.progress = 0.9 + 0.1 * job.encoder.encoded / job.total
            props.status = f"encoding the MP4: frame {job.encoder.encoded}/{job.total}"
        if self._timer is not None:
            context.window_manager.progress_update(job.done)
        return more

    def modal(self, context, event):
        if event.type == "ESC":
            self._cancel = True
            return self._end(context)
        if event.type == "TIMER":
            if not self._advance(context):
                return self._end(context)
            jobs.redraw(context, ("VIEW_3D", "PROPERTIES"))
        return {"PASS_THROUGH"}

    def _end(self, context):
        props = context.scene.fourlegs
        job = self._job
        if self._timer is not None:
            context.window_manager.event_timer_remove(self._timer)
            context.window_manager.progress_end()
            self._timer = None
        jobs.untrack(self._ticket)
        props.running = False
        if self._cancel or self._error == "cancelled":
            job.cancel()
            props.status = "render cancelled"
            self.report({"WARNING"}, f"4-LEGS Render Video cancelled after {job.done} of {job.total} frames")
            return {"CANCELLED"}
        if self._error is not None:
            props.status = f"error: {self._error}"
            self.report({"ERROR"}, f"4-LEGS Render Video: {self._error}")
            return {"CANCELLED"}
        try:
            out = job.finish()
        except Exception as exc:
            props.status = f"error: {error_line(exc)}"
            self.report({"ERROR"}, f"4-LEGS Render Video: {error_line(exc)}")
            return {"CANCELLED"}
        props.progress, props.status = 1.0, "video written"
        self.report({"INFO"}, f"wrote {out}")
        return {"FINISHED"}


classes = (FOURLEGS_OT_render_video,)
