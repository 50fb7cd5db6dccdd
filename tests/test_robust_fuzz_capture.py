"""Issue #30: damaged inputs of ``fit``, ``viclip-info``, the bench commands, annotation masks and presets,
and the map of which test fuzzes which file of which command.

Each case either succeeds (a tiny fit: 2 + 1 iterations at 32x18) or ends with one ``fourlegs: error:``
line naming the damaged file, exit code 2, no traceback, and nothing left behind (no output folder, no
``.NAME.fit`` work folder, no ``.part`` file). A checkpoint that is a pickle with a payload never runs it.

Every ``fourlegs`` command (``fourlegs --help``, ``fourlegs bench --help``) against the files it reads, and
where they are fuzzed (F: tests/test_robust_fuzz.py, C: this file, D: test_robust_damaged.py,
R: test_robust_field.py, V: test_robust_video.py, O: test_robust_outputs.py, P: test_highlights_presets.py,
A: test_annotation_masks.py):

=====================  ==========================================================  =======================
command                files it reads                                              fuzzed in
=====================  ==========================================================  =======================
info                   scene: bundle (scene.json, .npy), params.npz + *_meta.json,  F (loaders, bad scenes,
                       .ply; the field's files                                      damaged field files)
extract                scene; features/*.npy + .sha256 + manifest.json;            F, C (viclip), A, D
                       --checkpoint/--vocab (viclip); --masks folders (PNG)        (60000-px mask), C
train-ae               features; autoencoder.ckpt.pt, history.json, decoder.pt     F, D, R
distill                features, decoder.pt, encoder.pt, latents, steps/*.npy      F, R
language               all of extract, train-ae and distill                         F, C (masks)
viclip-info            checkpoint (.pth, .safetensors, -hf folder), --vocab .gz     C
query                  bundle, field files, codebook; several scenes                F, D (codebook), O
plan                   any scene; preset .toml (--preset, --preset-dir)             F, C (preset), P
highlight              any scene, preset, its output folder's own files, frames     F (headless job), O, V
fit                    capture: *_meta.json, ims/, seg/; its .NAME.fit work folder  C, D (checkpoints)
generate               nothing (writes -o)                                          F
build-extension        --extra-wheel / wheels folder                                D (garbage wheel)
bench compare,         JSON files of earlier runs                                   C (bench)
  fit-pareto
bench fit, fit-        a capture (+ its fitted scene)                               C (bench)
  background, device,
  device-data
bench real-lift,       a fitted scene bundle + annotation mask folders              C (bench)
  real-annotations,
  language-cost
bench viclip           --checkpoint (and its dataset folder)                        C (bench)
bench query-           a scene bundle with a field                                  C (bench)
  interactive,
  grounding,
  accuracy-time
bench blender, native- a scene (bpy only: tests/test_blender_*.py)                  not here (no bpy on the
  render, prepare-cost                                                              CPU test machine)
bench render, query-   nothing from the user (synthetic scenes)                     -
  speed, distill,
  cluster, main-job
=====================  ==========================================================  =======================
"""
from __future__ import annotations

import gzip
import io
import json
import os
import pickle
import shutil
import struct
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from _fit_helpers import write_tiny_capture
from _fuzz_helpers import HOSTILE_JSON, json_paths, remove_at, replace_at, run_command
from fourlegs_engine.language.viclip.tokenizer import MAX_VOCAB_BYTES

