"""The ViCLIP ``VideoTextEncoder``: contract, batching, validation, registry and CLI options."""
from __future__ import annotations

import argparse

import pytest
import torch

from fourlegs_engine.errors import InputError, OutputExistsError
from fourlegs_engine.language import encoders
from fourlegs_engine.commands.options import add_encoder_arguments, encoder_options_from_args
from fourlegs_engine.language.encoders import CANONICAL_PHRASES, VideoTextEncoder, get_encoder
from fourlegs_engine.pipeline import text_encoder
from fourlegs_engine.language.viclip import BPETokenizer, ViCLIPEncoder, ViCLIPModel, save_viclip
from fourlegs_engine.language.viclip.model import CLIP_MEAN, CLIP_STD, IMAGENET_MEAN, IMAGENET_STD

from _viclip_helpers import randomize_, tiny_config, write_tiny_vocab


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    root = tmp_path_factory.mktemp("viclip")
    torch.manual_seed(0)
    model = randomize_(ViCLIPModel(tiny_config()).eval(), seed=5)
    return model, save_viclip(model, root / "ViClip-tiny.pth"), write_tiny_vocab(root / "bpe.txt.gz")


@pytest.fixture(scope="module")
def encoder(files):
    _, checkpoint, vocab = files
    return ViCLIPEncoder.from_files(checkpoint, vocab, batch_size=2)


def _clips(batch, seed=0):
    gen = torch.Generator().manual_seed(seed)
    return torch.rand(batch, 8, 3, 32, 32, generator=gen)


def test_contract(encoder):
    assert isinstance(encoder, VideoTextEncoder)
    assert encoder.input_kind == "rgb" and encoder.dim == 48 and encoder.name == "viclip"
    assert CANONICAL_PHRASES == ("object", "things", "stuff", "texture")
    video = encoder.encode_video(encoder.normalize(_clips(5)))
    text = encoder.encode_text(["the cat", "hello", *CANONICAL_PHRASES])
    assert video.shape == (5, 48) and text.shape == (6, 48)
    assert video.dtype == text.dtype == torch.float32
    torch.testing.assert_close(video.norm(dim=-1), torch.ones(5), rtol=0, atol=1e-5)
    torch.testing.assert_close(text.norm(dim=-1), torch.ones(6), rtol=0, atol=1e-5)
    assert encoder.encode_text([]).shape == (0, 48)
    assert encoder.encode_video(torch.zeros(0, 8, 3, 32, 32)).shape == (0, 48)


def test_batching_does_not_change_results(files, encoder):
    model, _, vocab = files
    clips = encoder.normalize(_clips(5, seed=1))
    texts = ["the ball", "a cat", "hello hello", "the", "cat!"]
    one_shot = ViCLIPEncoder(model, BPETokenizer(vocab), batch_size=64)
    torch.testing.assert_close(encoder.encode_video(clips), one_shot.encode_video(clips), rtol=0, atol=1e-6)
    torch.testing.assert_close(encoder.encode_text(texts), one_shot.encode_text(texts), rtol=0, atol=1e-6)
    # the same as the model fed directly with the tokenizer's rows
    rows = BPETokenizer(vocab).tokenize(texts)
    with torch.no_grad():
        torch.testing.assert_close(encoder.encode_text(texts), model.encode_tokens(rows), rtol=0, atol=1e-6)


def test_normalization_statistics(files):
    model, _, vocab = files
    tok = BPETokenizer(vocab)
    clip_enc = ViCLIPEncoder(model, tok)
    imagenet_enc = ViCLIPEncoder(model, tok, normalization="imagenet")
    grey = torch.full((1, 8, 3, 32, 32), 0.5)
    expected = (0.5 - torch.tensor(CLIP_MEAN)) / torch.tensor(CLIP_STD)
    torch.testing.assert_close(clip_enc.normalize(grey)[0, 3, :, 7, 9], expected)
    torch.testing.assert_close(imagenet_enc.normalize(grey), clip_enc.normalize(grey))  # input is always CLIP
    # "clip" feeds the CLIP-normalized pixels unchanged; "imagenet" feeds ImageNet-normalized ones
    pixels = _clips(2, seed=7)
    with torch.no_grad():
        as_clip = model.encode_video(clip_enc.normalize(pixels))
        as_imagenet = model.encode_video((pixels - torch.tensor(IMAGENET_MEAN)[:, None, None])
                                         / torch.tensor(IMAGENET_STD)[:, None, None])
    torch.testing.assert_close(clip_enc.encode_video(clip_enc.normalize(pixels)), as_clip, rtol=0, atol=1e-6)
    torch.testing.assert_close(imagenet_enc.encode_video(clip_enc.normalize(pixels)), as_imagenet,
                               rtol=0, atol=1e-5)
    assert (as_clip - as_imagenet).abs().max() > 1e-4  # the choice matters
    assert clip_enc.config()["normalization"] == "clip" and imagenet_enc.config()["normalization"] == "imagenet"
    with pytest.raises(InputError, match="unknown normalization"):
        ViCLIPEncoder(model, tok, normalization="none")


