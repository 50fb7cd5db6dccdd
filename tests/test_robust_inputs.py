"""Issue #24, items 5, 6 and 9: one clear line instead of a traceback for the machine's limits (full or
read-only disk, no memory), a validated ``scene.json`` (types, bounds, paths inside the bundle) and
public functions that refuse degenerate values instead of dividing by zero or overflowing."""
from __future__ import annotations

import errno
import json
import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from _language_helpers import micro_bundle
from fourlegs_engine.commands.main import main
from fourlegs_engine.errors import InputError, describe_environment_error
from fourlegs_engine.query.temporal import sparkline
from fourlegs_engine.scene.bundle import load_bundle
from fourlegs_engine.scene.camera import Camera
from fourlegs_engine.scene.loaders import load_scene


@pytest.fixture(scope="module")
def bundle(tmp_path_factory) -> Path:
    return micro_bundle(tmp_path_factory.mktemp("robust") / "micro", T=2)


def _edited(bundle: Path, tmp_path: Path, edit) -> Path:
    copy = tmp_path / "edited"
    shutil.copytree(bundle, copy)
    meta = json.loads((copy / "scene.json").read_text())
    edit(meta)
    (copy / "scene.json").write_text(json.dumps(meta))
    return copy


def _one_line_error(capsys, argv) -> tuple[int, str]:
    code = main(argv)
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = [l for l in err.replace("\r", "\n").splitlines() if l.strip()]
    errors = [l for l in lines if l.startswith("fourlegs: error:")]
    assert len(errors) == 1 and lines[-1] == errors[0], err  # progress bars may come before it
    return code, errors[0]


# ------------------------------------------------------------------------- item 5: the CLI's errors
def test_a_full_disk_is_one_line_naming_the_path(bundle, tmp_path, monkeypatch, capsys):
    real_replace = os.replace

    def full_disk(src, dst, *a, **kw):
        raise OSError(errno.ENOSPC, "No space left on device", str(dst))

    monkeypatch.setattr(os, "replace", full_disk)
    out = tmp_path / "gen"
    code, line = _one_line_error(capsys, ["generate", "--size", "tiny", "-o", str(out)])
    monkeypatch.setattr(os, "replace", real_replace)
    assert code == 1
    assert line.startswith("fourlegs: error: no space left on device while writing ") and str(tmp_path) in line
    assert not out.exists() and not any(p.name.endswith(".part") for p in tmp_path.iterdir())


def test_an_output_parent_that_is_a_file_is_one_line(bundle, tmp_path, capsys):
    (tmp_path / "file").write_text("x")
    code, line = _one_line_error(capsys, ["generate", "--size", "tiny", "-o", str(tmp_path / "file" / "b")])
    assert code == 1 and str(tmp_path / "file") in line and "a file where a folder is needed" in line


@pytest.mark.skipif(os.geteuid() == 0, reason="root ignores permissions")
def test_a_read_only_folder_is_one_line(tmp_path, capsys):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        code, line = _one_line_error(capsys, ["generate", "--size", "tiny", "-o", str(ro / "b")])
    finally:
        ro.chmod(0o755)
    assert code == 1 and "permission denied" in line.lower() and str(ro) in line


def test_a_read_only_file_system_is_one_line(tmp_path, monkeypatch, capsys):
    def read_only(path, *a, **kw):
        raise OSError(errno.EROFS, "Read-only file system", str(path))

    monkeypatch.setattr(os, "mkdir", read_only)   # what every write below a read-only mount meets first
    code, line = _one_line_error(capsys, ["generate", "--size", "tiny", "-o", str(tmp_path / "ro" / "b")])
    assert code == 1 and line == (f"fourlegs: error: {tmp_path / 'ro'}: read-only file system "
                                  "(choose a writable output location)")


def test_memory_errors_are_one_line_and_bugs_keep_their_traceback():
    assert describe_environment_error(MemoryError()).startswith("out of memory")
    torch_msg = ("[enforce fail at alloc_cpu.cpp:117] data. DefaultCPUAllocator: not enough memory: you tried "
                 "to allocate 86000000000 bytes.")
    assert "86000000000 bytes" in describe_environment_error(RuntimeError(torch_msg))
    assert describe_environment_error(RuntimeError("shape mismatch")) is None
    assert describe_environment_error(KeyError("x")) is None


