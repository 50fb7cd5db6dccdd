"""ViCLIP (InternVid) in plain torch: a video ViT and a CLIP text transformer in one joint space.

The module tree reproduces the official parameter names exactly, so the published checkpoints
(``ViClip-InternVid-10M-FLT.pth``: ``{"model": state_dict}``; the ``ViCLIP-*-hf`` safetensors) load
with a strict key-for-key match:

``vision_encoder.*``
    ``conv1.weight`` (W, 3, 1, p, p) — a Conv3d patch embedding with a temporal kernel of 1 (no
    bias); ``class_embedding`` (W,); ``positional_embedding`` (g*g+1, W) shared by all frames;
    ``temporal_positional_embedding`` (1, F, W) added to every patch token of frame f;
    ``ln_pre``; ``transformer.resblocks.{i}.{ln_1, attn.{in_proj_weight, in_proj_bias, out_proj},
    ln_2, mlp.{c_fc, c_proj}}``; ``ln_post``; ``proj`` (W, D).
``text_encoder.*``
    ``token_embedding`` (V, Wt); ``positional_embedding`` (L=32, Wt); the same residual blocks under
    ``transformer.resblocks.{i}``, with a causal mask; ``ln_final``; ``text_projection`` (Wt, D).
``temp``
    the scalar contrastive temperature used in training (kept so the layout is complete).

Video forward (one clip of F frames): each frame is cut into g*g patches; every patch token gets the
spatial embedding of its position plus the temporal embedding of its frame; one class token
(``class_embedding + positional_embedding[0]``, no temporal term) is prepended and the whole
1 + g*g*F sequence goes through full (joint space-time) self-attention. The class token after
``ln_post``, times ``proj``, is the clip feature. Text forward: token + position embeddings, causal
transformer, ``ln_final``, the state at the end-of-text token (the largest id in each row), times
``text_projection``.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import torch
import torch.nn.functional as F
from torch import nn

# Image statistics. ViCLIP was trained with the ImageNet statistics (its data pipeline picks them for
# "vit" encoders and its demo uses them); the 4-LEGS feature pipeline describes CLIP statistics.
CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

HEAD_WIDTH = 64  # every CLIP/ViCLIP tower uses 64 channels per attention head


@dataclass(frozen=True)
class ViCLIPConfig:
    """Architecture hyper-parameters; ``ViCLIPConfig.large()`` / ``.base()`` are the published sizes."""

    image_size: int = 224
    patch_size: int = 14
    num_frames: int = 8
    vision_width: int = 1024
    vision_layers: int = 24
    vision_heads: int = 16
    embed_dim: int = 768
    vocab_size: int = 49408
    context_length: int = 32
    text_width: int = 768
    text_layers: int = 12
    text_heads: int = 12

    @classmethod
    def large(cls) -> "ViCLIPConfig":
        """ViCLIP-L/14: ViT-L/14 video tower, 12-layer 768-wide text tower, 768-d joint space."""
        return cls()

    @classmethod
    def base(cls) -> "ViCLIPConfig":
        """ViCLIP-B/16: ViT-B/16 video tower, 12-layer 512-wide text tower, 512-d joint space."""
        return cls(patch_size=16, vision_width=768, vision_layers=12, vision_heads=12,
                   embed_dim=512, text_width=512, text_layers=12, text_heads=8)

    @classmethod
    def preset(cls, size: str) -> "ViCLIPConfig":
        key = size.lower().replace("/", "").replace("-", "")
        if key in ("l", "l14", "large", "vitl14"):
            return cls.large()
        if key in ("b", "b16", "base", "vitb16"):
            return cls.base()
        raise ValueError(f"unknown ViCLIP size {size!r} (expected 'l' / 'L/14' or 'b' / 'B/16')")

    @property
    def grid_size(self) -> int:
        return self.image_size // self.patch_size

    @property
    def size_name(self) -> str:
        """'L/14', 'B/16' for the published sizes, a descriptive string otherwise."""
        if self == ViCLIPConfig.large():
            return "L/14"
        if self == ViCLIPConfig.base():
            return "B/16"
        return (f"custom(W={self.vision_width}x{self.vision_layers}, p={self.patch_size}, "
                f"text={self.text_width}x{self.text_layers}, D={self.embed_dim})")

    def validate(self) -> "ViCLIPConfig":
        if self.image_size % self.patch_size:
            raise ValueError(f"image_size {self.image_size} is not a multiple of patch_size {self.patch_size}")
        for width, heads, what in ((self.vision_width, self.vision_heads, "vision"),
                                   (self.text_width, self.text_heads, "text")):
            if heads < 1 or width % heads:
                raise ValueError(f"{what} width {width} is not divisible by {heads} heads")
        for name, value in asdict(self).items():
            if value < 1:
                raise ValueError(f"{name} must be positive, got {value}")
        return self

    def with_(self, **changes) -> "ViCLIPConfig":
        return replace(self, **changes)


class QuickGELU(nn.Module):
    """CLIP's activation: x * sigmoid(1.702 x)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * torch.sigmoid(1.702 * x)


