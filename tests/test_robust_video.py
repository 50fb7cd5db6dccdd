"""Issue #24, item 2: a frame counts as done only when it is a complete image. A full disk (Blender
writes 0-byte or cut-short files and still reports success) is reported as "no space left on device
while writing <frame>", never renamed to its final name, and never reused by the next run."""
from __future__ import annotations

import errno
import shutil
import struct
import zlib
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from fourlegs_engine.errors import describe_environment_error
from fourlegs_engine.fileio import image_file_problem, incomplete_write_error


def png_bytes(width: int, height: int, value: int = 128) -> bytes:
    """A complete 8-bit RGB PNG."""
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))
    rows = b"".join(b"\x00" + bytes([value]) * (3 * width) for _ in range(height))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b""))


def test_image_file_problem_tells_complete_from_cut_short(tmp_path):
    good = png_bytes(8, 4)
    path = tmp_path / "f.png"
    path.write_bytes(good)
    assert image_file_problem(path) is None and image_file_problem(path, (8, 4)) is None
    assert "expected 9x4" in image_file_problem(path, (9, 4))
    for cut in (0, 8, 20, len(good) - 12, len(good) - 1):
        path.write_bytes(good[:cut])
        assert image_file_problem(path) is not None, cut
    path.write_bytes(good[:40] + bytes([good[40] ^ 1]) + good[41:])
    assert "damaged" in image_file_problem(path)
    # the real thing: a PNG matplotlib wrote
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    plt.imsave(tmp_path / "m.png", np.zeros((5, 7, 3)))
    assert image_file_problem(tmp_path / "m.png", (7, 5)) is None


def test_an_incomplete_write_on_a_full_disk_says_so(tmp_path, monkeypatch):
    target = tmp_path / "frames" / "frame_0001.png"
    monkeypatch.setattr(shutil, "disk_usage", lambda p: SimpleNamespace(total=1, used=1, free=0))
    exc = incomplete_write_error(target, "empty (0 bytes)")
    assert exc.errno == errno.ENOSPC
    assert describe_environment_error(exc).startswith(f"no space left on device while writing {target}")
    monkeypatch.undo()
    exc = incomplete_write_error(target, "empty (0 bytes)")
    assert exc.errno == errno.EIO and "written incomplete" in describe_environment_error(exc)


# ------------------------------------------------------------------- through Blender's scene
bpy = pytest.importorskip("bpy", reason="Blender's bpy module is not installed")


@pytest.fixture()
def video(monkeypatch):
    from fourlegs_addon import video as video_module

    scene = bpy.data.scenes.new("robust-frames")
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 8, 4, 100
    scene.frame_start, scene.frame_end = 1, 3
    scene.render.use_compositing = False
    calls = []

    def install(writer):
        def render(write_still=False, scene=None, animation=False):
            calls.append(bpy.data.scenes[scene].frame_current)
            writer(Path(bpy.data.scenes[scene].render.filepath))
            return {"FINISHED"}
        fake_bpy = SimpleNamespace(ops=SimpleNamespace(render=SimpleNamespace(render=render)), data=bpy.data,
                                   app=bpy.app, path=bpy.path, types=bpy.types)
        monkeypatch.setattr(video_module, "bpy", fake_bpy)

    yield video_module, scene, install, calls
    bpy.data.scenes.remove(scene)


def test_a_full_disk_stops_with_enospc_and_leaves_no_final_frame(video, tmp_path, monkeypatch):
    video_module, scene, install, calls = video
    install(lambda path: path.write_bytes(b""))          # what Blender leaves on a full disk
    monkeypatch.setattr(shutil, "disk_usage", lambda p: SimpleNamespace(total=1, used=1, free=0))
    frames = tmp_path / "frames"
    with pytest.raises(OSError) as exc:
        video_module.render_frames(scene, frames)
    assert exc.value.errno == errno.ENOSPC and exc.value.filename == str(frames / "frame_0001.png")
    assert describe_environment_error(exc.value).startswith(
        f"no space left on device while writing {frames / 'frame_0001.png'}")
    assert list(frames.iterdir()) == []                   # neither the final name nor the temporary


def test_an_existing_empty_or_cut_frame_is_rendered_again(video, tmp_path):
    video_module, scene, install, calls = video
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "frame_0001.png").write_bytes(b"")                    # an earlier run on a full disk
    (frames / "frame_0002.png").write_bytes(png_bytes(8, 4)[:30])   # cut short
    (frames / "frame_0003.png").write_bytes(png_bytes(8, 4, 7))     # finished: reused
    install(lambda path: path.write_bytes(png_bytes(8, 4)))
    out = video_module.render_frames(scene, frames)
    assert calls == [1, 2]
    assert [image_file_problem(p, (8, 4)) for p in out] == [None, None, None]
    assert (frames / "frame_0003.png").read_bytes() == png_bytes(8, 4, 7)


def test_a_frame_of_the_wrong_size_is_not_accepted(video, tmp_path):
    video_module, scene, install, calls = video
    install(lambda path: path.write_bytes(png_bytes(5, 4)))
    with pytest.raises(OSError, match="expected 8x4"):
        video_module.render_frames(scene, tmp_path / "frames")
    assert not any((tmp_path / "frames").iterdir())


def test_encode_refuses_damaged_frames_before_blender_loads_them(tmp_path):
    from fourlegs_addon import video as video_module

    (tmp_path / "frame_0001.png").write_bytes(png_bytes(8, 4))
    (tmp_path / "frame_0002.png").write_bytes(b"")
    with pytest.raises(OSError, match="frame_0002.png"):
        video_module.encode_mp4([tmp_path / "frame_0001.png", tmp_path / "frame_0002.png"],
                                tmp_path / "out.mp4", fps=24)
    assert not (tmp_path / "out.mp4").exists()
