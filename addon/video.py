"""Render the scene's frame range to an MP4 (H.264 through Blender's FFmpeg) or an EXR/PNG sequence.

The movie is rendered into a temporary sibling directory and renamed onto the requested path only
when every frame succeeded, so a cancelled or failed render never leaves a half-written file, and an
existing output is refused unless ``overwrite=True``. Progress: ``on_frame(done, total)`` is called
after each frame (the headless job feeds tqdm from it).
"""
from __future__ import annotations

import contextlib
import shutil
import tempfile
from pathlib import Path
from typing import Callable, Iterator, Optional, Sequence

import bpy

from . import compositor, render_engine

FORMATS = ("MP4", "PNG", "EXR")


class OutputExists(FileExistsError):
    def __init__(self, path: Path):
        super().__init__(f"{path}: already exists (pass overwrite=True / --overwrite to replace it)")
        self.path = path


def configure_output(scene: bpy.types.Scene, fmt: str, quality: str = "HIGH") -> None:
    """Set the scene's output format: 'MP4' (H.264), 'PNG' (8-bit RGB) or 'EXR' (half float, multilayer)."""
    settings = scene.render.image_settings
    has_media_type = hasattr(settings, "media_type")  # Blender 5.0
    if fmt == "MP4":
        if has_media_type:
            settings.media_type = "VIDEO"  # must precede file_format on 5.0
        settings.file_format = "FFMPEG"
        ff = scene.render.ffmpeg
        ff.format = "MPEG4"
        ff.codec = "H264"
        ff.constant_rate_factor = quality
        ff.ffmpeg_preset = "GOOD"
        ff.audio_codec = "NONE"
        settings.color_mode = "RGB"
    elif fmt == "PNG":
        if has_media_type:
            settings.media_type = "IMAGE"
        settings.file_format = "PNG"
        settings.color_mode = "RGB"
        settings.color_depth = "8"
    elif fmt == "EXR":
        if has_media_type:
            settings.media_type = "MULTI_LAYER_IMAGE"
        else:
            settings.file_format = "OPEN_EXR_MULTILAYER"
        settings.color_depth = "16"
        settings.exr_codec = "ZIP"
    else:
        raise ValueError(f"unknown output format {fmt!r} (one of {', '.join(FORMATS)})")
    scene.render.use_file_extension = True


@contextlib.contextmanager
def _frame_callbacks(on_frame: Optional[Callable[[int, int], None]], total: int) -> Iterator[None]:
    done = [0]

    def post(scene, *_):
        done[0] += 1
        if on_frame is not None:
            on_frame(done[0], total)

    bpy.app.handlers.render_write.append(post)
    try:
        yield
    finally:
        bpy.app.handlers.render_write.remove(post)


