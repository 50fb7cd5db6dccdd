"""Strict, pickle-free ViCLIP checkpoint loading in the official layout (.pth and -hf safetensors)."""
from __future__ import annotations

import sys
import types
from pathlib import Path

import pytest
import torch
from safetensors.torch import save_file

from fourlegs_engine.errors import InputError, OutputExistsError
from fourlegs_engine.language.viclip import checkpoint as ckpt
from fourlegs_engine.language.viclip.checkpoint import load_viclip, read_state_dict, save_viclip
from fourlegs_engine.language.viclip.model import ViCLIPConfig, ViCLIPModel

from _viclip_helpers import randomize_, tiny_config

MARKER_NAME = "pwned.txt"


@pytest.fixture(scope="module")
def tiny_model():
    torch.manual_seed(0)
    return randomize_(ViCLIPModel(tiny_config()).eval(), seed=3)


def _inputs(config, seed=0):
    gen = torch.Generator().manual_seed(seed)
    clips = torch.randn(2, config.num_frames, 3, config.image_size, config.image_size, generator=gen)
    tokens = torch.zeros(2, config.context_length, dtype=torch.long)
    tokens[0, :4] = torch.tensor([config.vocab_size - 2, 7, 300, config.vocab_size - 1])
    tokens[1, :3] = torch.tensor([config.vocab_size - 2, 515, config.vocab_size - 1])
    return clips, tokens


def _outputs(model, config):
    clips, tokens = _inputs(config)
    with torch.no_grad():
        return model.encode_video(clips), model.encode_tokens(tokens)


def _official_pth(model, path: Path) -> Path:
    """Exactly what the InternVid release holds: {'model': state_dict} written by torch.save."""
    torch.save({"model": {k: v.clone() for k, v in model.state_dict().items()}}, path)
    return path


@pytest.mark.parametrize("fmt", ["pth", "safetensors", "hf_dir", "saved_pth", "saved_safetensors"])
def test_round_trip_gives_identical_outputs(tiny_model, tmp_path, fmt):
    config = tiny_model.config
    if fmt == "pth":
        path = _official_pth(tiny_model, tmp_path / "ViClip-InternVid-10M-FLT.pth")
    elif fmt == "safetensors":
        path = tmp_path / "model.safetensors"
        save_file({k: v.contiguous() for k, v in tiny_model.state_dict().items()}, str(path))
    elif fmt == "hf_dir":
        (tmp_path / "ViCLIP-L-14-hf").mkdir()
        save_file({k: v.contiguous() for k, v in tiny_model.state_dict().items()},
                  str(tmp_path / "ViCLIP-L-14-hf" / "model.safetensors"))
        path = tmp_path / "ViCLIP-L-14-hf"
    else:
        path = save_viclip(tiny_model, tmp_path / ("w.pth" if fmt == "saved_pth" else "w.safetensors"))
    loaded = load_viclip(path)  # the configuration is read off the file
    assert loaded.config == config
    assert not loaded.training and not any(p.requires_grad for p in loaded.parameters())
    for ours, theirs in zip(_outputs(loaded, config), _outputs(tiny_model, config)):
        assert torch.equal(ours, theirs)


def test_saved_pth_has_official_structure(tiny_model, tmp_path):
    path = save_viclip(tiny_model, tmp_path / "w.pth")
    raw = torch.load(path, weights_only=True)
    assert list(raw) == ["model"]
    keys = set(raw["model"])
    assert "temp" in keys and "vision_encoder.temporal_positional_embedding" in keys
    assert {k.split(".")[0] for k in keys} == {"vision_encoder", "text_encoder", "temp"}
    with pytest.raises(OutputExistsError):
        save_viclip(tiny_model, path)
    assert not list(tmp_path.glob("*.part*"))  # nothing half-written left behind


def _state(model):
    return {k: v.clone() for k, v in model.state_dict().items()}


def test_missing_key_is_named_with_the_file(tiny_model, tmp_path):
    state = _state(tiny_model)
    del state["text_encoder.ln_final.bias"]
    path = tmp_path / "ViClip-InternVid-10M-FLT.pth"
    torch.save({"model": state}, path)
    with pytest.raises(InputError) as err:
        load_viclip(path, size=tiny_model.config)
    message = str(err.value)
    assert message.startswith(str(path))
    assert "missing keys (1): text_encoder.ln_final.bias" in message
    assert "unexpected" not in message and "shape" not in message


def test_unexpected_key_and_shape_mismatch_listed_together(tiny_model, tmp_path):
    state = _state(tiny_model)
    state["text_encoder.logit_bias"] = torch.zeros(1)
    state["vision_encoder.proj"] = torch.zeros(64, 40)
    del state["vision_encoder.ln_pre.weight"]
    path = tmp_path / "model.safetensors"
    save_file({k: v.contiguous() for k, v in state.items()}, str(path))
    with pytest.raises(InputError) as err:
        load_viclip(path, size=tiny_model.config)
    message = str(err.value)
    assert "model.safetensors" in message
    assert "missing keys (1): vision_encoder.ln_pre.weight" in message
    assert "unexpected keys (1): text_encoder.logit_bias" in message
    assert "shape mismatches (1): vision_encoder.proj (file (64, 40), model (64, 48))" in message


