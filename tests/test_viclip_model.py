"""ViCLIP architecture: shapes, normalization, the official forward pass (float64 oracle), sizes."""
from __future__ import annotations

import math

import pytest
import torch

from fourlegs_engine.language.viclip.model import (ViCLIPConfig, ViCLIPModel, expected_shapes, infer_config,
                                                   l2_normalize)

from _viclip_helpers import TINY_VOCAB_SIZE, oracle_text, oracle_video, randomize_, tiny_config


@pytest.fixture(scope="module")
def model64():
    torch.manual_seed(0)
    # two heads per tower, so the head split and merge are checked against the oracle too
    config = tiny_config(patch_size=8, vision_heads=2, text_heads=2)
    return randomize_(ViCLIPModel(config).double().eval(), seed=1)


def _clips(batch=3, frames=8, seed=0, size=32):
    gen = torch.Generator().manual_seed(seed)
    return torch.randn(batch, frames, 3, size, size, generator=gen, dtype=torch.float64)


def _tokens(config, lengths=(5, 1, 12), seed=0):
    """Rows [sot, words..., eot, 0...] with eot = the largest id, as the tokenizer makes them."""
    gen = torch.Generator().manual_seed(seed)
    sot, eot = config.vocab_size - 2, config.vocab_size - 1
    rows = torch.zeros(len(lengths), config.context_length, dtype=torch.long)
    for r, n in enumerate(lengths):
        words = torch.randint(0, sot, (n,), generator=gen)
        rows[r, : n + 2] = torch.cat([torch.tensor([sot]), words, torch.tensor([eot])])
    return rows


def test_forward_shapes_and_unit_norm():
    config = tiny_config()
    model = ViCLIPModel(config).eval()
    with torch.no_grad():
        video = model.encode_video(_clips().float())
        text = model.encode_tokens(_tokens(config))
    assert video.shape == (3, config.embed_dim) and text.shape == (3, config.embed_dim)
    assert video.dtype == torch.float32
    torch.testing.assert_close(video.norm(dim=-1), torch.ones(3), rtol=0, atol=1e-6)
    torch.testing.assert_close(text.norm(dim=-1), torch.ones(3), rtol=0, atol=1e-6)


def test_video_tower_matches_float64_oracle(model64):
    clips = _clips()
    with torch.no_grad():
        ours = model64.vision_encoder(clips.permute(0, 2, 1, 3, 4))
    ref = oracle_video(model64.state_dict(), model64.config, clips)
    assert ours.abs().max() > 0.1  # a real, non-degenerate output
    torch.testing.assert_close(ours, ref, rtol=1e-10, atol=1e-10)


def test_still_image_uses_mean_temporal_embedding(model64):
    clips = _clips(batch=2, frames=1)
    with torch.no_grad():
        ours = model64.vision_encoder(clips.permute(0, 2, 1, 3, 4))
    torch.testing.assert_close(ours, oracle_video(model64.state_dict(), model64.config, clips),
                               rtol=1e-10, atol=1e-10)


def test_text_tower_matches_float64_oracle(model64):
    tokens = _tokens(model64.config)
    with torch.no_grad():
        ours = model64.text_encoder(tokens)
    ref = oracle_text(model64.state_dict(), model64.config, tokens)
    assert ours.abs().max() > 0.1
    torch.testing.assert_close(ours, ref, rtol=1e-10, atol=1e-10)


def test_text_is_causal_and_pooled_at_end_token(model64):
    tokens = _tokens(model64.config, lengths=(4, 4))
    tokens[1] = tokens[0]
    tokens[1, 8:] = torch.randint(1, 100, (tokens.shape[1] - 8,))  # garbage after eot (position 5)
    with torch.no_grad():
        out = model64.text_encoder(tokens)
    torch.testing.assert_close(out[0], out[1], rtol=0, atol=1e-12)
    # a word before the end token does change the embedding
    tokens[1, 2] = (tokens[1, 2] + 1) % 500
    with torch.no_grad():
        changed = model64.text_encoder(tokens)
    assert (changed[0] - changed[1]).abs().max() > 1e-6


def test_frame_order_matters_only_through_temporal_embedding(model64):
    clips = _clips(batch=1)
    shuffled = clips[:, torch.tensor([3, 1, 7, 0, 2, 6, 5, 4])]
    video = lambda c: model64.vision_encoder(c.permute(0, 2, 1, 3, 4))
    with torch.no_grad():
        assert (video(clips) - video(shuffled)).abs().max() > 1e-6
        saved = model64.vision_encoder.temporal_positional_embedding.clone()
        model64.vision_encoder.temporal_positional_embedding.zero_()
        try:
            # joint space-time attention is permutation-equivariant: with no temporal embedding the
            # class token cannot tell the frame order
            torch.testing.assert_close(video(clips), video(shuffled), rtol=1e-10, atol=1e-10)
        finally:
            model64.vision_encoder.temporal_positional_embedding.copy_(saved)