class LayerNorm(nn.LayerNorm):
    """LayerNorm computed in float32 even for half-precision inputs (as CLIP does)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.dtype in (torch.float16, torch.bfloat16):
            out = F.layer_norm(x.float(), self.normalized_shape, self.weight.float(), self.bias.float(), self.eps)
            return out.to(x.dtype)
        return super().forward(x)


class SelfAttention(nn.Module):
    """Multi-head self-attention with ``nn.MultiheadAttention``'s parameter names.

    ``in_proj_weight`` (3W, W) stacks the query, key and value projections; ``out_proj`` is (W, W).
    Works on batch-first tensors and uses ``scaled_dot_product_attention`` (fused kernels on GPU).
    """

    def __init__(self, width: int, heads: int):
        super().__init__()
        self.heads = heads
        self.in_proj_weight = nn.Parameter(torch.empty(3 * width, width))
        self.in_proj_bias = nn.Parameter(torch.zeros(3 * width))
        self.out_proj = nn.Linear(width, width)
        nn.init.xavier_uniform_(self.in_proj_weight)
        nn.init.zeros_(self.out_proj.bias)

    def forward(self, x: torch.Tensor, causal: bool = False) -> torch.Tensor:
        """x (B, L, W) -> (B, L, W); ``causal`` lets token i attend to tokens 0..i only."""
        batch, length, width = x.shape
        qkv = F.linear(x, self.in_proj_weight, self.in_proj_bias)
        qkv = qkv.view(batch, length, 3, self.heads, width // self.heads).permute(2, 0, 3, 1, 4)
        out = F.scaled_dot_product_attention(qkv[0], qkv[1], qkv[2], is_causal=causal)
        return self.out_proj(out.transpose(1, 2).reshape(batch, length, width))


class ResidualAttentionBlock(nn.Module):
    """Pre-norm transformer block: x + attn(ln_1(x)), then x + mlp(ln_2(x)) with a 4x QuickGELU MLP."""

    def __init__(self, width: int, heads: int):
        super().__init__()
        self.ln_1 = LayerNorm(width)
        self.attn = SelfAttention(width, heads)
        self.ln_2 = LayerNorm(width)
        self.mlp = nn.Sequential()
        self.mlp.add_module("c_fc", nn.Linear(width, 4 * width))
        self.mlp.add_module("gelu", QuickGELU())
        self.mlp.add_module("c_proj", nn.Linear(4 * width, width))

    def forward(self, x: torch.Tensor, causal: bool = False) -> torch.Tensor:
        x = x + self.attn(self.ln_1(x), causal=causal)
        return x + self.mlp(self.ln_2(x))


class Transformer(nn.Module):
    def __init__(self, width: int, layers: int, heads: int):
        super().__init__()
        self.resblocks = nn.ModuleList(ResidualAttentionBlock(width, heads) for _ in range(layers))

    def forward(self, x: torch.Tensor, causal: bool = False) -> torch.Tensor:
        for block in self.resblocks:
            x = block(x, causal=causal)
        return x


class VideoTower(nn.Module):
    """ViT with a shared spatial and a per-frame temporal positional embedding (``vision_encoder``)."""

    def __init__(self, config: ViCLIPConfig):
        super().__init__()
        width, patch = config.vision_width, config.patch_size
        self.num_frames = config.num_frames
        self.conv1 = nn.Conv3d(3, width, kernel_size=(1, patch, patch), stride=(1, patch, patch), bias=False)
        self.class_embedding = nn.Parameter(torch.empty(width))
        self.positional_embedding = nn.Parameter(torch.empty(config.grid_size ** 2 + 1, width))
        self.temporal_positional_embedding = nn.Parameter(torch.zeros(1, config.num_frames, width))
        self.ln_pre = LayerNorm(width)
        self.transformer = Transformer(width, config.vision_layers, config.vision_heads)
        self.ln_post = LayerNorm(width)
        self.proj = nn.Parameter(torch.empty(width, config.embed_dim))

    def reset_parameters(self) -> None:
        """CLIP's initialization of the embeddings and projection (a checkpoint replaces them)."""
        scale = self.class_embedding.shape[0] ** -0.5
        for param in (self.class_embedding, self.positional_embedding, self.proj):
            nn.init.normal_(param, std=scale)
        nn.init.zeros_(self.temporal_positional_embedding)

    def tokens(self, video: torch.Tensor) -> torch.Tensor:
        """video (B, 3, T, H, W) -> token sequence (B, 1 + g*g*T, W) before ``ln_pre``.

        Patch tokens are ordered patch-major, frame-minor (token 1 + n*T + t is patch n of frame t),
        as in the official implementation. T must equal ``num_frames``, or be 1 (a still image, which
        gets the mean temporal embedding, as the official code does).
        """
        x = self.conv1(video)  # (B, W, T, g, g)
        batch, width, frames = x.shape[:3]
        x = x.flatten(3).permute(0, 3, 2, 1)  # (B, g*g, T, W)
        x = x + self.positional_embedding[1:, None, :].to(x.dtype)
        temporal = self.temporal_positional_embedding.to(x.dtype)  # (1, F, W)
        x = x + (temporal.mean(1, keepdim=True) if frames == 1 else temporal)
        cls = (self.class_embedding + self.positional_embedding[0]).to(x.dtype).expand(batch, 1, width)
        return torch.cat([cls, x.reshape(batch, x.shape[1] * frames, width)], dim=1)

    def forward(self, video: torch.Tensor) -> torch.Tensor:
        """video (B, 3, T, H, W) normalized pixels -> (B, D) unnormalized clip embedding."""
        x = self.transformer(self.ln_pre(self.tokens(video)))
        return self.ln_post(x[:, 0]) @ self.proj.to(x.dtype)


