"""Issue #30, the remaining tracebacks: damaged files and machine faults are one line naming the file (and
the field), never a traceback, and a full disk leaves nothing printed after that line."""
from __future__ import annotations

import errno
import json
import shutil
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch

from _language_helpers import micro_bundle, one_thread  # noqa: F401 (one_thread: autouse fixture)
from fourlegs_engine.commands.main import main
from fourlegs_engine.errors import InputError

AE_ARGS = ["--epochs", "2", "--samples", "2048", "--ae-batch-size", "256"]
QUERY = ["ball flying in the air", "--no-spatial"]


@pytest.fixture(scope="module")
def distilled(tmp_path_factory) -> Path:
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    path = micro_bundle(tmp_path_factory.mktemp("damaged") / "micro", T=3)
    assert main(["extract", str(path), "--no-progress"]) == 0
    assert main(["train-ae", str(path), *AE_ARGS]) == 0
    assert main(["distill", str(path), "--no-progress"]) == 0
    torch.set_num_threads(old)
    return path


def _one_line(capsys, argv: list[str], code: int = 2) -> str:
    assert main(argv) == code
    err = capsys.readouterr().err
    assert "Traceback" not in err and "Exception ignored" not in err, err
    return err.strip().splitlines()[-1]


def _edit_meta(path: Path, edit) -> None:
    meta = json.loads((path / "scene.json").read_text())
    edit(meta)
    (path / "scene.json").write_text(json.dumps(meta))


# --------------------------------------------------------------------------- damaged scene.json
@pytest.mark.parametrize("key, value", [("encoder", 5), ("canonical_phrases", "x"), ("canonical_phrases", [1, 2]),
                                        ("latent_dim", "x"), ("mode", 3), ("latent_dim", True)])
def test_language_fields_of_the_wrong_type_are_one_line(distilled, tmp_path, capsys, key, value):
    path = Path(shutil.copytree(distilled, tmp_path / "b"))
    _edit_meta(path, lambda m: m["language"].__setitem__(key, value))
    line = _one_line(capsys, ["query", str(path), *QUERY])
    assert f"scene.json: language.{key}" in line, line


def test_a_scene_json_nested_200k_deep_is_one_line(distilled, tmp_path, capsys):
    path = Path(shutil.copytree(distilled, tmp_path / "b"))
    (path / "scene.json").write_text("[" * 200_000 + "]" * 200_000)
    assert "scene.json: nested too deeply" in _one_line(capsys, ["info", str(path)])


def test_latents_of_strings_are_one_line(distilled, tmp_path, capsys):
    path = Path(shutil.copytree(distilled, tmp_path / "b"))
    np.save(path / "language" / "latents.npy", np.array(["a", "b"]))
    assert "latents.npy" in _one_line(capsys, ["query", str(path), *QUERY])


# -------------------------------------------------------------------------- damaged checkpoints
def test_an_autoencoder_checkpoint_with_the_right_hash_and_a_wrong_body_is_one_line(distilled, tmp_path, capsys):
    from fourlegs_engine.language import autoencoder

    path = Path(shutil.copytree(distilled, tmp_path / "b"))
    assert autoencoder.train_autoencoder.__name__  # the real trainer
    assert main(["train-ae", str(path), *AE_ARGS, "--seed", "5", "--overwrite"]) == 0
    capsys.readouterr()
    report = json.loads((path / "language" / "autoencoder.json").read_text())
    torch.save({"config_hash": report["config_hash"], "epoch": 1, "model": {"net.0.weight": torch.zeros(2, 2)},
                "optimizer": {}, "history": [1.0]}, path / "language" / "autoencoder.ckpt.pt")
    line = _one_line(capsys, ["train-ae", str(path), *AE_ARGS, "--seed", "5", "--overwrite"])
    assert "autoencoder.ckpt.pt: damaged checkpoint" in line, line


@pytest.mark.parametrize("content", ["[1, 2]", "\"text\""])
def test_a_fit_history_that_is_not_an_object_is_one_line(tmp_path, content):
    from fourlegs_engine.fit import fitter

    work = tmp_path / "work"
    work.mkdir()
    (work / "history.json").write_text(content)
    with pytest.raises(InputError, match=r"history\.json: must be a JSON object"):
        fitter._run(None, range(0, 2), [], [], (8, 8), None, "cpu", 1.0, work, lambda ev: None)