def test_config_is_json_and_names_the_files(encoder, files):
    import json
    _, checkpoint, vocab = files
    config = json.loads(json.dumps(encoder.config()))
    assert config["checkpoint"] == checkpoint.name and config["vocab"] == vocab.name
    assert config["checkpoint_bytes"] == checkpoint.stat().st_size
    assert config["dim"] == 48 and config["num_frames"] == 8 and config["dtype"] == "float32"


@pytest.mark.parametrize("bad, match", [
    (torch.zeros(2, 8, 3, 32), r"clips must be \(B, 8, 3, 32, 32\), got \(2, 8, 3, 32\)"),
    (torch.zeros(2, 6, 3, 32, 32), r"got \(2, 6, 3, 32, 32\)"),
    (torch.zeros(2, 8, 4, 32, 32), r"got \(2, 8, 4, 32, 32\)"),
    (torch.zeros(2, 8, 3, 224, 224), r"got \(2, 8, 3, 224, 224\)"),
    (torch.zeros(1, 8, 3, 32, 32, dtype=torch.uint8), "floating point"),
    (torch.full((1, 8, 3, 32, 32), float("nan")), "NaN or Inf"),
])
def test_bad_clips_are_input_errors(encoder, bad, match):
    with pytest.raises(InputError, match=match) as err:
        encoder.encode_video(bad)
    assert err.value.field == "clips"


def test_vocab_must_fit_the_text_tower(files, tmp_path):
    model, _, _ = files
    other = BPETokenizer(write_tiny_vocab(tmp_path / "other.txt.gz", ["a b", "c d"]))
    with pytest.raises(InputError, match="other.txt.gz: the vocabulary has 516 ids but the model's text tower has 525"):
        ViCLIPEncoder(model, other)


def test_registry(files):
    _, checkpoint, vocab = files
    enc = get_encoder("viclip", checkpoint=checkpoint, vocab=vocab, device="cpu")
    assert isinstance(enc, ViCLIPEncoder) and enc.device == torch.device("cpu")
    with pytest.raises(InputError, match="needs a checkpoint"):
        get_encoder("viclip", vocab=vocab)
    with pytest.raises(InputError, match="needs the BPE vocabulary"):
        get_encoder("viclip", checkpoint=checkpoint)
    with pytest.raises(InputError, match="unknown encoder 'clip4'"):
        get_encoder("clip4")
    with pytest.raises(InputError, match="unknown option"):
        get_encoder("viclip", checkpoint=checkpoint, vocab=vocab, frames=4)
    # insisting on B/16 reports the mismatch against the published B/16 layout
    with pytest.raises(InputError, match="does not match ViCLIP B/16"):
        get_encoder("viclip-b16", checkpoint=checkpoint, vocab=vocab)
    assert {"viclip", "viclip-b16", "simulated"} <= set(encoders.encoder_names())
    simulated = get_encoder("simulated", labels=["person jumping", "ball flying"])  # imported on demand
    assert isinstance(simulated, VideoTextEncoder) and simulated.input_kind == "labels"
    assert simulated.encode_text(["a ball flying"]).shape == (1, simulated.dim)


def test_register_encoder_refuses_silent_override():
    with pytest.raises(ValueError, match="already registered"):
        encoders.register_encoder("viclip", lambda **kw: None)


