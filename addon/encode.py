"""Encode PNG frames to an H.264 MP4 with Blender's FFmpeg, in this process or in a child process.

Blender reaches its movie writer only by rendering a scene's animation (here a sequencer scene holding
the frames as one image strip), and that render blocks the process running it. Render Video therefore
runs it in a child (:class:`EncodeProcess`): Blender itself (``blender -b --factory-startup --python
encode.py -- ...``), or, where Blender is the ``bpy`` module, the same Python (``python encode.py ...``).
The child runs this file as a script, so it imports nothing but ``bpy`` and the standard library.
It prints one ``ENCODED_LINE`` per frame written; the parent reads them for progress and can stop it
at any time. The movie is written inside the directory it is given; the caller renames it into place.
"""
from __future__ import annotations

import sys
from pathlib import Path

if __name__ == "__main__":  # run as a script: the add-on's folder must not shadow anything bpy imports
    sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

import atexit
import json
import subprocess
import threading
from typing import Optional, Sequence

import bpy

#: what the child prints after each frame it wrote to the movie
ENCODED_LINE = "FOURLEGS-ENCODED"
#: the movie file's name stem inside the output directory (Blender appends the frame range)
MOVIE_STEM = "movie_"


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
        raise ValueError(f"unknown output format {fmt!r} (one of MP4, PNG, EXR)")
    scene.render.use_file_extension = True


def sequencer_scene(frames: Sequence[str | Path], *, fps: int, fps_base: float = 1.0) -> bpy.types.Scene:
    """A new scene whose sequencer plays ``frames`` (PNG files of one size, in one directory) from frame
    1, with the frames' resolution, ``fps`` / ``fps_base``, a neutral view transform and MP4 output.
    The caller removes it (``bpy.data.scenes.remove``)."""
    first = bpy.data.images.load(str(frames[0]), check_existing=False)
    width, height = first.size
    bpy.data.images.remove(first)
    encoder = bpy.data.scenes.new("4-LEGS Encode")
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
    configure_output(encoder, "MP4")
    return encoder


def child_command(frames_json: Path, out_dir: Path, fps: int, fps_base: float) -> list[str]:
    """The command line of the encoding child: Blender in background mode, or this Python for bpy."""
    args = [str(frames_json), str(out_dir), str(int(fps)), repr(float(fps_base))]
    binary = bpy.app.binary_path
    if binary and Path(binary).is_file():
        return [binary, "--background", "--factory-startup", "--python-exit-code", "1",
                "--python", str(Path(__file__).resolve()), "--", *args]
    return [sys.executable, str(Path(__file__).resolve()), *args]


class EncodeProcess:
    """``frames`` encoded into ``out_dir/movie_*.mp4`` by a child process started at construction.

    :meth:`poll` says whether it is still running (without waiting), :attr:`encoded` how many frames it
    has written, :meth:`wait` waits for it, :meth:`cancel` stops it. ``out_dir`` is created and receives
    ``frames.json`` (the frame list the child reads), ``encode.log`` (the child's stderr) and the movie.
    """

    def __init__(self, frames: Sequence[str | Path], out_dir: str | Path, *, fps: int, fps_base: float = 1.0):
        if not frames:
            raise ValueError("no frames to encode")
        self.total = len(frames)
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        frames_json = self.out_dir / "frames.json"
        frames_json.write_text(json.dumps([str(Path(f).resolve()) for f in frames]), encoding="utf-8")
        self.log_path = self.out_dir / "encode.log"
        self.encoded = 0
        with open(self.log_path, "wb") as log:
            self._proc = subprocess.Popen(child_command(frames_json, self.out_dir, fps, fps_base),
                                          stdout=subprocess.PIPE, stderr=log, stdin=subprocess.DEVNULL)
        self._reader = threading.Thread(target=self._read, name="fourlegs-encode-progress", daemon=True)
        self._reader.start()
        atexit.register(self.cancel)  # Blender quitting mid-encode must not leave the child running

    def _read(self) -> None:
        for raw in self._proc.stdout:
            if raw.startswith(ENCODED_LINE.encode()):
                self.encoded += 1

    def poll(self) -> bool:
        """True while the child is running."""
        return self._proc.poll() is None

    def wait(self, timeout: Optional[float] = None) -> None:
        self._proc.wait(timeout)
        self._close()

    def _close(self) -> None:
        """After the child exited: let the reader take its last lines, then close the pipe."""
        self._reader.join(5.0)
        if not self._reader.is_alive():
            self._proc.stdout.close()

    def result(self) -> Path:
        """The movie the finished child wrote; RuntimeError (with the child's last error line) if it failed."""
        self.wait()
        atexit.unregister(self.cancel)
        movies = sorted(self.out_dir.glob(f"{MOVIE_STEM}*.mp4"))
        if self._proc.returncode != 0 or len(movies) != 1:
            log = self.log_path.read_text(encoding="utf-8", errors="replace").strip().splitlines()
            why = next((line for line in reversed(log) if line.strip()), f"exit status {self._proc.returncode}")
            raise RuntimeError(f"encoding the MP4 failed: {why}")
        return movies[0]

    def cancel(self) -> None:
        """Stop the child (if it still runs) and wait for it to exit."""
        atexit.unregister(self.cancel)
        if self._proc.poll() is None:
            self._proc.terminate()
            try:
                self._proc.wait(10)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()
        self._close()


def main(argv: Sequence[str]) -> None:
    """The child: ``FRAMES_JSON OUT_DIR FPS FPS_BASE`` -> ``OUT_DIR/movie_*.mp4``."""
    frames_json, out_dir, fps, fps_base = argv
    frames = json.loads(Path(frames_json).read_text(encoding="utf-8"))
    scene = sequencer_scene(frames, fps=int(fps), fps_base=float(fps_base))
    scene.render.filepath = str(Path(out_dir) / MOVIE_STEM)

    def written(*_):
        print(ENCODED_LINE, flush=True)

    bpy.app.handlers.render_write.append(written)
    result = bpy.ops.render.render(animation=True, scene=scene.name)
    if "FINISHED" not in result:
        raise SystemExit(f"rendering the sequencer stopped ({result})")


if __name__ == "__main__":
    main(sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:])