@pytest.mark.parametrize("damage", ["empty", "truncated", "missing-key", "nan"])
def test_a_damaged_fit_checkpoint_is_one_line(tmp_path, damage):
    from fourlegs_engine.fit.fitter import _load_npz, _save_npz

    path = tmp_path / "t000000.npz"
    _save_npz(path, means=np.zeros((4, 3), np.float32), rotations=np.zeros((4, 4), np.float32))
    if damage == "empty":
        path.write_bytes(b"")
    elif damage == "truncated":
        path.write_bytes(path.read_bytes()[:40])
    elif damage == "missing-key":
        _save_npz(path, means=np.zeros((4, 3), np.float32))
    else:
        _save_npz(path, means=np.full((4, 3), np.nan, np.float32), rotations=np.zeros((4, 4), np.float32))
    with pytest.raises(InputError, match=r"t000000\.npz: (unreadable|damaged) checkpoint"):
        _load_npz(path)


# ---------------------------------------------------------------------------------- huge images
def _png_header_only(width: int, height: int) -> bytes:
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 1, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"")) + chunk(b"IEND", b""))


def test_a_60000_pixel_png_is_one_line_as_a_mask_and_as_a_frame(tmp_path):
    from fourlegs_engine.fit.dataset import _open_image
    from fourlegs_engine.language.annotations import read_mask

    path = tmp_path / "000000.png"
    path.write_bytes(_png_header_only(60000, 60000))
    with pytest.raises(InputError, match=r"000000\.png: masks: is too large to be a mask"):
        read_mask(path)
    with pytest.raises(InputError, match=r"000000\.png: is too large to be a frame"):
        _open_image(path)


def test_a_ply_claiming_10_to_the_12_vertices_names_the_file(tmp_path):
    from fourlegs_engine.scene.ply import read_ply_splats

    path = tmp_path / "big.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 1000000000000\nproperty float x\nproperty float y\n"
                    "property float z\nend_header\n0 0 0\n")
    with pytest.raises(InputError, match=r"big\.ply: vertex: its header claims more vertices than fit in memory"):
        read_ply_splats(path)


# ---------------------------------------------------------------------------------- a full disk
def _disk_full(monkeypatch) -> None:
    usage = shutil.disk_usage("/")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage._replace(free=0))


def test_a_full_disk_during_train_ae_is_one_line_naming_the_file(distilled, tmp_path, capsys, monkeypatch):
    path = Path(shutil.copytree(distilled, tmp_path / "b"))
    before = (path / "language" / "decoder.pt").read_bytes()
    _disk_full(monkeypatch)

    def full_disk_save(obj, f, *args, **kwargs):
        raise RuntimeError("[enforce fail at inline_container.cc:664] . unexpected pos 64 vs 0")

    monkeypatch.setattr(torch, "save", full_disk_save)
    line = _one_line(capsys, ["train-ae", str(path), *AE_ARGS, "--seed", "7", "--overwrite"], code=1)
    assert line.startswith("fourlegs: error: no space left on device while writing") and ".pt" in line, line
    assert (path / "language" / "decoder.pt").read_bytes() == before
    assert [p for p in (path / "language").iterdir() if ".part" in p.name] == []


def test_a_full_disk_during_a_numpy_write_names_the_file(tmp_path, monkeypatch, capsys):
    from fourlegs_engine.errors import describe_environment_error
    from fourlegs_engine.fileio import save_npy_atomic

    _disk_full(monkeypatch)

    def short_write(fh, arr, **kw):
        raise OSError("1812480 requested and 985024 written")

    monkeypatch.setattr(np, "save", short_write)
    with pytest.raises(OSError) as exc:
        save_npy_atomic(tmp_path / "t000001.npy", np.zeros(10))
    assert exc.value.errno == errno.ENOSPC
    assert describe_environment_error(exc.value) == (f"no space left on device while writing {tmp_path}/t000001.npy; "
                                                     "free some space and run the same command again")
    assert list(tmp_path.iterdir()) == []


