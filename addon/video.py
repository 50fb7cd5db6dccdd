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
from .encode import EncodeProcess, configure_output, sequencer_scene

FORMATS = ("MP4", "PNG", "EXR")


class OutputExists(FileExistsError):
    def __init__(self, path: Path):
        super().__init__(f"{path}: already exists (pass overwrite=True / --overwrite to replace it)")
        self.path = path


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

    Known only for the add-on's own blur/desaturation graph: it passes the image through unchanged where
    the plan's weights are 0, so those frames skip the compositor entirely.
    """
    if not scene.render.use_compositing or not compositor.has_masking(scene):
        return None
    plan = render_engine.plan_of(scene)
    if not plan:
        return None
    return {f for f, w in compositor.mask_weights(plan).items() if w > 0.0}


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


def check_frames(frames: Sequence[Path]) -> None:
    """Raise an incomplete-write error naming the first frame that is not a complete PNG of the first
    one's size (a damaged frame would reach FFmpeg, or Blender's image loader, as garbage)."""
    first_size = None
    for path in frames:
        problem = _engine_api().image_file_problem(path, first_size)
        if problem is not None:
            raise _engine_api().incomplete_write_error(path, problem)
        if first_size is None:
            first_size = _png_size(path)


def encode_mp4(frames: Sequence[Path], output: str | Path, *, fps: int, fps_base: float = 1.0,
               overwrite: bool = False) -> Path:
    """Encode PNG frames to an H.264 MP4 with Blender's FFmpeg (through a temporary sequencer scene), in
    this process (it blocks: Render Video encodes in a child process instead, see :class:`RenderJob`)."""
    if not frames:
        raise ValueError("no frames to encode")
    check_frames(frames)
    encoder = sequencer_scene(frames, fps=fps, fps_base=fps_base)
    try:
        return render_animation(encoder, output, fmt="MP4", overwrite=overwrite)
    finally:
        bpy.data.scenes.remove(encoder)


class RenderJob:
    """Render the frame range one frame per :meth:`step`, then encode the MP4 in a child process while
    :meth:`step` only looks whether it is done, so a modal operator keeps the UI responsive throughout.

    Frames go to a temporary sibling directory of ``output`` (``frame_####.png``/``.exr``, each written
    under a temporary name and checked complete before it is renamed). For an MP4, once every frame is
    rendered the scene's settings are restored and :class:`~.encode.EncodeProcess` encodes them into
    that directory; :meth:`finish` checks the movie (one file, every frame in it) and renames it onto
    ``output`` (a sequence: the directory itself). :meth:`cancel` stops the encoder and removes the
    directory, so neither a cancelled nor a failed render leaves anything at ``output``. The scene's
    output path, compositing switch and current frame are restored by both.
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
        self.encoder: Optional[EncodeProcess] = None
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

    @property
    def encoding(self) -> bool:
        """True while the MP4 encoder runs."""
        return self.encoder is not None and self.encoder.poll()

    def step(self) -> bool:
        """Render the next frame, or (MP4, every frame rendered) start the encoder, or look whether it is
        done; True while work remains. Raises (after :meth:`cancel`) on failure."""
        try:
            if self.done < self.total:
                self._render(self.frames[self.done])
                return self.done < self.total or self.fmt == "MP4"
            if self.fmt != "MP4":
                return False
            if self.encoder is None:
                self._restore()
                check_frames(self.written)
                self.encoder = EncodeProcess(self.written, self.tmp / "movie", fps=self.scene.render.fps,
                                             fps_base=self.scene.render.fps_base)
            return self.encoder.poll()
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
        """Write the output from the rendered frames (every frame must be done; an MP4 encoder still
        running is waited for); returns its path."""
        if self.done < self.total:
            raise RuntimeError(f"only {self.done} of {self.total} frames rendered")
        try:
            self._restore()
            if self.fmt == "MP4":
                while self.step():
                    self.encoder.wait()
                movie = self.encoder.result()
                if movie.stat().st_size == 0:
                    raise _engine_api().incomplete_write_error(self.output, "the movie file is empty")
                frames = movie_frame_count(movie)
                if frames != self.total:
                    raise _engine_api().incomplete_write_error(
                        self.output, f"the movie holds {frames} of {self.total} frames")
                if self.output.exists():
                    self.output.unlink() if self.output.is_file() else shutil.rmtree(self.output)
                movie.replace(self.output)
            else:
                if self.output.exists():
                    self.output.unlink() if self.output.is_file() else shutil.rmtree(self.output)
                self.tmp.replace(self.output)
            return self.output
        except BaseException:
            self.cancel()
            raise
        finally:
            shutil.rmtree(self.tmp, ignore_errors=True)

    def cancel(self) -> None:
        """Stop: end the encoder, remove the frames rendered so far and restore the scene's settings."""
        if self.encoder is not None:
            self.encoder.cancel()
        self._restore()
        shutil.rmtree(self.tmp, ignore_errors=True)

    def _restore(self) -> None:
        filepath, compositing, frame = self._saved
        self.scene.render.filepath = filepath
        self.scene.render.use_compositing = compositing
        configure_output(self.scene, self.fmt)  # the scene's output is the video it made
        if self.scene.frame_current != frame:
            self.scene.frame_set(frame)