EXAMPLES = int(os.environ.get("FOURLEGS_FUZZ_EXAMPLES", "30"))
FUZZ = settings(max_examples=max(EXAMPLES // 3, 1), deadline=None,
                derandomize=not os.environ.get("FOURLEGS_FUZZ_RANDOM"),
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
TINY_FIT = ["--first-iterations", "2", "--iterations", "1", "--max-iterations", "0", "--device", "cpu",
            "--init-foreground", "300", "--init-background", "300", "--max-gaussians", "1000"]


def _run(argv: list[str], capsys) -> tuple[int, list[str]]:
    code, err = run_command(argv, capsys)
    assert "Traceback" not in err, (argv, err)
    return code, [line for line in err.replace("\r", "\n").splitlines() if line.strip()]


def _assert_one_line_naming(code: int, lines: list[str], name: str) -> None:
    assert code == 2 and len(lines) == 1, (code, lines)
    assert lines[0].startswith("fourlegs: error:") and name in lines[0], (name, lines)


# ----------------------------------------------------------------------------------- fit on a capture
@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    return write_tiny_capture(tmp_path_factory.mktemp("capture") / "cap")


def _png_with_header(width: int, height: int) -> bytes:
    """A PNG whose header claims ``width`` x ``height`` pixels and whose data is a few bytes."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\x00" * 16)) + chunk(b"IEND", b""))


def _image_bytes(kind: str, raw: bytes, at: float) -> bytes:
    if kind == "truncated":
        return raw[:int(len(raw) * at)]
    if kind == "flipped":
        i = min(int(len(raw) * at), len(raw) - 1)
        return raw[:i] + bytes([raw[i] ^ 0x5A]) + raw[i + 1:]
    if kind == "empty":
        return b""
    if kind == "text":
        return b"not an image\n"
    if kind == "bomb":
        return _png_with_header(60_000, 60_000)
    buffer = io.BytesIO()
    size = (33, 18) if kind == "wrong size" else (32, 18)
    mode = {"rgba": "RGBA", "16-bit": "I;16"}.get(kind, "RGB")
    Image.new(mode, size).save(buffer, "PNG")
    return buffer.getvalue()


IMAGE_DAMAGES = ["truncated", "flipped", "empty", "text", "bomb", "wrong size", "rgba", "16-bit"]


def _damage(cap: Path, kind: str, data) -> str | None:
    """Damage one file of ``cap`` in the way ``kind`` names; returns the file name the error must mention
    (None: the capture is still valid and the fit must succeed)."""
    if kind in IMAGE_DAMAGES:
        target = data.draw(st.sampled_from(sorted(cap.rglob("*.png"))), label="file")
        target.write_bytes(_image_bytes(kind, target.read_bytes(), data.draw(st.floats(0.0, 0.99), label="at")))
        return None if kind in ("rgba", "16-bit") else target.name
    meta_file = cap / data.draw(st.sampled_from(["train_meta.json", "test_meta.json"]), label="meta")
    meta = json.loads(meta_file.read_text())
    if kind == "value":
        path = data.draw(st.sampled_from(sorted(json_paths(meta), key=repr)), label="path")
        meta = replace_at(meta, path, data.draw(HOSTILE_JSON, label="value"))
    elif kind == "remove":
        path = data.draw(st.sampled_from(sorted(json_paths(meta), key=repr)[1:]), label="path")
        meta = remove_at(meta, path)
    elif kind == "fn outside":
        elsewhere = str(next(cap.glob("ims/*/000000.png")).resolve())
        meta["fn"][data.draw(st.integers(0, 1))][0] = data.draw(st.sampled_from(
            [elsewhere, "../cap/ims/1/000000.png", "1/../../cap/ims/1/000000.png", "C:\\x.png", "1/\x00.png"]))
    else:  # one camera moves 50 m and turns between the timesteps: taken as given
        w2c = np.asarray(meta["w2c"][1][0])
        w2c[:3, :3] = w2c[:3, [2, 0, 1]]
        w2c[:3, 3] += 50.0
        meta["w2c"][1][0] = w2c.tolist()
    meta_file.write_text(json.dumps(meta))
    return None if kind == "camera jumps" else meta_file.name


def _fit_damaged(capture: Path, root: Path, kind: str, data, capsys) -> None:
    cap = Path(shutil.copytree(capture, root / "cap"))
    name = _damage(cap, kind, data)
    out = root / "out" / "scene"
    out.parent.mkdir()
    code, lines = _run(["fit", str(cap), "-o", str(out), *TINY_FIT], capsys)
    leftovers = sorted(p.name for p in out.parent.iterdir() if p != out)
    assert not leftovers, leftovers  # no .scene.fit work folder, no .part, no lock file
    if name is None:
        assert code == 0 and (out / "scene.json").is_file(), lines
    elif code == 0:
        # e.g. a test camera's id renamed, or a flipped byte of a checksum PIL does not read (IEND's)
        assert kind in ("value", "remove", "flipped") and (out / "scene.json").is_file()
    else:
        assert not out.exists()
        _assert_one_line_naming(code, lines, name)


@settings(FUZZ, max_examples=2)
@given(data=st.data())
@pytest.mark.parametrize("kind", IMAGE_DAMAGES + ["fn outside", "camera jumps"])
def test_fit_on_a_damaged_frame_or_camera_fits_or_is_one_line_and_leaves_nothing(capture, tmp_path_factory, capsys,
                                                                                 kind, data):
    _fit_damaged(capture, tmp_path_factory.mktemp("fit"), kind, data, capsys)


@FUZZ
@given(data=st.data(), kind=st.sampled_from(["value", "remove"]))
def test_fit_on_damaged_metadata_fits_or_is_one_line_and_leaves_nothing(capture, tmp_path_factory, capsys, kind, data):
    _fit_damaged(capture, tmp_path_factory.mktemp("fit"), kind, data, capsys)


@pytest.fixture(scope="module")
def interrupted_fit(capture, tmp_path_factory) -> Path:
    """A fit of ``capture`` stopped during its second timestep: its work folder holds config.json,
    history.json, effort.json, static.npz and t000000.npz."""
    from fourlegs_engine.commands.fit import options_from_args
    from fourlegs_engine.commands.main import build_parser
    from fourlegs_engine.errors import Cancelled
    from fourlegs_engine.fit.fitter import fit_capture

    root = tmp_path_factory.mktemp("interrupted")
    args = build_parser().parse_args(["fit", str(capture), "-o", str(root / "scene"), *RESUMED_FIT])

    def stop_in_timestep_1(event):
        if event.timestep == 1:
            raise Cancelled("stopped by the test")
    with pytest.raises(Cancelled):
        fit_capture(capture, root / "scene", options_from_args(args), progress=stop_in_timestep_1)
    assert sorted(p.name for p in (root / ".scene.fit").iterdir()) == [
        "config.json", "effort.json", "history.json", "static.npz", "t000000.npz"]
    return root


RESUMED_FIT = [*TINY_FIT[:TINY_FIT.index("--max-iterations")], "--max-iterations", "2", "--min-iterations", "1",
               *TINY_FIT[TINY_FIT.index("--max-iterations") + 2:]]


@FUZZ
@given(data=st.data())
def test_a_fit_resumed_over_a_damaged_work_file_fits_or_is_one_line(capture, interrupted_fit, tmp_path_factory,
                                                                  capsys, data):
    root = Path(shutil.copytree(interrupted_fit, tmp_path_factory.mktemp("resume") / "r"))
    target = root / ".scene.fit" / data.draw(st.sampled_from(
        ["config.json", "effort.json", "history.json", "static.npz", "t000000.npz"]))
    if target.suffix == ".json" and data.draw(st.booleans()):
        target.write_text(json.dumps(data.draw(st.one_of(HOSTILE_JSON, st.just({"1": [1]}),
                                                         st.just({"1": {"residual": "x"}})))))
    else:
        raw = target.read_bytes()
        target.write_bytes(raw[:data.draw(st.integers(0, len(raw) - 1))])
    code, lines = _run(["fit", str(capture), "-o", str(root / "scene"), *RESUMED_FIT, "--no-test-psnr"], capsys)
    if code == 0:
        assert (root / "scene" / "scene.json").is_file() and not (root / ".scene.fit").exists()
    else:
        assert lines and lines[-1].startswith("fourlegs: error:"), lines
        named = target.name if target.name != "config.json" else ".scene.fit"  # another config is not this one's
        assert named in lines[-1], lines
        assert not (root / "scene").exists()


def test_fit_checks_every_frame_before_fitting(capture, tmp_path, capsys):
    """A damaged frame of the last timestep (or of a test camera) stops the fit before its first step."""
    for damaged in ("ims/2/000001.png", "seg/3/000001.png", "ims/0/000001.png"):
        cap = Path(shutil.copytree(capture, tmp_path / damaged.replace("/", "_") / "cap"))
        (cap / damaged).write_bytes((cap / damaged).read_bytes()[:60])
        code, lines = _run(["fit", str(cap), "-o", str(cap.parent / "scene"), *TINY_FIT], capsys)
        _assert_one_line_naming(code, lines, damaged)
        assert "not a readable image" in lines[0]
        assert sorted(p.name for p in cap.parent.iterdir()) == ["cap"]
    code, lines = _run(["fit", str(cap), "-o", str(cap.parent / "scene"), *TINY_FIT, "--no-test-psnr"], capsys)
    assert code == 0, lines  # the test cameras' frames are not read then


# ----------------------------------------------------------------------------------- viclip-info
class _Payload:
    """Unpickling it would create the marker folder: proof that pickled code ran."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return os.makedirs, (str(self.marker),)


@pytest.fixture(scope="module")
def viclip_files(tmp_path_factory) -> dict[str, Path]:
    from _viclip_helpers import randomize_, tiny_config, write_tiny_vocab
    from fourlegs_engine.language.viclip.model import ViCLIPModel

    root = tmp_path_factory.mktemp("viclip")
    state = {k: v.contiguous() for k, v in randomize_(ViCLIPModel(tiny_config()), seed=1).state_dict().items()}
    torch.save({"model": state}, root / "tiny.pth")
    from safetensors.torch import save_file
    save_file(state, str(root / "tiny.safetensors"))
    return {"pth": root / "tiny.pth", "safetensors": root / "tiny.safetensors",
            "vocab": write_tiny_vocab(root / "bpe.txt.gz")}


CHECKPOINT_DAMAGES = ["truncated", "flipped", "empty", "pickle payload", "torch pickle payload", "zip not torch",
                      "wrong shape", "wrong dtype", "missing key", "nan", "not a tensor", "not a dict"]


def _damaged_checkpoint(files: dict[str, Path], work: Path, kind: str, data) -> Path:
    fmt = data.draw(st.sampled_from(["pth", "safetensors"]), label="format")
    path = work / files[fmt].name
    raw = files[fmt].read_bytes()
    if kind in ("truncated", "flipped", "empty"):
        at = data.draw(st.integers(0, len(raw) - 1), label="at")
        path.write_bytes({"truncated": raw[:at], "empty": b"",
                          "flipped": raw[:at] + bytes([raw[at] ^ 0xA5]) + raw[at + 1:]}[kind])
        return path
    if kind == "pickle payload":
        path = work / "tiny.pth"
        path.write_bytes(pickle.dumps({"model": {"w": _Payload(work / "pwned")}}))
        return path
    if kind == "torch pickle payload":
        path = work / "tiny.pth"
        torch.save({"model": {"w": _Payload(work / "pwned")}}, path)
        return path
    if kind == "zip not torch":
        path = work / "tiny.pth"
        with zipfile.ZipFile(path, "w") as z:
            z.writestr("archive/data.pkl", b"not a pickle")
            z.writestr("readme.txt", "hello")
        return path
    state = dict(torch.load(files["pth"], weights_only=True)["model"])
    key = data.draw(st.sampled_from(sorted(state)), label="key")
    if kind == "wrong shape":
        state[key] = torch.zeros(tuple(s + 1 for s in state[key].shape) or (2,))
    elif kind == "wrong dtype":
        state[key] = torch.zeros(state[key].shape, dtype=data.draw(st.sampled_from(
            [torch.int64, torch.bool, torch.uint8, torch.complex64]), label="dtype"))
    elif kind == "missing key":
        del state[key]
    elif kind == "nan":
        state[key] = state[key].clone()
        state[key].view(-1)[0] = data.draw(st.sampled_from([float("nan"), float("inf")]), label="value")
    if kind in ("not a tensor", "not a dict"):
        path = work / "tiny.pth"
        torch.save({"model": dict(state, extra=3)} if kind == "not a tensor" else [1, 2, 3], path)
    elif fmt == "pth":
        torch.save({"model": state}, path)
    else:
        from safetensors.torch import save_file
        save_file(state, str(path))
    return path


@settings(FUZZ, max_examples=2)
@given(data=st.data())
@pytest.mark.parametrize("kind", CHECKPOINT_DAMAGES)
def test_viclip_info_on_a_damaged_checkpoint_is_one_line_and_runs_no_pickled_code(viclip_files, tmp_path_factory,
                                                                                  capsys, kind, data):
    work = tmp_path_factory.mktemp("ckpt")
    path = _damaged_checkpoint(viclip_files, work, kind, data)
    argv = ["viclip-info", str(path), "--vocab", str(viclip_files["vocab"]), "--convert", str(work / "out.safetensors")]
    code, lines = _run(argv, capsys)
    assert not (work / "pwned").exists()
    if code == 0:
        assert kind in ("flipped", "wrong dtype")  # a flipped byte of a tensor's data changes one weight
        assert (work / "out.safetensors").is_file()
    else:
        _assert_one_line_naming(code, lines, path.name)
        assert sorted(p.name for p in work.iterdir()) == [path.name]


VOCAB_DAMAGES = ["empty", "garbage", "gzip of garbage", "truncated gzip", "header only", "three symbols",
                 "gzip bomb"]


@settings(FUZZ, max_examples=1)
@given(data=st.data())
@pytest.mark.parametrize("kind", VOCAB_DAMAGES)
def test_viclip_info_on_a_damaged_vocabulary_is_one_line(viclip_files, tmp_path_factory, capsys, kind, data):
    vocab = tmp_path_factory.mktemp("vocab") / "bpe_simple_vocab_16e6.txt.gz"
    good = viclip_files["vocab"].read_bytes()
    vocab.write_bytes({
        "empty": b"", "garbage": bytes(range(256)) * 4, "gzip of garbage": gzip.compress(bytes(range(128, 256)) * 8),
        "truncated gzip": good[:data.draw(st.integers(1, len(good) - 1))],
        "header only": gzip.compress(b"#version: 0.2\n"), "three symbols": gzip.compress(b"#version: 0.2\nh e l\n"),
        "gzip bomb": gzip.compress(b"#version: 0.2\n" + b"a b\n" * (MAX_VOCAB_BYTES >> 2))}[kind])
    code, lines = _run(["viclip-info", str(viclip_files["safetensors"]), "--vocab", str(vocab)], capsys)
    lines = [line for line in lines if not line.startswith(str(viclip_files["safetensors"]))]
    _assert_one_line_naming(code, lines, vocab.name)
    if kind == "gzip bomb":
        assert "more than 16 MiB of text" in lines[0]  # refused before it is unpacked whole


@pytest.mark.parametrize("kind", ["pickle payload", "wrong dtype", "vocab"])
def test_extract_with_a_damaged_viclip_checkpoint_or_vocabulary_is_one_line(viclip_files, tmp_path, capsys, kind):
    from _language_helpers import micro_bundle

    bundle = micro_bundle(tmp_path / "bundle", T=2, cameras=2)
    checkpoint, vocab = tmp_path / "tiny.pth", viclip_files["vocab"]
    if kind == "pickle payload":
        torch.save({"model": {"w": _Payload(tmp_path / "pwned")}}, checkpoint)
    elif kind == "wrong dtype":
        state = torch.load(viclip_files["pth"], weights_only=True)["model"]
        torch.save({"model": dict(state, temp=torch.zeros((), dtype=torch.int64))}, checkpoint)
    else:
        checkpoint, vocab = viclip_files["pth"], tmp_path / "bpe.txt.gz"
        vocab.write_bytes(b"\x1f\x8b garbage")
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    code, lines = _run(["extract", str(bundle), "--encoder", "viclip", "--checkpoint", str(checkpoint),
                        "--vocab", str(vocab), "--no-progress"], capsys)
    _assert_one_line_naming(code, lines, (vocab if kind == "vocab" else checkpoint).name)
    assert not (tmp_path / "pwned").exists()
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before


# ----------------------------------------------------------------------------------- bench commands
BENCH_READERS = {
    "compare": lambda bad, out: ["bench", "compare", bad, "--out", str(out / "cmp")],
    "fit-pareto": lambda bad, out: ["bench", "fit-pareto", bad, "--out", str(out / "pareto")],
    "fit": lambda bad, out: ["bench", "fit", "--dataset", bad, "--out", str(out / "fit"), "--timesteps", "2"],
    "fit-background": lambda bad, out: ["bench", "fit-background", "--dataset", bad, "--out", str(out / "bg")],
    "real-lift": lambda bad, out: ["bench", "real-lift", "--scene", bad, "--masks", bad],
    "real-annotations": lambda bad, out: ["bench", "real-annotations", "--scene", bad, "-o", str(out / "ann")],
    "device": lambda bad, out: ["bench", "device", "--size", "toy", "--device", "cpu", "--data", bad, "--out",
                                str(out / "dev")],
    "device-data": lambda bad, out: ["bench", "device-data", "--source", bad, "-o", str(out / "dd"),
                                     "--timesteps", "1"],
    "viclip": lambda bad, out: ["bench", "viclip", "--checkpoint", bad],
    "query-interactive": lambda bad, out: ["bench", "query-interactive", bad, "ball", "--json", str(out / "q.json")],
    "grounding": lambda bad, out: ["bench", "grounding", "--bundle", bad],
    "accuracy-time": lambda bad, out: ["bench", "accuracy-time", "--bundle", bad, "--out", str(out / "at")],
    "language-cost": lambda bad, out: ["bench", "language-cost", "--proxies", "real", "--real-scene", bad,
                                       "--masks", bad, "--out", str(out / "lc")],
}


@pytest.fixture(scope="module")
def bad_inputs(capture, tmp_path_factory) -> list[str]:
    root = tmp_path_factory.mktemp("bad")
    (root / "garbage.json").write_text("{not json")
    (root / "list.json").write_text("[1, 2]")
    (root / "empty").mkdir()
    damaged = Path(shutil.copytree(capture, root / "damaged-capture"))
    meta = json.loads((damaged / "train_meta.json").read_text())
    meta["k"][0][0] = "x"
    (damaged / "train_meta.json").write_text(json.dumps(meta))
    return [str(root / "missing"), str(root / "garbage.json"), str(root / "list.json"), str(root / "empty"),
            str(damaged)]


@pytest.mark.parametrize("bench", sorted(BENCH_READERS))
def test_bench_commands_on_bad_inputs_are_one_line_and_write_nothing(bench, bad_inputs, tmp_path, capsys):
    for bad in bad_inputs:
        code, lines = _run(BENCH_READERS[bench](bad, tmp_path), capsys)
        assert code not in (0, None) and lines and "error:" in lines[-1], (bench, bad, lines)
        assert not any(tmp_path.iterdir()), (bench, bad, sorted(p.name for p in tmp_path.iterdir()))


# ----------------------------------------------------------------------- annotation masks and presets
@pytest.fixture(scope="module")
def masks_scene(tmp_path_factory) -> tuple[Path, Path]:
    from _language_helpers import micro_bundle
    from fourlegs_engine.scene.bundle import load_bundle

    root = tmp_path_factory.mktemp("masks")
    bundle = micro_bundle(root / "micro", T=2)
    scene = load_bundle(bundle)
    for cam in scene.cameras.train[0]:
        (root / "person" / cam.name).mkdir(parents=True)
        for t in range(scene.num_timesteps):
            mask = np.zeros((cam.height, cam.width), np.uint8)
            mask[: cam.height // 2] = 255
            Image.fromarray(mask).save(root / "person" / cam.name / f"{t:06d}.png")
    return bundle, root / "person"


@pytest.mark.parametrize("kind", ["truncated", "empty", "text", "bomb", "wrong size"])
def test_language_with_a_damaged_annotation_mask_is_one_line_naming_it(masks_scene, tmp_path, capsys, kind):
    bundle, masks = masks_scene
    scene = Path(shutil.copytree(bundle, tmp_path / "scene"))
    folder = Path(shutil.copytree(masks, tmp_path / "person"))
    target = sorted(folder.rglob("*.png"))[-1]
    target.write_bytes(_image_bytes(kind, target.read_bytes(), 0.5))
    code, lines = _run(["language", str(scene), "--encoder", "masks", "--masks", f"a person={folder}",
                        "--no-progress"], capsys)
    assert code == 2 and lines and lines[-1].startswith("fourlegs: error:") and target.name in lines[-1], lines
    assert not (scene / "language").exists()


@settings(FUZZ, max_examples=6)
@given(data=st.data())
def test_plan_with_a_damaged_preset_file_is_one_line_naming_it(tmp_path_factory, capsys, data):
    from fourlegs_engine.highlights.presets import available_presets

    root = tmp_path_factory.mktemp("preset")
    text = Path(available_presets()["broadcast"]).read_bytes()
    how = data.draw(st.sampled_from(["truncated", "garbage", "not utf-8", "value"]))
    if how == "truncated":
        text = text[:data.draw(st.integers(0, len(text) - 1))]
    elif how == "garbage":
        text = bytes(range(256))
    elif how == "not utf-8":
        text = text.replace(b"broadcast", b"broad\xffcast", 1)
    else:
        key = data.draw(st.sampled_from([b"fps", b"resolution", b"factor", b"from", b"effect", b"speed"]))
        value = data.draw(st.sampled_from([b"nan", b"inf", b"-1", b"1e400", b'"x"', b"[[1]]", b"{a = 1}", b"true"]))
        lines = text.split(b"\n")
        at = next((i for i, line in enumerate(lines) if line.split(b"=")[0].strip() == key), 0)
        lines[at] = key + b" = " + value
        text = b"\n".join(lines)
    preset = root / "mine.toml"
    preset.write_bytes(text)
    # the preset is read before the scene: a preset still valid meets the missing scene next
    code, lines = _run(["plan", str(root / "no-scene"), "a ball", "--preset", str(preset), "-o",
                        str(root / "plan.json")], capsys)
    assert code == 2 and len(lines) == 1 and lines[0].startswith("fourlegs: error:"), lines
    assert "mine.toml" in lines[0] or "no-scene" in lines[0], lines
    assert sorted(p.name for p in root.iterdir()) == ["mine.toml"]