def test_a_full_disk_during_an_npz_write_prints_nothing_after_the_error(tmp_path, monkeypatch, capfd):
    import gc
    import sys

    from fourlegs_engine.fileio import save_npz_atomic

    ignored = []
    monkeypatch.setattr(sys, "unraisablehook", ignored.append)  # what Python would print as "Exception ignored"
    _disk_full(monkeypatch)
    real_write = np.lib.format.write_array

    def full(fp, array, *args, **kwargs):
        real_write(fp, array[:1], *args, **kwargs)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(np.lib.format, "write_array", full)
    with pytest.raises(OSError) as exc:
        save_npz_atomic(tmp_path / "static.npz", a=np.zeros(100), b=np.ones(100))
    assert exc.value.errno == errno.ENOSPC and exc.value.filename == str(tmp_path / "static.npz")
    del exc
    gc.collect()
    assert ignored == [] and "Exception ignored" not in capfd.readouterr().err
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------ numeric edges, wheels
def test_unproject_with_infinite_depth_is_refused():
    from fourlegs_engine.scene import Camera

    cam = Camera.look_at((0, -3, 0), (0, 0, 0), width=16, height=16, fov_y=0.8)
    assert np.isfinite(cam.unproject(np.array([[8.0, 8.0]]), np.array([2.0]))).all()
    for depth in (np.inf, np.nan):
        with pytest.raises(InputError, match="unproject"):
            cam.unproject(np.array([[8.0, 8.0]]), np.array([depth]))


def test_a_garbage_wheel_is_not_bundled(tmp_path):
    import zipfile

    from fourlegs_addon.build import wheel_problem

    garbage = tmp_path / "evil-1.0-py3-none-any.whl"
    garbage.write_bytes(b"not a zip at all")
    assert "not a zip archive" in wheel_problem(garbage)
    empty = tmp_path / "empty-1.0-py3-none-any.whl"
    with zipfile.ZipFile(empty, "w") as zf:
        zf.writestr("empty/__init__.py", "")
    assert "dist-info/WHEEL" in wheel_problem(empty)
    good = tmp_path / "good-1.0-py3-none-any.whl"
    with zipfile.ZipFile(good, "w") as zf:
        zf.writestr("good-1.0.dist-info/WHEEL", "Wheel-Version: 1.0\n")
        zf.writestr("good-1.0.dist-info/METADATA", "Name: good\n")
    assert wheel_problem(good) is None


def test_an_exr_the_full_disk_cut_short_is_one_line_and_not_kept(tmp_path, monkeypatch):
    import OpenEXR

    from fourlegs_engine.errors import describe_environment_error
    from fourlegs_engine.query.exr import write_exr

    real = OpenEXR.File

    class CutShort:
        def __init__(self, *args):
            self.inner = real(*args)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def write(self, name):
            Path(name).write_bytes(b"\x76\x2f\x31\x01")  # a header cut short, no error reported

    monkeypatch.setattr(OpenEXR, "File", CutShort)
    _disk_full(monkeypatch)
    with pytest.raises(OSError) as exc:
        write_exr(tmp_path / "cam_t0001.exr", {"relevancy": np.ones((4, 4), np.float32)})
    assert describe_environment_error(exc.value).startswith(f"no space left on device while writing {tmp_path}")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("damage", ["empty", "truncated", "codes-strings", "codes-out-of-range"])
def test_a_damaged_codebook_is_one_line(distilled, tmp_path, capsys, damage):
    path = Path(shutil.copytree(distilled, tmp_path / "b"))
    argv = ["query", str(path), *QUERY, "--path", "codebook", "--codebook-size", "8"]
    assert main(argv) == 0
    capsys.readouterr()
    npz = next(path.rglob("codebook_8.npz"))
    codes = npz.parent / "codes_8.npy"
    if damage == "empty":
        npz.write_bytes(b"")
    elif damage == "truncated":
        npz.write_bytes(npz.read_bytes()[:100])
    elif damage == "codes-strings":
        np.save(codes, np.array(["a", "b"]))
    else:
        np.save(codes, np.full(np.load(codes).shape, 99, np.int64))
    line = _one_line(capsys, argv)
    assert ("codebook_8.npz" if damage in ("empty", "truncated") else "codes_8.npy") in line, line