@pytest.mark.parametrize("argv, needle", [
    (["--scale", "1000"], "--scale"), (["--scale", "0"], "--scale"), (["--scale", "nan"], "--scale"),
    (["--dilation", "1000000000"], "--dilation"), (["--dilation", "-1"], "--dilation"),
    (["--stride", "0"], "--stride"), (["--codebook-size", "0"], "--codebook-size")])
def test_query_arguments_are_bounded_before_any_work(bundle, capsys, argv, needle):
    with pytest.raises(SystemExit) as exc:
        main(["query", str(bundle), "ball", *argv])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and needle in err.splitlines()[-1] and "Traceback" not in err


def test_query_engine_bounds_its_options():
    from fourlegs_engine.query.engine import QueryEngine, QueryOptions
    for kw in ({"dilation": -1}, {"dilation": 1e9}, {"resolution_scale": 1000.0}, {"resolution_scale": math.inf}):
        with pytest.raises(InputError, match=next(iter(kw))):
            QueryEngine(None, None, None, QueryOptions(**kw))


def test_query_on_a_non_bundle_names_commands_that_exist(tmp_path, capsys):
    code, line = _one_line_error(capsys, ["query", str(tmp_path), "ball"])
    assert code == 2 and "fourlegs convert" not in line and "fourlegs highlight" in line
    from fourlegs_engine.commands.main import build_parser
    commands = build_parser()._subparsers._group_actions[0].choices
    assert "highlight" in commands and "language" in commands and "convert" not in commands


# ------------------------------------------------------------------------- item 6: scene.json schema
@pytest.mark.parametrize("edit, field", [
    (lambda m: m.update(num_timesteps="2"), "num_timesteps"),
    (lambda m: m.update(num_timesteps=2.5), "num_timesteps"),
    (lambda m: m.update(num_timesteps=None), "num_timesteps"),
    (lambda m: m.update(num_gaussians=[1]), "num_gaussians"),
    (lambda m: m.update(fps="fast"), "fps"),
    (lambda m: m.update(fps=-1), "fps"),
    (lambda m: m.update(arrays=["means.npy"]), "arrays"),
    (lambda m: m["arrays"].update(means=3), "arrays.means"),
    (lambda m: m.update(cameras=[]), "cameras"),
    (lambda m: m["cameras"].update(train=5), "cameras.train"),
    (lambda m: m["cameras"]["train"].__setitem__(0, "cam"), "cameras.train[0]"),
    (lambda m: m["cameras"]["train"][0].update(width="wide"), "cameras.train[0].width"),
    (lambda m: m["cameras"]["train"][0].update(width=1e30), "cameras.train[0].width"),
    (lambda m: m["cameras"]["train"][0].update(width=None), "cameras.train[0].width"),
    (lambda m: m["cameras"].update(num_timesteps=10**10), "cameras.num_timesteps"),
    (lambda m: m["cameras"].update(static="yes"), "cameras.static"),
    (lambda m: m.update(language=[1]), "language"),
])
def test_bad_scene_json_values_are_one_clear_error(bundle, tmp_path, edit, field):
    path = _edited(bundle, tmp_path, edit)
    with pytest.raises(InputError) as exc:
        load_scene(path)
    assert exc.value.field == field and exc.value.file == str(path / "scene.json")


def test_a_huge_camera_timestep_count_is_refused_before_expanding(bundle, tmp_path):
    import time
    path = _edited(bundle, tmp_path, lambda m: m["cameras"].update(num_timesteps=10**10))
    start = time.process_time()
    with pytest.raises(InputError, match="cameras.num_timesteps"):
        load_bundle(path)
    assert time.process_time() - start < 2.0


@pytest.mark.parametrize("target", ["/etc/hostname", "../outside.npy", "language/../../outside.npy"])
def test_array_paths_outside_the_bundle_are_refused(bundle, tmp_path, target):
    np.save(tmp_path / "outside.npy", np.zeros((2, 3)))
    path = _edited(bundle, tmp_path, lambda m: m["arrays"].update(colors=target))
    with pytest.raises(InputError, match="outside the bundle") as exc:
        load_scene(path)
    assert exc.value.field == "arrays.colors"


def test_an_array_symlinked_outside_the_bundle_is_refused(bundle, tmp_path):
    path = _edited(bundle, tmp_path, lambda m: None)
    np.save(tmp_path / "outside.npy", np.load(path / "colors.npy"))
    (path / "colors.npy").unlink()
    (path / "colors.npy").symlink_to(tmp_path / "outside.npy")
    with pytest.raises(InputError, match="outside the bundle"):
        load_scene(path)


