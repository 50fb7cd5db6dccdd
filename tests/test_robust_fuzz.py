"""Issue #24: "0 tracebacks, 0 partial outputs" over every loader and CLI entry, kept from regressing.

Hypothesis mutates valid inputs (one ``scene.json`` or ``*_meta.json`` value replaced by a hostile
JSON value; bytes of ``.npy``/``params.npz``/``.ply``/``decoder.pt`` files cut or flipped) and
drives every ``fourlegs`` command with a corpus of bad scenes, texts, numbers and output locations.
Each loader either loads or raises :class:`InputError`; each command either succeeds or prints one
``fourlegs: error:`` line (or argparse's usage error) and leaves no new file behind.
"""
from __future__ import annotations

import json
import os
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from _fuzz_helpers import HOSTILE_JSON, NOT_UTF8, json_paths, replace_at, run_command
from _language_helpers import micro_bundle
from fourlegs_engine.commands.main import main
from fourlegs_engine.errors import FourlegsError, InputError
from fourlegs_engine.language.autoencoder import FeatureDecoder, load_decoder
from fourlegs_engine.scene.dynamic3dgs import write_dynamic3dgs
from fourlegs_engine.scene.loaders import load_scene
from fourlegs_engine.scene.ply import write_ply_scene

# FOURLEGS_FUZZ_EXAMPLES=500 FOURLEGS_FUZZ_RANDOM=1 runs a deeper, randomized search
EXAMPLES = int(os.environ.get("FOURLEGS_FUZZ_EXAMPLES", "30"))
FAST = settings(max_examples=EXAMPLES, deadline=None, derandomize=not os.environ.get("FOURLEGS_FUZZ_RANDOM"),
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
_paths, _replace = json_paths, replace_at


def _loads_or_input_error(load, *args):
    try:
        load(*args)
    except InputError as exc:
        assert str(exc).strip() and "\n" not in str(exc)


@pytest.fixture(scope="module")
def sources(tmp_path_factory):
    root = tmp_path_factory.mktemp("fuzz")
    bundle = micro_bundle(root / "bundle", T=2, cameras=2)
    scene = load_scene(bundle)
    d3 = write_dynamic3dgs(scene, root / "d3dgs")
    plys = write_ply_scene(scene, root / "plys")
    ply = sorted(Path(plys).glob("*.ply"))[0]
    dec = root / "decoder.pt"
    torch.save(FeatureDecoder((8, 16, 32)).state_dict(), dec)
    return {"root": root, "bundle": bundle, "d3dgs": d3, "ply": ply, "decoder": dec}


# ------------------------------------------------------------------------------- loaders
@FAST
@given(data=st.data(), value=HOSTILE_JSON)
def test_scene_json_with_any_value_replaced_loads_or_is_one_input_error(sources, tmp_path_factory, data, value):
    meta = json.loads((sources["bundle"] / "scene.json").read_text())
    path = data.draw(st.sampled_from(sorted(_paths(meta), key=repr)))
    work = tmp_path_factory.mktemp("b") / "b"
    shutil.copytree(sources["bundle"], work)
    (work / "scene.json").write_text(json.dumps(_replace(meta, path, value)))
    _loads_or_input_error(load_scene, work)


@FAST
@given(data=st.data(), value=HOSTILE_JSON)
def test_dynamic3dgs_meta_with_any_value_replaced_loads_or_is_one_input_error(sources, tmp_path_factory,
                                                                              data, value):
    meta = json.loads((sources["d3dgs"] / "train_meta.json").read_text())
    path = data.draw(st.sampled_from(sorted(_paths(meta), key=repr)))
    work = tmp_path_factory.mktemp("d") / "d"
    shutil.copytree(sources["d3dgs"], work)
    (work / "train_meta.json").write_text(json.dumps(_replace(meta, path, value)))
    _loads_or_input_error(load_scene, work)


def _damaged(data_bytes: bytes, data) -> bytes:
    how = data.draw(st.sampled_from(["cut", "flip", "empty", "zeros"]))
    if how == "empty":
        return b""
    at = data.draw(st.integers(0, max(len(data_bytes) - 1, 0)))
    if how == "cut":
        return data_bytes[:at]
    if how == "zeros":
        return data_bytes[:at] + bytes(min(64, len(data_bytes) - at)) + data_bytes[at + 64:]
    return data_bytes[:at] + bytes([data_bytes[at] ^ 0xFF]) + data_bytes[at + 1:]


@FAST
@given(data=st.data())
def test_damaged_binary_files_load_or_are_one_input_error(sources, tmp_path_factory, data):
    kind = data.draw(st.sampled_from(["means.npy", "params.npz", "ply", "decoder.pt"]))
    work = tmp_path_factory.mktemp("bin")
    if kind == "means.npy":
        target = shutil.copytree(sources["bundle"], work / "b") / "means.npy"
        load, arg = load_scene, target.parent
    elif kind == "params.npz":
        target = shutil.copytree(sources["d3dgs"], work / "d") / "params.npz"
        load, arg = load_scene, target.parent
    elif kind == "ply":
        target = Path(shutil.copy(sources["ply"], work / "one.ply"))
        load, arg = load_scene, target
    else:
        target = Path(shutil.copy(sources["decoder"], work / "decoder.pt"))
        load, arg = load_decoder, target
    target.write_bytes(_damaged(target.read_bytes(), data))
    _loads_or_input_error(load, arg)


# ------------------------------------------------------------------------------- the CLI
def _snapshot(root: Path) -> set[Path]:
    return {p for p in root.rglob("*")}


def _run_cli(argv, capsys, tmp: Path, before: set[Path]) -> None:
    try:
        code = main(argv)
    except SystemExit as exc:       # argparse: usage + one "error:" line
        code = exc.code
    out = capsys.readouterr()
    assert "Traceback" not in out.err, (argv, out.err)
    if code not in (0, None):
        lines = [l for l in out.err.replace("\r", "\n").splitlines() if l.strip()]
        assert lines and ("error:" in lines[-1]), (argv, out.err)
        new = _snapshot(tmp) - before
        assert not new, (argv, sorted(map(str, new)))   # nothing partial (or whole) left by a failure


@pytest.fixture(scope="module")
def bad_scenes(sources):
    root = sources["root"] / "bad"
    root.mkdir()
    garbage = root / "garbage"
    garbage.mkdir()
    (garbage / "scene.json").write_text("{not json")
    wrong = shutil.copytree(sources["bundle"], root / "wrong")
    meta = json.loads((wrong / "scene.json").read_text())
    meta["cameras"]["num_timesteps"] = 10**10
    (wrong / "scene.json").write_text(json.dumps(meta))
    outside = shutil.copytree(sources["bundle"], root / "outside")
    meta = json.loads((outside / "scene.json").read_text())
    meta["arrays"]["means"] = "/etc/hostname"
    (outside / "scene.json").write_text(json.dumps(meta))
    (root / "file.txt").write_text("hello")
    (root / "empty").mkdir()
    return [str(root / "missing"), str(garbage), str(wrong), str(outside), str(root / "file.txt"),
            str(root / "empty"), str(garbage / "scene.json"), NOT_UTF8]


COMMANDS = [
    lambda s, t, o: ["info", s], lambda s, t, o: ["info", s, "--json"],
    lambda s, t, o: ["extract", s, "--no-progress"], lambda s, t, o: ["train-ae", s],
    lambda s, t, o: ["distill", s, "--no-progress"], lambda s, t, o: ["distill", s, "--check"],
    lambda s, t, o: ["language", s, "--no-progress"], lambda s, t, o: ["viclip-info", s],
    lambda s, t, o: ["query", s, t, "--json", o], lambda s, t, o: ["plan", s, t, "-o", o],
    lambda s, t, o: ["generate", "--size", "tiny", "-o", s],
]


@FAST
@given(data=st.data())
def test_every_command_on_bad_input_is_one_line_and_writes_nothing(sources, bad_scenes, tmp_path_factory,
                                                                  capsys, data):
    tmp = tmp_path_factory.mktemp("cli")
    command = data.draw(st.sampled_from(COMMANDS))
    scene = data.draw(st.sampled_from(bad_scenes))
    text = data.draw(st.sampled_from(["ball", NOT_UTF8, "", " "]))
    out = data.draw(st.sampled_from([str(tmp / "o.json"), str(Path(bad_scenes[4]) / "o.json")]))
    if command(scene, text, out)[0] == "generate":
        scene = data.draw(st.sampled_from([bad_scenes[4], str(Path(bad_scenes[4]) / "sub"), str(sources["bundle"])]))
    _run_cli(command(scene, text, out), capsys, tmp, _snapshot(tmp))


@pytest.fixture(scope="module")
def distilled(sources):
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    path = shutil.copytree(sources["bundle"], sources["root"] / "distilled")
    assert main(["extract", str(path), "--no-progress"]) == 0
    assert main(["train-ae", str(path), "--epochs", "1", "--samples", "1024", "--ae-batch-size", "256"]) == 0
    assert main(["distill", str(path), "--no-progress"]) == 0
    torch.set_num_threads(old)
    return path


NUMBERS = ["-1", "0", "1", "1e9", "1000", "nan", "inf", "-inf", "1e-300", "x", "3"]


@settings(FAST, max_examples=max(EXAMPLES * 5 // 6, 1))
@given(data=st.data())
def test_query_options_on_a_real_field_are_bounded(distilled, tmp_path_factory, capsys, data):
    tmp = tmp_path_factory.mktemp("q")
    argv = ["query", str(distilled), data.draw(st.sampled_from(["person jumping", NOT_UTF8])),
            "--json", str(tmp / "q.json")]
    for option in data.draw(st.lists(st.sampled_from(["--scale", "--dilation", "--stride", "--frames",
                                                      "--codebook-size", "--negatives"]), max_size=2,
                                     unique=True)):
        argv += [option, data.draw(st.sampled_from(NUMBERS + (["peak"] if option == "--frames" else [])))]
    if "--frames" in argv:
        argv += ["--exr", str(tmp / "maps")]
    else:
        argv.append("--no-spatial")
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        _run_cli(argv, capsys, tmp, _snapshot(tmp))
    finally:
        torch.set_num_threads(old)


def test_the_headless_job_on_bad_input_is_one_line(bad_scenes, tmp_path, capsys):
    from fourlegs_addon import headless

    for scene in bad_scenes[:6]:
        code = headless.main([scene, "ball", "-o", str(tmp_path / "out")])
        err = capsys.readouterr().err
        assert code == 2 and "Traceback" not in err and err.strip().startswith("fourlegs: error:"), err
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


# ------------------------------------------------------------------------------------ issue #30
DAMAGES = st.one_of(
    st.tuples(st.just("truncate"), st.floats(0.0, 0.999)),
    st.tuples(st.just("flip"), st.floats(0.0, 0.999), st.integers(1, 255)),
    st.tuples(st.just("value"), st.floats(0.0, 0.999), st.sampled_from([float("nan"), float("inf"), -float("inf")])),
    st.tuples(st.just("dtype"), st.sampled_from(["float32", "float64", "int16", "<U3"])),
    st.tuples(st.just("shape"), st.integers(-2, 2).filter(bool)))


def _damage_npy(path: Path, damage: tuple) -> None:
    raw = path.read_bytes()
    kind = damage[0]
    if kind == "truncate":
        path.write_bytes(raw[:int(len(raw) * damage[1])])
    elif kind == "flip":
        at = int(len(raw) * damage[1])
        path.write_bytes(raw[:at] + bytes([raw[at] ^ damage[2]]) + raw[at + 1:])
    elif kind == "value":
        arr = np.load(path)
        arr.reshape(-1)[int(arr.size * damage[1])] = damage[2]
        np.save(path, arr)
    elif kind == "dtype":
        np.save(path, np.load(path).astype(damage[1]))
    else:
        arr = np.load(path)
        np.save(path, arr[:damage[1]] if damage[1] < 0 else np.concatenate([arr, arr[:damage[1]]]))


@settings(FAST, max_examples=max(EXAMPLES // 3, 1))
@given(damage=DAMAGES, t=st.integers(0, 1), stage=st.sampled_from(["features", "language/steps"]))
def test_any_damage_to_a_finished_step_file_is_never_trusted(distilled, tmp_path_factory, capsys, damage, t, stage):
    """Issue #30, items 2 and 4: a resume verifies every finished file (shape, dtype, finite, checksum)."""
    from fourlegs_engine.language.extract import feature_store
    from fourlegs_engine.language.store import StepStore
    from fourlegs_engine.scene.bundle import load_bundle

    path = Path(shutil.copytree(distilled, tmp_path_factory.mktemp("damage") / "b"))
    scene = load_bundle(path)
    if stage == "features":
        store = feature_store(scene)
    else:
        steps = path / "language" / "steps"
        store = StepStore(steps, "latents", {"a": 1}, scene.num_timesteps, shape_of=lambda k: (scene.num_gaussians, 4),
                          dtype="float16").open()
        for k in range(scene.num_timesteps):
            store.save(k, np.full((scene.num_gaussians, 4), 0.5, np.float16))
    assert store.problem(t) is None
    _damage_npy(store.step_path(t), damage)
    assert store.problem(t) is not None and not store.is_done(t) and t in store.missing()
    if stage == "features":
        assert main(["train-ae", str(path), "--epochs", "1", "--samples", "1024", "--ae-batch-size", "256",
                     "--seed", "9"]) == 2
        err = capsys.readouterr().err
        assert "Traceback" not in err and f"t{t:06d}.npy" in err.strip().splitlines()[-1], err


@settings(FAST, max_examples=max(EXAMPLES // 2, 1))
@given(data=st.data())
def test_train_ae_and_distill_refuse_bad_numbers_before_replacing_anything(distilled, tmp_path_factory, capsys, data):
    """Issue #30, item 3: every --overwrite path validates its arguments first."""
    tmp = tmp_path_factory.mktemp("ae")
    path = Path(shutil.copytree(distilled, tmp / "b"))
    keep = {p: p.read_bytes() for p in (path / "language").iterdir() if p.is_file()}
    command = data.draw(st.sampled_from(["train-ae", "distill"]))
    options = {"train-ae": {"--lr": ["-1", "0", "nan", "inf", "-inf", "1e9", "x"],
                            "--holdout-camera": ["99", "-99", "1000000000"], "--seed": ["-1", "1e30", "x"],
                            "--epochs": ["0", "-1", "nan"], "--ae-batch-size": ["1", "0", "-5"]},
               "distill": {"--view-scale": ["1e-9", "0", "nan", "2", "-1"], "--teacher-stride": ["0", "100000", "-1"],
                           "--neighbours": ["0", "100000"], "--iterations": ["-1", "1e99"]}}[command]
    option = data.draw(st.sampled_from(sorted(options)))
    argv = [command, str(path), option, data.draw(st.sampled_from(options[option])), "--overwrite"]
    try:
        code = main(argv + (["--no-progress"] if command == "distill" else []))
    except SystemExit as exc:
        code = exc.code
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err, (argv, err)
    assert {p: p.read_bytes() for p in (path / "language").iterdir() if p.is_file()} == keep


FIELD_FILES = ["features/t000000.npy", "features/manifest.json", "language/encoder.pt", "language/decoder.pt",
               "language/autoencoder.json", "language/latents.npy", "scene.json"]
FIELD_COMMANDS = [["query", "{p}", "person jumping", "--no-spatial"], ["info", "{p}"], ["extract", "{p}", "--check"],
                  ["train-ae", "{p}", "--epochs", "1", "--samples", "1024", "--ae-batch-size", "256", "--seed", "4"],
                  ["distill", "{p}", "--no-progress", "--teacher-stride", "2", "--overwrite"]]


@settings(FAST, max_examples=max(EXAMPLES // 2, 1))
@given(data=st.data())
def test_every_command_on_a_field_with_one_damaged_file_is_one_line(distilled, tmp_path_factory, capsys, data):
    """Issue #30: every command, with any file of a distilled field it reads damaged: success or one line."""
    path = Path(shutil.copytree(distilled, tmp_path_factory.mktemp("field") / "b"))
    target = path / data.draw(st.sampled_from(FIELD_FILES))
    if target.suffix == ".json" and data.draw(st.booleans()):
        text = json.dumps(data.draw(st.one_of(HOSTILE_JSON, st.just({"config_hash": 5}))))
        target.write_text(text)
    else:
        target.write_bytes(_damaged(target.read_bytes(), data))
    argv = [w.replace("{p}", str(path)) for w in data.draw(st.sampled_from(FIELD_COMMANDS))]
    code, err = run_command(argv, capsys)
    assert "Traceback" not in err, (argv, target.name, err)
    if code not in (0, 1, None) or (code == 1 and argv[0] != "extract"):
        lines = [line for line in err.replace("\r", "\n").splitlines() if line.strip()]
        assert lines and "error:" in lines[-1], (argv, target.name, err)
