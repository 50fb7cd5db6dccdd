"""Shared pieces of the ViCLIP tests: a tiny vocabulary, a tiny configuration and a float64 oracle.

The oracle re-derives the official forward pass independently of ``fourlegs_engine``: sequence-first
tensors, ``torch.nn.MultiheadAttention`` fed with the same weights, an explicit additive -inf causal
mask, and the official token bookkeeping (per-frame class tokens of which the first B are kept).
"""
from __future__ import annotations

import gzip
from pathlib import Path

import torch
import torch.nn.functional as F

from fourlegs_engine.language.viclip.model import ViCLIPConfig

# Merge list of the tiny vocabulary, in priority order (rank = index).
TINY_MERGES = ["h e", "l l", "he ll", "hell o</w>", "t h", "th e</w>", "c a", "ca t</w>", "b a", "l l</w>",
               "ba ll</w>"]
TINY_VOCAB_SIZE = 256 * 2 + len(TINY_MERGES) + 2


def write_tiny_vocab(path: Path, merges=TINY_MERGES, *, compress: bool = True) -> Path:
    """The published file's format: a header line, then one merge per line, gzip'd."""
    text = "#version: 0.2\n" + "\n".join(merges) + "\n"
    path.write_bytes(gzip.compress(text.encode("utf-8")) if compress else text.encode("utf-8"))
    return path


def tiny_config(**changes) -> ViCLIPConfig:
    """Small enough for milliseconds, widths multiples of 64 so the head count can be inferred."""
    base = ViCLIPConfig(image_size=32, patch_size=16, num_frames=8, vision_width=64, vision_layers=2,
                        vision_heads=1, embed_dim=48, vocab_size=TINY_VOCAB_SIZE, context_length=32,
                        text_width=64, text_layers=2, text_heads=1)
    return base.with_(**changes)


def randomize_(model: torch.nn.Module, seed: int = 0) -> torch.nn.Module:
    """Give every parameter non-trivial values (biases, LayerNorm gains, temporal embedding too)."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, param in model.named_parameters():
            noise = torch.randn(param.shape, generator=gen, dtype=torch.float64)
            scale = 0.3 if param.ndim <= 1 else param.shape[-1] ** -0.5
            value = noise * scale
            if "ln_" in name and name.endswith("weight"):  # LayerNorm gains near 1
                value = 1.0 + 0.1 * noise
            param.copy_(value.to(param.dtype))
    return model


def _block(x, state, prefix, heads, mask=None):
    """One official residual block, sequence-first x (L, N, W)."""
    width = x.shape[-1]
    attn = torch.nn.MultiheadAttention(width, heads, dtype=torch.float64)
    attn.load_state_dict({
        "in_proj_weight": state[prefix + "attn.in_proj_weight"],
        "in_proj_bias": state[prefix + "attn.in_proj_bias"],
        "out_proj.weight": state[prefix + "attn.out_proj.weight"],
        "out_proj.bias": state[prefix + "attn.out_proj.bias"],
    })
    h = F.layer_norm(x, (width,), state[prefix + "ln_1.weight"], state[prefix + "ln_1.bias"])
    x = x + attn(h, h, h, need_weights=False, attn_mask=mask)[0]
    h = F.layer_norm(x, (width,), state[prefix + "ln_2.weight"], state[prefix + "ln_2.bias"])
    h = F.linear(h, state[prefix + "mlp.c_fc.weight"], state[prefix + "mlp.c_fc.bias"])
    h = h * torch.sigmoid(1.702 * h)
    return x + F.linear(h, state[prefix + "mlp.c_proj.weight"], state[prefix + "mlp.c_proj.bias"])


def oracle_video(state: dict, config: ViCLIPConfig, clips: torch.Tensor) -> torch.Tensor:
    """clips (B, T, 3, H, W) -> (B, D) unnormalized, in float64, the official way."""
    s = {k[len("vision_encoder."):]: v.double() for k, v in state.items() if k.startswith("vision_encoder.")}
    video = clips.double().permute(0, 2, 1, 3, 4)  # B C T H W
    x = F.conv3d(video, s["conv1.weight"], stride=s["conv1.weight"].shape[2:])
    B, C, T, H, W = x.shape
    x = x.permute(0, 2, 3, 4, 1).reshape(B * T, H * W, C)
    cls = s["class_embedding"].expand(B * T, 1, C)
    x = torch.cat([cls, x], dim=1) + s["positional_embedding"]
    cls_tokens = x[:B, :1]
    patches = x[:, 1:].reshape(B, T, H * W, C).transpose(1, 2)  # B, N, T, C
    patches = patches + s["temporal_positional_embedding"][:, None] if T > 1 else \
        patches + s["temporal_positional_embedding"].mean(1)
    x = torch.cat([cls_tokens, patches.reshape(B, H * W * T, C)], dim=1)
    x = F.layer_norm(x, (C,), s["ln_pre.weight"], s["ln_pre.bias"]).transpose(0, 1)
    for i in range(config.vision_layers):
        x = _block(x, s, f"transformer.resblocks.{i}.", config.vision_heads)
    x = F.layer_norm(x, (C,), s["ln_post.weight"], s["ln_post.bias"])
    return x[0] @ s["proj"]


def oracle_text(state: dict, config: ViCLIPConfig, tokens: torch.Tensor) -> torch.Tensor:
    """tokens (n, L) -> (n, D) unnormalized, in float64, the official way."""
    s = {k[len("text_encoder."):]: v.double() for k, v in state.items() if k.startswith("text_encoder.")}
    L = tokens.shape[1]
    x = s["token_embedding.weight"][tokens] + s["positional_embedding"]
    mask = torch.full((L, L), float("-inf"), dtype=torch.float64).triu_(1)
    x = x.transpose(0, 1)
    for i in range(config.text_layers):
        x = _block(x, s, f"transformer.resblocks.{i}.", config.text_heads, mask=mask)
    x = x.transpose(0, 1)
    x = F.layer_norm(x, (x.shape[-1],), s["ln_final.weight"], s["ln_final.bias"])
    return x[torch.arange(x.shape[0]), tokens.argmax(-1)] @ s["text_projection"]