def test_batch_members_are_independent(model64):
    clips = _clips(batch=3, seed=4)
    with torch.no_grad():
        together = model64.encode_video(clips)
        alone = torch.cat([model64.encode_video(clips[i:i + 1]) for i in range(3)])
    torch.testing.assert_close(together, alone, rtol=1e-10, atol=1e-12)


def test_half_precision_layer_norm_stays_finite():
    model = ViCLIPModel(tiny_config()).to(torch.bfloat16).eval()
    with torch.no_grad():
        out = model.encode_video(_clips(batch=2).to(torch.bfloat16) * 50)  # large pixels
    assert out.dtype == torch.bfloat16 and bool(torch.isfinite(out).all())
    torch.testing.assert_close(out.float().norm(dim=-1), torch.ones(2), rtol=0, atol=2e-2)


def test_l2_normalize_zero_row_stays_finite():
    x = torch.tensor([[0.0, 0.0], [3.0, 4.0], [1e-30, 0.0]])
    out = l2_normalize(x)
    assert bool(torch.isfinite(out).all())
    torch.testing.assert_close(out[1], torch.tensor([0.6, 0.8]))
    assert out[0].abs().max() == 0


# Parameter counts: OpenAI CLIP ViT-L/14 has 427,616,513 and ViT-B/16 149,620,737 parameters;
# ViCLIP shortens the text context from 77 to 32 positions (-45 x text width) and adds the temporal
# embedding (+8 x vision width); its "temp" replaces CLIP's logit_scale one for one.
@pytest.mark.parametrize("size, width, patch, layers, dim, text_width, params", [
    ("L/14", 1024, 14, 24, 768, 768, 427_616_513 - 45 * 768 + 8 * 1024),
    ("B/16", 768, 16, 12, 512, 512, 149_620_737 - 45 * 512 + 8 * 768),
])
def test_published_sizes_key_layout(size, width, patch, layers, dim, text_width, params):
    config = ViCLIPConfig.preset(size)
    shapes = expected_shapes(config)  # meta device: no memory
    grid = 224 // patch
    assert shapes["vision_encoder.conv1.weight"] == (width, 3, 1, patch, patch)
    assert shapes["vision_encoder.positional_embedding"] == (grid * grid + 1, width)
    assert shapes["vision_encoder.temporal_positional_embedding"] == (1, 8, width)
    assert shapes["vision_encoder.class_embedding"] == (width,)
    assert shapes["vision_encoder.proj"] == (width, dim)
    assert shapes[f"vision_encoder.transformer.resblocks.{layers - 1}.attn.in_proj_weight"] == (3 * width, width)
    assert f"vision_encoder.transformer.resblocks.{layers}.ln_1.weight" not in shapes
    assert shapes["text_encoder.token_embedding.weight"] == (49408, text_width)
    assert shapes["text_encoder.positional_embedding"] == (32, text_width)
    assert shapes["text_encoder.text_projection"] == (text_width, dim)
    assert shapes["text_encoder.transformer.resblocks.11.mlp.c_fc.weight"] == (4 * text_width, text_width)
    assert shapes["temp"] == ()
    assert sum(math.prod(s) for s in shapes.values()) == params
    assert infer_config(shapes) == config
    assert config.size_name == size


def test_config_validation():
    with pytest.raises(ValueError, match="multiple of patch_size"):
        tiny_config(image_size=30).validate()
    with pytest.raises(ValueError, match="divisible"):
        tiny_config(text_heads=3).validate()
    with pytest.raises(ValueError, match="unknown ViCLIP size"):
        ViCLIPConfig.preset("xl")
    assert tiny_config().vocab_size == TINY_VOCAB_SIZE


@pytest.mark.parametrize("frames", [8, 1])
def test_video_clip_flops_match_torchs_flop_counter(frames):
    """The analytic count equals torch's FlopCounterMode on the math attention path (which it can see)."""
    from torch.nn.attention import SDPBackend, sdpa_kernel
    from torch.utils.flop_counter import FlopCounterMode

    from fourlegs_engine.language.viclip.model import video_clip_flops
    config = tiny_config(num_frames=frames, vision_layers=3)
    model = ViCLIPModel(config).double().eval()
    clips = torch.randn(2, frames, 3, config.image_size, config.image_size, dtype=torch.float64)
    with torch.no_grad(), sdpa_kernel(SDPBackend.MATH), FlopCounterMode(display=False) as counter:
        model.encode_video(clips)
    counts = {str(op).split(".")[-1]: n for op, n in counter.get_flop_counts()["Global"].items()}
    flops = video_clip_flops(config)
    assert counts.pop("bmm") == 2 * flops["attention"]
    assert sum(counts.values()) == 2 * flops["matmul"] and flops["total"] == flops["matmul"] + flops["attention"]
    large = video_clip_flops(ViCLIPConfig.large())
    assert large["total"] == 1_652_741_996_544  # ViT-L/14, 8 frames: 2049 tokens, 24 blocks of width 1024