def test_wrong_size_lists_many_mismatches_briefly(tiny_model, tmp_path):
    path = _official_pth(tiny_model, tmp_path / "tiny.pth")
    with pytest.raises(InputError, match=r"does not match ViCLIP L/14: missing keys \(\d+\): .*and \d+ more"):
        load_viclip(path, size="l")


def test_not_a_viclip_state_dict(tmp_path):
    path = tmp_path / "other.pth"
    torch.save({"model": {"encoder.weight": torch.zeros(2, 2)}}, path)
    with pytest.raises(InputError, match="other.pth: state dict: not a ViCLIP checkpoint: key "
                                         "vision_encoder.conv1.weight is missing"):
        load_viclip(path)
    torch.save({"model": {"a": torch.zeros(1), "b": 3}}, path)
    with pytest.raises(InputError, match="entries that are not tensors: b"):
        read_state_dict(path)
    torch.save([torch.zeros(1)], path)
    with pytest.raises(InputError, match="expected a state dict under 'model'"):
        read_state_dict(path)


def test_missing_and_corrupt_files(tmp_path):
    with pytest.raises(InputError, match="checkpoint file is missing"):
        load_viclip(tmp_path / "ViClip-InternVid-10M-FLT.pth")
    with pytest.raises(InputError, match="holds no model.safetensors"):
        load_viclip(tmp_path)
    junk = tmp_path / "junk.pth"
    junk.write_bytes(b"not a checkpoint at all")
    with pytest.raises(InputError, match="junk.pth: not a readable torch checkpoint"):
        load_viclip(junk)
    junk_st = tmp_path / "junk.safetensors"
    junk_st.write_bytes(b"\x08\x00\x00\x00\x00\x00\x00\x00{broken}")
    with pytest.raises(InputError, match="junk.safetensors: not a readable safetensors file"):
        load_viclip(junk_st)


class _Payload:
    """Unpickling this object would create a marker file: it must never run."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def test_pickled_code_is_refused_and_never_runs(tiny_model, tmp_path):
    marker = tmp_path / MARKER_NAME
    state = _state(tiny_model)
    path = tmp_path / "ViClip-InternVid-10M-FLT.pth"
    torch.save({"model": state, "extra": _Payload(marker)}, path)
    assert not marker.exists()
    with pytest.raises(InputError, match="refused: the file holds pickled Python objects"):
        load_viclip(path)
    assert not marker.exists()


def _easydict_class():
    """A stand-in of ``easydict.EasyDict`` (items mirrored as attributes), pickled under that name."""
    class EasyDict(dict):
        def __init__(self, d=None, **kwargs):
            super().__init__()
            for key, value in dict(d or {}, **kwargs).items():
                setattr(self, key, value)

        def __setattr__(self, name, value):
            if isinstance(value, dict) and not isinstance(value, EasyDict):
                value = EasyDict(value)
            super().__setattr__(name, value)
            super().__setitem__(name, value)

        __setitem__ = __setattr__

    EasyDict.__module__, EasyDict.__qualname__ = "easydict", "EasyDict"
    return EasyDict


def test_training_checkpoint_with_easydict_config_loads(tiny_model, tmp_path, monkeypatch):
    easydict = types.ModuleType("easydict")
    easydict.EasyDict = _easydict_class()
    monkeypatch.setitem(sys.modules, "easydict", easydict)
    config = easydict.EasyDict(model={"vision_encoder": {"name": "vit_l14"}}, max_txt_l=32, lr=1e-5)
    path = tmp_path / "ViClip-InternVid-10M-FLT.pth"
    torch.save({"model": _state(tiny_model), "config": config, "epoch": 9}, path)
    monkeypatch.delitem(sys.modules, "easydict")  # the package is not needed to read the file
    loaded = load_viclip(path)
    for ours, theirs in zip(_outputs(loaded, tiny_model.config), _outputs(tiny_model, tiny_model.config)):
        assert torch.equal(ours, theirs)
    assert "easydict" not in sys.modules


def test_torch_load_is_called_with_weights_only(tiny_model, tmp_path, monkeypatch):
    calls = []
    real_load = torch.load

    def spy(*args, **kwargs):
        calls.append(kwargs)
        return real_load(*args, **kwargs)

    monkeypatch.setattr(ckpt.torch, "load", spy)
    load_viclip(_official_pth(tiny_model, tmp_path / "w.pth"))
    assert calls and all(call.get("weights_only") is True for call in calls)


def test_half_precision_and_ddp_prefix_are_accepted(tiny_model, tmp_path):
    state = {"module." + k: v.half() for k, v in tiny_model.state_dict().items()}
    path = tmp_path / "half.pth"
    torch.save({"model": state}, path)
    loaded = load_viclip(path)
    assert loaded.temp.dtype == torch.float32
    ours, theirs = _outputs(loaded, tiny_model.config), _outputs(tiny_model, tiny_model.config)
    for a, b in zip(ours, theirs):
        torch.testing.assert_close(a, b, rtol=0, atol=2e-2)  # half-precision weights, float32 compute


def test_explicit_size_must_be_known(tiny_model, tmp_path):
    path = _official_pth(tiny_model, tmp_path / "w.pth")
    with pytest.raises(InputError, match="unknown ViCLIP size 'xl'"):
        load_viclip(path, size="xl")
    assert load_viclip(path, size=tiny_model.config).config == tiny_model.config
    assert ViCLIPConfig.preset("B/16").embed_dim == 512
