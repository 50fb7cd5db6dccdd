"""Issue #24, items 1, 4, 7 and 9: the language field survives an interrupted ``distill --overwrite``,
records the autoencoder it was distilled with, refuses pickled/garbage/NaN decoders and NaN latents
with one line naming the file."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from _language_helpers import kill_after_first_step, micro_bundle, one_thread  # noqa: F401 (one_thread: autouse fixture)
from fourlegs_engine.commands.main import main
from fourlegs_engine.errors import InputError
from fourlegs_engine.language.autoencoder import load_decoder, weights_fingerprint
from fourlegs_engine.language.field import LanguageField

AE_ARGS = ["--epochs", "2", "--samples", "2048", "--ae-batch-size", "256"]


@pytest.fixture(scope="module")
def distilled(tmp_path_factory) -> Path:
    """Micro bundle with features, autoencoder and a lifted field (through the CLI)."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    path = micro_bundle(tmp_path_factory.mktemp("field") / "micro")
    assert main(["extract", str(path), "--no-progress"]) == 0
    assert main(["train-ae", str(path), *AE_ARGS]) == 0
    assert main(["distill", str(path), "--no-progress"]) == 0
    torch.set_num_threads(old)
    return path


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def _query_error(capsys, path: Path) -> str:
    code = main(["query", str(path), "person jumping", "--no-spatial"])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err, err
    return err.strip().splitlines()[-1]


class _Evil:
    def __reduce__(self):
        return (os.system, ("touch EXECUTED",))


# ------------------------------------------------------------------ item 7: pickled or garbage decoder
@pytest.mark.parametrize("kind", ["pickled", "legacy-pickled", "garbage", "empty", "tensor", "nan"])
def test_a_bad_decoder_is_one_line_naming_it(distilled, tmp_path, capsys, monkeypatch, kind):
    path = _copy(distilled, tmp_path / "b")
    decoder = path / "language" / "decoder.pt"
    monkeypatch.chdir(tmp_path)
    if kind == "pickled":
        torch.save({"net.0.weight": _Evil()}, decoder)
    elif kind == "legacy-pickled":
        torch.save({"net.0.weight": _Evil()}, decoder, _use_new_zipfile_serialization=False)
    elif kind == "garbage":
        decoder.write_bytes(b"\x80\x04garbage" * 50)
    elif kind == "empty":
        decoder.write_bytes(b"")
    elif kind == "tensor":
        torch.save(torch.zeros(3), decoder)
    else:
        state = torch.load(decoder, weights_only=True)
        state["net.0.weight"][0, 0] = float("nan")
        torch.save(state, decoder)
    with pytest.raises(InputError) as exc:
        load_decoder(decoder)
    assert exc.value.file == str(decoder)
    if kind.endswith("pickled"):
        assert "pickled objects are never loaded" in str(exc.value)
        assert "weights_only" not in str(exc.value) and "likely succeed" not in str(exc.value)
    if kind == "nan":
        assert "NaN" in str(exc.value)
    line = _query_error(capsys, path)
    assert "decoder.pt" in line
    assert not (tmp_path / "EXECUTED").exists()


def test_viclip_refusal_does_not_suggest_weights_only_false(tmp_path, monkeypatch):
    from fourlegs_engine.language.viclip.checkpoint import _read_torch
    monkeypatch.chdir(tmp_path)
    torch.save({"model": _Evil()}, tmp_path / "v.pt", _use_new_zipfile_serialization=False)
    with pytest.raises(InputError) as exc:
        _read_torch(tmp_path / "v.pt")
    assert "pickled objects are refused" in str(exc.value)
    assert "likely succeed" not in str(exc.value) and "weights_only` set to `False" not in str(exc.value)
    assert not (tmp_path / "EXECUTED").exists()


# ---------------------------------------------------------------------- item 9: NaN latents
@pytest.mark.parametrize("share", ["all", "part"])
def test_nan_latents_are_refused_naming_the_file(distilled, tmp_path, capsys, share):
    path = _copy(distilled, tmp_path / "b")
    lat_path = path / "language" / "latents.npy"
    lat = np.load(lat_path)
    if share == "all":
        lat[:] = np.nan
    else:
        lat[2, 5:9] = np.nan
    np.save(lat_path, lat)
    with pytest.raises(InputError, match="NaN") as exc:
        LanguageField.open(path)
    assert exc.value.file == str(lat_path)
    assert "latents.npy" in _query_error(capsys, path)