def test_encoder_from_command_line_options(files):
    _, checkpoint, vocab = files
    parser = argparse.ArgumentParser()
    add_encoder_arguments(parser)
    args = parser.parse_args(["--encoder", "viclip", "--checkpoint", str(checkpoint), "--vocab", str(vocab),
                              "--device", "cpu", "--encoder-batch-size", "3", "--pixel-normalization", "imagenet"])
    enc = text_encoder(None, encoder_options_from_args(args))
    assert enc.batch_size == 3 and enc.normalization == "imagenet"
    assert enc.encode_text(["hello"]).shape == (1, 48)
    # a parser that defined only some of the options still works (defaults fill the rest)
    bare = argparse.Namespace(encoder="viclip", checkpoint=str(checkpoint), vocab=str(vocab))
    assert text_encoder(None, encoder_options_from_args(bare).replace(device="cpu")).dim == 48
    missing = parser.parse_args(["--vocab", str(vocab), "--device", "cpu"])
    with pytest.raises(InputError, match="--checkpoint"):
        text_encoder(None, encoder_options_from_args(missing))


def test_device_resolution():
    assert encoders.resolve_device("cpu") == torch.device("cpu")
    assert encoders.resolve_device("auto").type in ("cpu", "cuda")
    with pytest.raises(InputError, match="not a device"):
        encoders.resolve_device("quantum")
    if not torch.cuda.is_available():
        with pytest.raises(InputError, match="no CUDA device"):
            encoders.resolve_device("cuda")
    assert encoders.resolve_dtype("bfloat16") is torch.bfloat16
    assert encoders.resolve_dtype(torch.float64) is torch.float64
    with pytest.raises(InputError, match="unknown dtype 'int8'"):
        encoders.resolve_dtype("int8")


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_cpu(files):
    _, checkpoint, vocab = files
    cpu = ViCLIPEncoder.from_files(checkpoint, vocab)
    gpu = ViCLIPEncoder.from_files(checkpoint, vocab, device="cuda")
    clips = cpu.normalize(_clips(3, seed=2))
    out = gpu.encode_video(clips)
    assert out.device.type == "cpu"  # results come back to the clips' device
    torch.testing.assert_close(out, cpu.encode_video(clips), rtol=0, atol=1e-4)
    torch.testing.assert_close(gpu.encode_text(["hello"]).cpu(), cpu.encode_text(["hello"]), rtol=0, atol=1e-4)


def test_bench_reports_time_and_accuracy_per_knob(tmp_path):
    from fourlegs_bench.viclip import bench_viclip, write_report
    report = bench_viclip(size=tiny_config(), dtypes=("float32", "bfloat16"), batch_sizes=(1, 2), clips=2,
                          phrases=3, repeats=1, device="cpu")
    rows = {(r["dtype"], r["batch_size"]): r for r in report["rows"]}
    assert set(rows) == {("float32", 1), ("float32", 2), ("bfloat16", 1), ("bfloat16", 2)}
    assert all(r["seconds_per_clip"] > 0 and r["seconds_per_phrase"] > 0 and r["finite"] for r in rows.values())
    assert rows["float32", 1]["video_min_cosine"] > 1 - 1e-6  # float32 vs the float64 reference
    assert 0.9 < rows["bfloat16", 1]["video_min_cosine"] < rows["float32", 1]["video_min_cosine"]
    paths = write_report(report, tmp_path / "viclip")
    assert [p.suffix for p in paths] == [".json", ".md", ".png"] and all(p.stat().st_size > 0 for p in paths)
    assert "| bfloat16 | 2 |" in paths[1].read_text()


def test_viclip_info_command_checks_and_converts(files, tmp_path, capsys):
    from fourlegs_engine.commands import viclip as commands
    model, checkpoint, vocab = files
    parser = argparse.ArgumentParser()
    commands.register(parser.add_subparsers())
    out = tmp_path / "converted.safetensors"
    args = parser.parse_args(["viclip-info", str(checkpoint), "--vocab", str(vocab), "--convert", str(out)])
    assert args.func(args) == 0
    printed = capsys.readouterr().out
    params = sum(p.numel() for p in model.parameters())
    assert f"{params:,} parameters" in printed and "texture" in printed and f"written: {out}" in printed
    converted = ViCLIPEncoder.from_files(out, vocab)
    original = ViCLIPEncoder.from_files(checkpoint, vocab)
    clips = original.normalize(_clips(2, seed=3))
    assert torch.equal(converted.encode_video(clips), original.encode_video(clips))
    with pytest.raises(OutputExistsError):  # an existing output is not overwritten unless asked
        args.func(args)
