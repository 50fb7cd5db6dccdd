"""Issue #30, items 1-4: nothing a resume or an ``--overwrite`` trusts is lost or poisoned.

A feature or step file holding NaN/Inf, cut short, of the wrong shape or dtype, or whose bytes differ from
the checksum written with it is never skipped as done nor merged; ``train-ae`` checks its options and its
inputs before it replaces anything and keeps the old autoencoder until a finite new one is complete.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from _language_helpers import micro_bundle, one_thread  # noqa: F401 (one_thread: autouse fixture)
from fourlegs_engine.commands.main import main
from fourlegs_engine.errors import InputError
from fourlegs_engine.language.store import StepStore

AE_ARGS = ["--epochs", "2", "--samples", "2048", "--ae-batch-size", "256"]
T = 4


@pytest.fixture(scope="module")
def distilled(tmp_path_factory) -> Path:
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    path = micro_bundle(tmp_path_factory.mktemp("resume") / "micro", T=T)
    assert main(["extract", str(path), "--no-progress"]) == 0
    assert main(["train-ae", str(path), *AE_ARGS]) == 0
    assert main(["distill", str(path), "--no-progress"]) == 0
    torch.set_num_threads(old)
    return path


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def _last_line(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    return err.strip().splitlines()[-1]


def _poison(path: Path, value: float) -> None:
    arr = np.load(path)
    arr.reshape(-1)[len(arr.reshape(-1)) // 2] = value
    np.save(path, arr)


def _ae_files(path: Path) -> dict[str, bytes]:
    return {name: (path / "language" / name).read_bytes() for name in ("encoder.pt", "decoder.pt", "autoencoder.json")}


# --------------------------------------------------------- item 1: NaN features never reach the weights
@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_train_ae_overwrite_on_poisoned_features_keeps_the_autoencoder(distilled, tmp_path, capsys, value):
    path = _copy(distilled, tmp_path / "b")
    before = _ae_files(path)
    _poison(path / "features" / "t000003.npy", value)
    assert main(["train-ae", str(path), *AE_ARGS, "--seed", "1", "--overwrite"]) == 2
    line = _last_line(capsys)
    assert "t000003.npy" in line and "NaN or Inf" in line, line
    assert _ae_files(path) == before


def test_language_recomputes_a_poisoned_feature_file(distilled, tmp_path, capsys):
    path = _copy(distilled, tmp_path / "b")
    good = np.load(path / "features" / "t000002.npy")
    _poison(path / "features" / "t000002.npy", np.nan)
    assert main(["extract", str(path), "--no-progress"]) == 0
    assert "1 timestep(s) encoded" in capsys.readouterr().out
    again = np.load(path / "features" / "t000002.npy")
    assert np.array_equal(again, good)


def test_a_diverging_training_writes_nothing(distilled, tmp_path, capsys, monkeypatch):
    from fourlegs_engine.language import autoencoder

    path = _copy(distilled, tmp_path / "b")
    before = _ae_files(path)
    real = autoencoder.reconstruction_loss
    monkeypatch.setattr(autoencoder, "reconstruction_loss", lambda p, t: real(p, t) * float("nan"))
    assert main(["train-ae", str(path), *AE_ARGS, "--seed", "2", "--overwrite"]) == 2
    assert "diverged" in _last_line(capsys)
    assert _ae_files(path) == before
    assert not (path / "language" / "autoencoder.ckpt.pt").exists()


# ------------------------------------------------------- item 3: arguments checked before anything goes
@pytest.mark.parametrize("argv, field", [(["--lr", "-1"], "--lr"), (["--lr", "nan"], "--lr"),
                                         (["--lr", "inf"], "--lr"), (["--lr", "0"], "--lr"),
                                         (["--holdout-camera", "99"], "--holdout-camera"),
                                         (["--seed", "-1"], "--seed"), (["--epochs", "0"], "--epochs"),
                                         (["--samples", "100000000000"], "--samples")])
def test_train_ae_overwrite_with_a_bad_argument_deletes_nothing(distilled, tmp_path, capsys, argv, field):
    path = _copy(distilled, tmp_path / "b")
    before = _ae_files(path)
    assert main(["train-ae", str(path), *AE_ARGS, *argv, "--overwrite"]) == 2
    assert field in _last_line(capsys)
    assert _ae_files(path) == before


@pytest.mark.parametrize("content", ["[1, 2]", "{\"config_hash\": 5}"])
def test_an_autoencoder_report_that_is_not_an_object_is_one_line(distilled, tmp_path, capsys, content):
    path = _copy(distilled, tmp_path / "b")
    (path / "language" / "autoencoder.json").write_text(content)
    assert main(["train-ae", str(path), *AE_ARGS]) == 2
    assert "autoencoder.json" in _last_line(capsys)
    assert main(["distill", str(path), "--no-progress", "--overwrite", "--teacher-stride", "2"]) == 2
    assert "autoencoder.json" in _last_line(capsys)


# ---------------------------------------------------------- item 2: a poisoned step file is not merged
def test_a_resumed_distill_recomputes_a_nan_step_file(distilled, tmp_path, capsys):
    path = _copy(distilled, tmp_path / "b")
    reference = np.load(path / "language" / "latents.npy")
    argv = ["distill", str(path), "--no-progress", "--teacher-stride", "2", "--overwrite"]
    assert main([*argv, "--timesteps", "0:3"]) == 0
    _poison(path / "language" / "steps" / "t000001.npy", np.nan)
    assert main(argv) == 0
    assert "2 timestep(s) distilled, 2 already done" in capsys.readouterr().out
    merged = np.load(path / "language" / "latents.npy")
    assert np.isfinite(merged).all() and merged.shape == reference.shape
    fresh = _copy(distilled, tmp_path / "fresh")
    assert main(["distill", str(fresh), "--no-progress", "--teacher-stride", "2", "--overwrite"]) == 0
    assert np.array_equal(merged, np.load(fresh / "language" / "latents.npy"))


def test_a_step_file_holding_nan_is_neither_done_nor_loaded_for_a_merge(tmp_path):
    store = StepStore(tmp_path / "steps", "latents", {"a": 1}, 2, shape_of=lambda t: (5, 4), dtype="float16").open()
    store.save(0, np.zeros((5, 4), np.float16))
    store.save(1, np.full((5, 4), np.nan, np.float16))
    assert store.is_done(0) and not store.is_done(1) and store.missing() == [1]
    with pytest.raises(InputError, match=r"t000001\.npy: latents timestep 1: contains NaN or Inf"):
        store.load_verified(1)


# ------------------------------------------------------------ item 4: resume verifies finished files
def _damage(path: Path, kind: str) -> None:
    arr = np.load(path)
    if kind == "truncated":
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "shape":
        np.save(path, arr[:-1])
    elif kind == "dtype":
        np.save(path, arr.astype(np.float32))
    elif kind == "strings":
        np.save(path, np.array(["a", "b"]))
    elif kind == "body":  # same size, one value changed: only the checksum sees it
        arr = arr.copy()
        arr.reshape(-1)[0] = arr.reshape(-1)[0] + np.float16(0.5)
        np.save(path, arr)


@pytest.mark.parametrize("kind", ["truncated", "empty", "shape", "dtype", "strings", "body"])
def test_a_damaged_feature_file_is_not_skipped_as_done(distilled, tmp_path, capsys, kind):
    path = _copy(distilled, tmp_path / "b")
    good = np.load(path / "features" / "t000003.npy")
    _damage(path / "features" / "t000003.npy", kind)
    assert main(["extract", str(path), "--check"]) == 1
    report = json.loads(capsys.readouterr().out)
    assert [b["t"] for b in report["bad"]] == [3], report
    assert main(["extract", str(path), "--no-progress"]) == 0
    assert "1 timestep(s) encoded" in capsys.readouterr().out
    assert np.array_equal(np.load(path / "features" / "t000003.npy"), good)


@pytest.mark.parametrize("kind", ["truncated", "shape", "dtype", "strings", "body"])
def test_train_ae_names_a_damaged_feature_file(distilled, tmp_path, capsys, kind):
    path = _copy(distilled, tmp_path / "b")
    _damage(path / "features" / "t000001.npy", kind)
    assert main(["train-ae", str(path), *AE_ARGS, "--seed", "3"]) == 2
    assert "t000001.npy" in _last_line(capsys)


def test_labels_outside_the_vocabulary_are_refused(distilled, tmp_path, capsys):
    path = _copy(distilled, tmp_path / "b")
    labels = np.load(path / "labels.npy")
    labels[0, 0] = 999
    np.save(path / "labels.npy", labels)
    shutil.rmtree(path / "features")
    assert main(["extract", str(path), "--no-progress"]) == 2
    line = _last_line(capsys)
    assert "labels" in line and "999" in line, line
    assert not (path / "features").exists()


def test_a_vocabulary_that_is_not_text_is_refused(distilled, tmp_path, capsys):
    path = _copy(distilled, tmp_path / "b")
    meta = json.loads((path / "scene.json").read_text())
    meta["metadata"]["labels"] = [1, 2, 3]
    (path / "scene.json").write_text(json.dumps(meta))
    assert main(["extract", str(path), "--no-progress", "--overwrite"]) == 2
    assert "metadata.labels" in _last_line(capsys)