class TextTower(nn.Module):
    """CLIP text transformer with a causal mask, pooled at the end-of-text token (``text_encoder``)."""

    def __init__(self, config: ViCLIPConfig):
        super().__init__()
        width = config.text_width
        self.context_length = config.context_length
        # an explicit weight skips nn.Embedding's own random init (see ViCLIPModel: meta construction)
        self.token_embedding = nn.Embedding(config.vocab_size, width,
                                            _weight=torch.empty(config.vocab_size, width))
        self.positional_embedding = nn.Parameter(torch.empty(config.context_length, width))
        self.transformer = Transformer(width, config.text_layers, config.text_heads)
        self.ln_final = LayerNorm(width)
        self.text_projection = nn.Parameter(torch.empty(width, config.embed_dim))

    def reset_parameters(self) -> None:
        """CLIP's initialization of the embeddings and projection (a checkpoint replaces them)."""
        nn.init.normal_(self.token_embedding.weight, std=0.02)
        nn.init.normal_(self.positional_embedding, std=0.01)
        nn.init.normal_(self.text_projection, std=self.text_projection.shape[0] ** -0.5)

    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        """tokens (n, L) int ids (start, words, end, zero padding) -> (n, D) unnormalized embedding.

        The pooled position is the argmax of each row: the end-of-text token has the largest id of
        the vocabulary (this is how CLIP and ViCLIP pool).
        """
        x = self.token_embedding(tokens) + self.positional_embedding[: tokens.shape[1]]
        x = self.ln_final(self.transformer(x, causal=True))
        eot = tokens.argmax(dim=-1)
        return x[torch.arange(x.shape[0], device=x.device), eot] @ self.text_projection.to(x.dtype)


