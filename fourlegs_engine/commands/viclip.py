"""CLI: ``fourlegs viclip-info CHECKPOINT`` (heavy imports stay inside).

``viclip-info`` loads a checkpoint strictly and reports its size and parameter count; with
``--vocab`` it also encodes the canonical phrases (a quick check that weights and vocabulary fit
together); with ``--convert OUT.safetensors`` it writes the weights once as safetensors (flat, no
pickle, memory-mappable) for faster, safer loading later.
"""
from __future__ import annotations

import argparse
from typing import Any


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "viclip-info", help="check a ViCLIP checkpoint (strict load), optionally convert it to safetensors",
        description=__doc__.splitlines()[2])
    p.add_argument("checkpoint", help="ViClip-InternVid-10M-FLT.pth, a .safetensors file or a ViCLIP-*-hf directory")
    p.add_argument("--vocab", default=None, help="bpe_simple_vocab_16e6.txt.gz: also encode the canonical phrases")
    p.add_argument("--size", default="auto", choices=("auto", "l", "b"), help="expected size (default: read it)")
    p.add_argument("--convert", default=None, metavar="OUT", help="write the weights to OUT (.safetensors or .pth)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --convert output")
    p.set_defaults(func=run_info)


def run_info(args: argparse.Namespace) -> int:
    import torch

    from ..language.encoders import CANONICAL_PHRASES
    from ..language.viclip.checkpoint import load_viclip, resolve_checkpoint_path, save_viclip
    from ..language.viclip.model import count_parameters

    path = resolve_checkpoint_path(args.checkpoint)
    model = load_viclip(path, size=args.size)
    config = model.config
    print(f"{path}: ViCLIP {config.size_name}, {count_parameters(model):,} parameters, "
          f"{config.num_frames} frames of {config.image_size}x{config.image_size}, text context "
          f"{config.context_length}, {config.embed_dim}-d joint space (strict load: all keys match)")
    if args.vocab:
        from ..language.viclip.encoder import ViCLIPEncoder
        from ..language.viclip.tokenizer import BPETokenizer
        encoder = ViCLIPEncoder(model, BPETokenizer(args.vocab))
        emb = encoder.encode_text(list(CANONICAL_PHRASES))
        sims = (emb @ emb.T).tolist()
        print("canonical phrases, cosine similarities:")
        for phrase, row in zip(CANONICAL_PHRASES, sims):
            print(f"  {phrase:>8}: " + " ".join(f"{v:.3f}" for v in row))
        if not bool(torch.isfinite(emb).all()):
            print("warning: non-finite text embeddings")
            return 1
    if args.convert:
        out = save_viclip(model, args.convert, overwrite=args.overwrite)
        print(f"written: {out}")
    return 0
