"""CLI: ``fourlegs viclip-info CHECKPOINT`` and ``fourlegs bench viclip`` (heavy imports stay inside).

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


def register_bench(bench_subparsers: Any) -> None:
    p = bench_subparsers.add_parser(
        "viclip", help="ViCLIP encoder: seconds per clip/phrase and accuracy per precision and batch size",
        description="Seconds per 8-frame clip and per phrase, and the worst cosine to a float64 reference, "
                    "for every precision and batch size, in one run.")
    p.add_argument("--size", default="b", choices=("b", "l"), help="ViCLIP size (default b = B/16)")
    p.add_argument("--checkpoint", default=None, help="real weights (default: random weights from --seed)")
    p.add_argument("--dtypes", default="float32,bfloat16", help="precisions to measure (default float32,bfloat16)")
    p.add_argument("--batch-sizes", default="1,4", help="clips per forward pass (default 1,4)")
    p.add_argument("--reference", default="float64", choices=("float64", "float32", "bfloat16", "float16"),
                   help="precision of the reference embeddings (default float64)")
    p.add_argument("--clips", type=int, default=4, help="clips encoded per measurement (default 4)")
    p.add_argument("--phrases", type=int, default=16, help="phrases encoded per measurement (default 16)")
    p.add_argument("--repeats", type=int, default=2, help="timed repeats, the median is reported (default 2)")
    p.add_argument("--device", default="auto", help="cpu, cuda or auto (default)")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (default: torch's choice)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="bench/viclip", help="output prefix (default bench/viclip)")
    p.set_defaults(func=_run_bench)


def _run_bench(args: argparse.Namespace) -> int:
    from .bench import run_bench_viclip
    return run_bench_viclip(args)


def run_info(args: argparse.Namespace) -> int:
    import torch

    from ..encoders import CANONICAL_PHRASES
    from .checkpoint import load_viclip, resolve_checkpoint_path, save_viclip
    from .model import count_parameters

    path = resolve_checkpoint_path(args.checkpoint)
    model = load_viclip(path, size=args.size)
    config = model.config
    print(f"{path}: ViCLIP {config.size_name}, {count_parameters(model):,} parameters, "
          f"{config.num_frames} frames of {config.image_size}x{config.image_size}, text context "
          f"{config.context_length}, {config.embed_dim}-d joint space (strict load: all keys match)")
    if args.vocab:
        from .encoder import ViCLIPEncoder
        from .tokenizer import BPETokenizer
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