def test_the_unedited_bundle_still_loads(bundle):
    scene = load_scene(bundle)
    assert scene.num_timesteps == 2 and scene.cameras.num_cameras() == 3


def test_a_dynamic3dgs_meta_width_of_1e30_is_refused(tmp_path):
    from fourlegs_engine.scene.camera import MAX_IMAGE_SIDE
    cam = Camera.look_at((3, 0, 1), (0, 0, 0), width=32, height=18)
    with pytest.raises(InputError, match=str(MAX_IMAGE_SIDE)):
        Camera(K=cam.K, w2c=cam.w2c, width=int(1e30), height=18).validate()
    with pytest.raises(InputError, match="pixel limit"):
        cam.scaled(1e6)


# ------------------------------------------------------------------- item 9: public numeric edges
@pytest.mark.parametrize("kw, field", [({"fov_y": 0.0}, "fov_y"), ({"fov_y": math.pi}, "fov_y"),
                                       ({"fov_y": math.nan}, "fov_y"), ({"focal": 0.0}, "focal"),
                                       ({"width": 0}, "width"), ({"width": math.inf}, "width")])
def test_look_at_refuses_degenerate_lenses(kw, field):
    args = {"width": 32, "height": 18, **kw}
    with pytest.raises(InputError, match=field):
        Camera.look_at((3, 0, 1), (0, 0, 0), **args)


def test_look_at_with_a_far_eye_is_a_valid_camera_not_coincident():
    cam = Camera.look_at((1e300, 0, 0), (0, 0, 0), width=32, height=18)
    assert np.all(np.isfinite(cam.w2c)) and np.allclose(cam.forward, [-1, 0, 0])
    with pytest.raises(InputError, match="coincide"):
        Camera.look_at((1, 2, 3), (1, 2, 3), width=32, height=18)
    with pytest.raises(InputError, match="too far apart"):
        Camera.look_at((1e308, 0, 0), (-1e308, 0, 0), width=32, height=18)
    with pytest.raises(InputError, match="finite"):
        Camera.look_at((math.nan, 0, 0), (0, 0, 0), width=32, height=18)


@pytest.mark.parametrize("scores, expected", [([math.nan], " "), ([math.nan, 1.0], " █"),
                                              ([math.inf, 0.5], "██"), ([math.inf], "█"), ([0.0, 0.5, 1.0], " ▄█"), ([], "")])
def test_sparkline_of_non_finite_scores(scores, expected):
    assert sparkline(scores) == expected


@pytest.mark.parametrize("w", [1e30, float("inf"), 10**6])
def test_a_dynamic3dgs_meta_with_a_huge_width_is_refused_at_load(bundle, tmp_path, w):
    from fourlegs_engine.scene.dynamic3dgs import write_dynamic3dgs
    path = write_dynamic3dgs(load_scene(bundle), tmp_path / "d3")
    meta = json.loads((path / "train_meta.json").read_text())
    meta["w"] = w
    (path / "train_meta.json").write_text(json.dumps(meta))
    with pytest.raises(InputError) as exc:
        load_scene(path)
    assert exc.value.field == "w/h" and exc.value.file == str(path / "train_meta.json")


@pytest.mark.parametrize("key", ["latents", "decoder"])
def test_language_files_outside_the_bundle_are_refused(bundle, tmp_path, key):
    from fourlegs_engine.language.field import LanguageField
    path = _edited(bundle, tmp_path, lambda m: m.update(language={"latents": "language/latents.npy",
                                                                  "decoder": "language/decoder.pt",
                                                                  "encoder": "simulated", key: "/etc/hostname"}))
    with pytest.raises(InputError, match="inside the bundle") as exc:
        load_scene(path)
    assert exc.value.field == f"language.{key}"
    with pytest.raises(InputError, match="inside the bundle"):
        LanguageField.open(path)


def test_no_message_points_to_a_command_that_does_not_exist():
    import re
    from fourlegs_engine.commands.main import build_parser
    commands = set(build_parser()._subparsers._group_actions[0].choices)
    root = Path(__file__).resolve().parents[1]
    sources = list((root / "fourlegs_engine").rglob("*.py")) + list((root / "addon").rglob("*.py"))
    named = {m for p in sources for m in re.findall(r"`fourlegs ([a-z][a-z0-9-]+)", p.read_text(encoding="utf-8"))}
    assert named and named <= commands | {"bench"}, sorted(named - commands)