def render_animation(scene: bpy.types.Scene, output: str | Path, *, fmt: str = "MP4", overwrite: bool = False,
                     on_frame: Optional[Callable[[int, int], None]] = None) -> Path:
    """Render ``scene.frame_start..frame_end`` to ``output``.

    Args:
        output: the .mp4 file (MP4), or the directory receiving ``frame_0001.png``/``.exr`` (sequences).
        fmt: 'MP4', 'PNG' or 'EXR'.
        overwrite: replace an existing output.
        on_frame: progress callback ``(frames_done, frames_total)``.
    Returns:
        The output path.
    """
    fmt = fmt.upper()
    output = Path(bpy.path.abspath(str(output))).resolve()
    if output.exists() and not overwrite:
        raise OutputExists(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    total = scene.frame_end - scene.frame_start + 1
    tmp = Path(tempfile.mkdtemp(prefix=f".{output.name}.", suffix=".part", dir=output.parent))
    old_path = scene.render.filepath
    try:
        configure_output(scene, fmt)
        scene.render.filepath = str(tmp / ("movie_" if fmt == "MP4" else "frame_"))
        with _frame_callbacks(on_frame, total):
            result = bpy.ops.render.render(animation=True, scene=scene.name)
        if "FINISHED" not in result:
            raise RuntimeError(f"rendering stopped ({result})")
        files = sorted(p for p in tmp.iterdir() if p.is_file())
        if fmt != "MP4":
            size = _output_size(scene)
            for path in files:
                _check_complete(path, output / path.name, size)
        elif any(p.stat().st_size == 0 for p in files):
            raise _engine_api().incomplete_write_error(output, "the movie file is empty")
        if fmt == "MP4":
            movies = [p for p in files if p.suffix.lower() == ".mp4"]
            if len(movies) != 1:
                raise RuntimeError(f"expected one movie file from Blender's FFmpeg, found {[p.name for p in files]}")
            if output.exists():
                output.unlink() if output.is_file() else shutil.rmtree(output)
            movies[0].replace(output)
        else:
            if len(files) != total:
                raise RuntimeError(f"expected {total} frames, Blender wrote {len(files)}")
            if output.exists():
                output.unlink() if output.is_file() else shutil.rmtree(output)
            tmp.replace(output)
        return output
    finally:
        scene.render.filepath = old_path
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def _engine_api():
    from fourlegs_engine import api

    return api


def _output_size(scene: bpy.types.Scene) -> tuple[int, int]:
    """(width, height) in pixels of the scene's rendered images."""
    pct = scene.render.resolution_percentage / 100.0
    return int(scene.render.resolution_x * pct), int(scene.render.resolution_y * pct)


def _png_size(path: Path) -> tuple[int, int]:
    import struct

    with open(path, "rb") as fh:
        head = fh.read(24)
    return struct.unpack(">II", head[16:24])


def _check_complete(written: Path, target: Path, size: Optional[tuple[int, int]]) -> None:
    """Raise ``OSError`` naming ``target`` unless ``written`` is a complete image of ``size``.

    Blender reports success when a full disk truncated the file; ENOSPC is raised when the disk
    has too little space left for another frame, EIO otherwise.
    """
    check = size if written.suffix.lower() == ".png" else None
    problem = _engine_api().image_file_problem(written, check)
    if problem is not None:
        needed = 4 * size[0] * size[1] + (1 << 20) if size else 1 << 20
        raise _engine_api().incomplete_write_error(target, problem, needed_bytes=needed)


def movie_frame_count(path: str | Path) -> int:
    """Number of frames of a movie file, decoded with Blender's own FFmpeg (movie clip loading)."""
    clip = bpy.data.movieclips.load(str(path), check_existing=False)
    try:
        return int(clip.frame_duration)
    finally:
        bpy.data.movieclips.remove(clip)


def compositing_frames(scene: bpy.types.Scene) -> Optional[set[int]]:
    """Frames on which the compositor changes the image, or None when that is unknown (always composite).

    Known only for the add-on's own desaturation graph: it passes the image through unchanged where
    the plan's desaturation weight is 0, so those frames skip the compositor entirely.
    """
    if not scene.render.use_compositing or not compositor.has_desaturation(scene):
        return None
    plan = render_engine.plan_of(scene)
    if not plan:
        return None
    return {f for f, w in compositor.frame_weights(plan).items() if w > 0.0}


def render_frames(scene: bpy.types.Scene, frames_dir: str | Path, *,
                  on_frame: Optional[Callable[[int, int], None]] = None) -> list[Path]:
    """Render every frame of the range to ``frames_dir/frame_####.png``, skipping frames already there.

    Each frame is written to a temporary name, checked (a complete PNG of the output size) and only
    then renamed, so an interrupted run resumes at the first missing frame and a frame a full disk
    cut short is rendered again instead of reused. The compositor runs only on frames where the plan's
    desaturation is non-zero (:func:`compositing_frames`). Returns the frame files in order.
    """
    frames_dir = Path(frames_dir)
    frames_dir.mkdir(parents=True, exist_ok=True)
    frames = list(range(scene.frame_start, scene.frame_end + 1))
    old_path = scene.render.filepath
    old_compositing = scene.render.use_compositing
    composite = compositing_frames(scene)
    size = _output_size(scene)
    out = []
    try:
        configure_output(scene, "PNG")
        for i, frame in enumerate(frames):
            target = frames_dir / f"frame_{frame:04d}.png"
            if target.is_file() and _engine_api().image_file_problem(target, size) is not None:
                target.unlink()  # left by a failed write (e.g. a full disk): not a finished frame
            if not target.is_file():
                tmp = frames_dir / f".frame_{frame:04d}.part.png"
                if composite is not None:
                    scene.render.use_compositing = frame in composite
                scene.frame_set(frame)
                scene.render.filepath = str(tmp)
                result = bpy.ops.render.render(write_still=True, scene=scene.name)
                if render_engine.stats.get("cancelled"):
                    tmp.unlink(missing_ok=True)
                    raise KeyboardInterrupt
                if "FINISHED" not in result or not tmp.is_file():
                    raise RuntimeError(f"rendering frame {frame} stopped ({result})")
                try:
                    _check_complete(tmp, target, size)
                except BaseException:
                    tmp.unlink(missing_ok=True)
                    raise
                tmp.replace(target)
            out.append(target)
            if on_frame is not None:
                on_frame(i + 1, len(frames))
    finally:
        scene.render.filepath = old_path
        scene.render.use_compositing = old_compositing
    return out


def encode_mp4(frames: Sequence[Path], output: str | Path, *, fps: int, fps_base: float = 1.0,
               overwrite: bool = False) -> Path:
    """Encode PNG frames to an H.264 MP4 with Blender's FFmpeg (through a temporary sequencer scene)."""
    if not frames:
        raise ValueError("no frames to encode")
    first_size = None
    for path in frames:  # a damaged frame would reach FFmpeg (or Blender's image loader) as garbage
        problem = _engine_api().image_file_problem(path, first_size)
        if problem is not None:
            raise _engine_api().incomplete_write_error(path, problem)
        if first_size is None:
            first_size = _png_size(path)
    first = bpy.data.images.load(str(frames[0]), check_existing=False)
    width, height = first.size
    bpy.data.images.remove(first)
    encoder = bpy.data.scenes.new("4-LEGS Encode")
    try:
        editor = encoder.sequence_editor_create()
        strips = editor.strips if hasattr(editor, "strips") else editor.sequences  # 5.0 renamed it
        strip = strips.new_image(name="frames", filepath=str(frames[0]), channel=1, frame_start=1)
        for path in frames[1:]:
            strip.elements.append(Path(path).name)
        encoder.frame_start, encoder.frame_end = 1, len(frames)
        render = encoder.render
        render.resolution_x, render.resolution_y, render.resolution_percentage = width, height, 100
        render.fps, render.fps_base = int(fps), float(fps_base)
        encoder.view_settings.view_transform = "Standard"
        encoder.view_settings.look = "None"
        render.use_sequencer = True
        return render_animation(encoder, output, fmt="MP4", overwrite=overwrite)
    finally:
        bpy.data.scenes.remove(encoder)


class RenderJob:
    """Render the frame range one frame per :meth:`step`, so a modal operator can keep the UI responsive.

    Frames go to a temporary sibling directory of ``output`` (``frame_####.png``/``.exr``, each written
    under a temporary name and checked complete before it is renamed); :meth:`finish` encodes them to
    the MP4 (or moves the sequence directory onto ``output``) and :meth:`cancel` removes them, so
    neither a cancelled nor a failed render leaves anything at ``output``. The scene's output path,
    compositing switch and current frame are restored by both.
    """

    def __init__(self, scene: bpy.types.Scene, output: str | Path, *, fmt: str = "MP4", overwrite: bool = False):
        self.scene, self.fmt, self.overwrite = scene, fmt.upper(), overwrite
        if self.fmt not in FORMATS:
            raise ValueError(f"unknown output format {fmt!r} (one of {', '.join(FORMATS)})")
        self.output = Path(bpy.path.abspath(str(output))).resolve()
        if self.output.exists() and not overwrite:
            raise OutputExists(self.output)
        self.output.parent.mkdir(parents=True, exist_ok=True)
        self.frames = list(range(scene.frame_start, scene.frame_end + 1))
        self.written: list[Path] = []
        self._saved = (scene.render.filepath, scene.render.use_compositing, scene.frame_current)
        self._composite = compositing_frames(scene)
        self._size = _output_size(scene)
        self._ext = ".exr" if self.fmt == "EXR" else ".png"
        self.tmp = Path(tempfile.mkdtemp(prefix=f".{self.output.name}.", suffix=".part", dir=self.output.parent))
        configure_output(scene, "EXR" if self.fmt == "EXR" else "PNG")

    @property
    def total(self) -> int:
        return len(self.frames)

    @property
    def done(self) -> int:
        return len(self.written)

    def step(self) -> bool:
        """Render the next frame; True while frames remain. Raises (after :meth:`cancel`) on failure."""
        try:
            if self.done < self.total:
                self._render(self.frames[self.done])
            return self.done < self.total
        except BaseException:
            self.cancel()
            raise

    def _render(self, frame: int) -> None:
        scene = self.scene
        target = self.tmp / f"frame_{frame:04d}{self._ext}"
        part = self.tmp / f".frame_{frame:04d}.part{self._ext}"
        if self._composite is not None:
            scene.render.use_compositing = frame in self._composite
        scene.frame_set(frame)
        scene.render.filepath = str(part)
        result = bpy.ops.render.render(write_still=True, scene=scene.name)
        if render_engine.stats.get("cancelled"):
            raise KeyboardInterrupt
        if "FINISHED" not in result or not part.is_file():
            raise RuntimeError(f"rendering frame {frame} stopped ({result})")
        _check_complete(part, self.output / target.name if self.fmt != "MP4" else self.output,
                        self._size if self.fmt != "EXR" else None)
        part.replace(target)
        self.written.append(target)

    def finish(self) -> Path:
        """Write the output from the rendered frames (every frame must be done); returns its path."""
        if self.done < self.total:
            raise RuntimeError(f"only {self.done} of {self.total} frames rendered")
        try:
            self._restore()
            if self.fmt == "MP4":
                encode_mp4(self.written, self.output, fps=self.scene.render.fps,
                           fps_base=self.scene.render.fps_base, overwrite=self.overwrite)
            else:
                if self.output.exists():
                    self.output.unlink() if self.output.is_file() else shutil.rmtree(self.output)
                self.tmp.replace(self.output)
            return self.output
        finally:
            shutil.rmtree(self.tmp, ignore_errors=True)

    def cancel(self) -> None:
        """Stop: remove the frames rendered so far and restore the scene's settings."""
        self._restore()
        shutil.rmtree(self.tmp, ignore_errors=True)

    def _restore(self) -> None:
        filepath, compositing, frame = self._saved
        self.scene.render.filepath = filepath
        self.scene.render.use_compositing = compositing
        configure_output(self.scene, self.fmt)  # the scene's output is the video it made
        if self.scene.frame_current != frame:
            self.scene.frame_set(frame)