class ViCLIPModel(nn.Module):
    """The two towers and the training temperature, under the official top-level names."""

    def __init__(self, config: ViCLIPConfig | None = None):
        super().__init__()
        self.config = (config or ViCLIPConfig.large()).validate()
        self.vision_encoder = VideoTower(self.config)
        self.text_encoder = TextTower(self.config)
        self.temp = nn.Parameter(torch.full((), 1 / 100.0))
        # On the meta device (shape tables, loading a checkpoint) random init is skipped: it is
        # wasted work there, and torch's meta random ops import hundreds of modules on first use.
        if not self.temp.is_meta:
            self.vision_encoder.reset_parameters()
            self.text_encoder.reset_parameters()

    def encode_video(self, clips: torch.Tensor) -> torch.Tensor:
        """clips (B, T, 3, H, W) normalized pixels -> (B, D) L2-normalized embeddings."""
        video = clips.to(self.temp.dtype).permute(0, 2, 1, 3, 4)  # (B, 3, T, H, W)
        return l2_normalize(self.vision_encoder(video))

    def encode_tokens(self, tokens: torch.Tensor) -> torch.Tensor:
        """tokens (n, L) int ids -> (n, D) L2-normalized embeddings."""
        return l2_normalize(self.text_encoder(tokens.long()))


def l2_normalize(x: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Rows scaled to unit length; the norm is clamped so a zero row stays zero (never NaN)."""
    return x / x.norm(dim=-1, keepdim=True).clamp_min(eps)


def video_clip_flops(config: ViCLIPConfig) -> dict[str, int]:
    """Floating-point operations of one clip through the video tower (a multiply-add counts 2).

    ``matmul``: the patch embedding, every block's linear layers (q, k, v, out: 4 W^2; MLP: 8 W^2 per
    token) and the projection; ``attention``: the two (L, L) products of joint space-time attention
    over L = 1 + g*g*F tokens, 4 L^2 W per block. LayerNorms, activations and softmax are left out
    (linear in L, a fraction of a percent).
    """
    width, frames = config.vision_width, config.num_frames
    patches = config.grid_size ** 2 * frames
    length = patches + 1
    matmul = (2 * patches * 3 * config.patch_size ** 2 * width
              + config.vision_layers * 24 * length * width ** 2 + 2 * width * config.embed_dim)
    attention = config.vision_layers * 4 * length ** 2 * width
    return {"matmul": matmul, "attention": attention, "total": matmul + attention}


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def expected_shapes(config: ViCLIPConfig) -> dict[str, tuple[int, ...]]:
    """The official key -> shape table for ``config``, built on the meta device (no memory used)."""
    with torch.device("meta"):
        model = ViCLIPModel(config)
    return {key: tuple(value.shape) for key, value in model.state_dict().items()}


def infer_config(shapes: dict[str, tuple[int, ...]]) -> ViCLIPConfig:
    """Read the architecture off a checkpoint's key -> shape table (heads = width / 64, as in CLIP).

    Raises ``KeyError`` naming the first key it needs and cannot find.
    """
    def shape(key: str) -> tuple[int, ...]:
        if key not in shapes:
            raise KeyError(key)
        return tuple(shapes[key])

    def layers(prefix: str) -> int:
        indices = {int(k[len(prefix):].split(".", 1)[0]) for k in shapes
                   if k.startswith(prefix) and k[len(prefix):].split(".", 1)[0].isdigit()}
        return max(indices) + 1 if indices else 0

    conv = shape("vision_encoder.conv1.weight")
    vision_width, patch = conv[0], conv[-1]
    grid = math.isqrt(max(shape("vision_encoder.positional_embedding")[0] - 1, 0))
    vocab, text_width = shape("text_encoder.token_embedding.weight")
    return ViCLIPConfig(
        image_size=grid * patch,
        patch_size=patch,
        num_frames=shape("vision_encoder.temporal_positional_embedding")[1],
        vision_width=vision_width,
        vision_layers=layers("vision_encoder.transformer.resblocks."),
        vision_heads=max(vision_width // HEAD_WIDTH, 1),
        embed_dim=shape("vision_encoder.proj")[1],
        vocab_size=vocab,
        context_length=shape("text_encoder.positional_embedding")[0],
        text_width=text_width,
        text_layers=layers("text_encoder.transformer.resblocks."),
        text_heads=max(text_width // HEAD_WIDTH, 1),
    )