# ------------------------------------------------- item 4: a field bound to its autoencoder
def test_a_retrained_autoencoder_is_noticed_and_refused(distilled, tmp_path, capsys):
    path = _copy(distilled, tmp_path / "b")
    lang = json.loads((path / "scene.json").read_text())["language"]
    assert lang["decoder_fingerprint"] == weights_fingerprint(load_decoder(path / "language" / "decoder.pt"))
    assert main(["train-ae", str(path), "--epochs", "3", "--samples", "2048", "--ae-batch-size", "256",
                 "--overwrite"]) == 0
    capsys.readouterr()
    line = _query_error(capsys, path)
    assert "distilled with another autoencoder" in line and "distill --overwrite" in line
    assert main(["distill", str(path), "--overwrite", "--no-progress"]) == 0
    assert main(["query", str(path), "person jumping", "--no-spatial"]) == 0


def test_an_older_field_without_fingerprint_is_checked_through_the_autoencoder_hash(distilled, tmp_path):
    path = _copy(distilled, tmp_path / "b")
    meta = json.loads((path / "scene.json").read_text())
    del meta["language"]["decoder_fingerprint"]
    (path / "scene.json").write_text(json.dumps(meta))
    LanguageField.open(path)  # same autoencoder: opens
    report = json.loads((path / "language" / "autoencoder.json").read_text())
    report["config_hash"] = "0" * 16
    (path / "language" / "autoencoder.json").write_text(json.dumps(report))
    with pytest.raises(InputError, match="another autoencoder"):
        LanguageField.open(path)


# ------------------------------------------- item 1: distill --overwrite keeps the old field readable
CODE = ("import sys, torch; torch.set_num_threads(1); from fourlegs_engine.commands.main import main; "
        "sys.exit(main(sys.argv[1:]))")


def test_an_interrupted_distill_overwrite_keeps_the_old_field(distilled, tmp_path):
    path = _copy(distilled, tmp_path / "b")
    old = np.load(path / "language" / "latents.npy")
    old_meta = json.loads((path / "scene.json").read_text())
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    args = ["distill", str(path), "--mode", "optimize", "--iterations", "20", "--no-progress", "--overwrite"]
    steps = path / "language" / "steps"
    kill_after_first_step([sys.executable, "-c", CODE, *args], env, steps)
    # the old field is untouched and readable: info, query and the field itself
    np.testing.assert_array_equal(np.load(path / "language" / "latents.npy"), old)
    assert json.loads((path / "scene.json").read_text())["language"] == old_meta["language"]
    assert main(["info", str(path)]) == 0
    LanguageField.open(path)
    assert main(["query", str(path), "person jumping", "--no-spatial"]) == 0
    # the same command resumes and then swaps the new field in
    subprocess.run([sys.executable, "-c", CODE, *args], env=env, check=True, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL, timeout=300)
    meta = json.loads((path / "scene.json").read_text())
    assert meta["language"]["mode"] == "optimize" and not steps.exists()
    new = np.load(path / meta["language"]["latents"])
    assert new.shape == old.shape and not np.array_equal(new, old)
    LanguageField.open(path)


def test_a_swap_cut_short_leaves_a_readable_field_and_is_finished_later(distilled, tmp_path, monkeypatch):
    import fourlegs_engine.language.latents_file as distill

    path = _copy(distilled, tmp_path / "b")

    def killed(*_):
        raise KeyboardInterrupt

    monkeypatch.setattr(distill.os, "link", killed)
    assert main(["distill", str(path), "--teacher-stride", "1", "--overwrite", "--no-progress"]) == 130
    monkeypatch.undo()
    meta = json.loads((path / "scene.json").read_text())
    assert meta["language"]["latents"] == "language/latents.next.npy"   # the new field, complete
    assert LanguageField.open(path).config_hash == meta["language"]["config_hash"]
    assert main(["distill", str(path), "--teacher-stride", "1", "--overwrite", "--no-progress"]) == 0
    meta = json.loads((path / "scene.json").read_text())
    assert meta["language"]["latents"] == "language/latents.npy" and meta["arrays"]["latents"] == "language/latents.npy"
    assert not (path / "language" / "latents.next.npy").exists()
    LanguageField.open(path)
