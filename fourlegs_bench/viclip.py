"""``fourlegs bench viclip`` (options in :mod:`.commands`): seconds per clip/phrase AND embedding accuracy of every precision/batch knob.

Every run of a size builds one reference model (float64 by default, from a fixed seed, or the
weights of ``--checkpoint``), encodes the same random clips and token rows with each precision and
batch size, and reports, in one table: seconds per clip (video tower), seconds per phrase (text
tower), and the worst cosine between each embedding and the reference one. Timing depends only on
shapes, so random weights measure speed faithfully; accuracy is most meaningful with a real
checkpoint. Output: ``PREFIX.json``, ``PREFIX.md`` (table) and ``PREFIX.png`` (plot).

With ``--dataset`` the bench measures the real configuration on a capture's real frames instead
(:mod:`.viclip_real`).
"""
from __future__ import annotations

import argparse
import shlex
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import torch

from fourlegs_engine.errors import InputError
from fourlegs_engine.language.viclip.model import ViCLIPConfig, ViCLIPModel, l2_normalize

DTYPES = {"float64": torch.float64, "float32": torch.float32, "bfloat16": torch.bfloat16,
          "float16": torch.float16}


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _timed(fn, device: torch.device, repeats: int) -> float:
    """Median seconds of ``repeats`` calls after one warm-up call."""
    fn()
    _sync(device)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        _sync(device)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def _inputs(config: ViCLIPConfig, clips: int, phrases: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    video = torch.randn(clips, config.num_frames, 3, config.image_size, config.image_size, generator=gen)
    tokens = torch.zeros(phrases, config.context_length, dtype=torch.long)
    for row in range(phrases):  # [sot, words, eot, pad] with lengths 2..context
        length = 1 + row % (config.context_length - 1)
        words = torch.randint(0, config.vocab_size - 2, (length - 1,), generator=gen)
        tokens[row, :length + 1] = torch.cat([torch.tensor([config.vocab_size - 2]), words,
                                              torch.tensor([config.vocab_size - 1])])
    return video, tokens


def _cast(model: ViCLIPModel, dtype: torch.dtype) -> ViCLIPModel:
    """A copy of ``model`` in ``dtype`` (built on the meta device: no throw-away random init)."""
    with torch.device("meta"):
        copy = ViCLIPModel(model.config)
    copy.load_state_dict({k: v.to(dtype, copy=True) for k, v in model.state_dict().items()}, assign=True)
    return copy.eval()


def bench_viclip(*, size: str | ViCLIPConfig = "b", checkpoint: str | None = None, dtypes=("float32", "bfloat16"),
                 batch_sizes=(1, 4), reference: str = "float64", clips: int = 4, phrases: int = 16,
                 repeats: int = 2, device: str = "cpu", seed: int = 0) -> dict[str, Any]:
    """One row per (dtype, batch size): seconds per clip and per phrase, worst cosine to the reference."""
    from fourlegs_engine.language.encoders import resolve_device
    from fourlegs_engine.language.viclip.checkpoint import load_viclip
    target = resolve_device(device)
    for name in (*dtypes, reference):
        if name not in DTYPES:
            raise InputError(f"unknown dtype {name!r} (choose from {', '.join(DTYPES)})", field="--dtypes")
    if checkpoint:
        ref_model = load_viclip(checkpoint, size=size, device=target, dtype=DTYPES[reference])
    else:
        torch.manual_seed(seed)
        config = size if isinstance(size, ViCLIPConfig) else ViCLIPConfig.preset(size)
        ref_model = ViCLIPModel(config).to(target, DTYPES[reference]).eval()
    config = ref_model.config
    video, tokens = _inputs(config, clips, phrases, seed)
    with torch.inference_mode():
        ref_video = ref_model.encode_video(video.to(target, DTYPES[reference])).double().cpu()
        ref_text = ref_model.encode_tokens(tokens.to(target)).double().cpu()
    rows = []
    for dtype_name in dtypes:
        dtype = DTYPES[dtype_name]
        model = ref_model if dtype_name == reference else _cast(ref_model, dtype)
        for batch in batch_sizes:
            def run_video():
                return torch.cat([model.encode_video(chunk.to(target, dtype)) for chunk in video.split(batch)])

            def run_text():
                return torch.cat([model.encode_tokens(chunk.to(target)) for chunk in tokens.split(batch)])

            with torch.inference_mode():
                video_seconds = _timed(run_video, target, repeats) / clips
                text_seconds = _timed(run_text, target, repeats) / phrases
                # re-normalized in float64: the accuracy of the direction, not of the low-precision norm
                out_video = l2_normalize(run_video().double().cpu())
                out_text = l2_normalize(run_text().double().cpu())
            rows.append({
                "dtype": dtype_name, "batch_size": batch,
                "seconds_per_clip": video_seconds, "seconds_per_phrase": text_seconds,
                "video_min_cosine": float((out_video * ref_video).sum(-1).min()),
                "text_min_cosine": float((out_text * ref_text).sum(-1).min()),
                "finite": bool(torch.isfinite(out_video).all() and torch.isfinite(out_text).all()),
            })
        del model
    return {"benchmark": "viclip", "size": config.size_name, "weights": checkpoint or f"random (seed {seed})",
            "reference_dtype": reference, "device": str(target), "threads": torch.get_num_threads(),
            "clips": clips, "phrases": phrases, "repeats": repeats, "rows": rows}


def write_report(report: dict[str, Any], prefix: Path) -> list[Path]:
    """``prefix.json``, ``prefix.md`` and ``prefix.png``, each written atomically."""
    from fourlegs_engine.fileio import atomic_path, write_bytes_atomic, write_json_atomic
    prefix.parent.mkdir(parents=True, exist_ok=True)
    json_path, md_path, png_path = (prefix.with_suffix(s) for s in (".json", ".md", ".png"))
    write_json_atomic(json_path, report)
    lines = [f"# ViCLIP {report['size']} encoder benchmark",
             "",
             f"Device {report['device']}, {report['threads']} torch threads, weights {report['weights']}; "
             f"accuracy = worst cosine to the {report['reference_dtype']} reference over {report['clips']} "
             f"clips and {report['phrases']} phrases.",
             "",
             "| dtype | batch | s / clip | s / phrase | video min cos | text min cos | finite |",
             "|---|---:|---:|---:|---:|---:|---|"]
    for r in report["rows"]:
        lines.append(f"| {r['dtype']} | {r['batch_size']} | {r['seconds_per_clip']:.3f} | "
                     f"{r['seconds_per_phrase']:.4f} | {r['video_min_cosine']:.6f} | {r['text_min_cosine']:.6f} | "
                     f"{'yes' if r['finite'] else 'NO'} |")
    write_bytes_atomic(md_path, ("\n".join(lines) + "\n").encode())

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 4))
    for dtype in dict.fromkeys(r["dtype"] for r in report["rows"]):
        rows = [r for r in report["rows"] if r["dtype"] == dtype]
        ax.plot([r["seconds_per_clip"] for r in rows], [1 - r["video_min_cosine"] + 1e-12 for r in rows],
                marker="o", label=dtype)
        for r in rows:
            ax.annotate(f"b={r['batch_size']}", (r["seconds_per_clip"], 1 - r["video_min_cosine"] + 1e-12),
                        fontsize=7)
    ax.set_xlabel("seconds per 8-frame clip")
    ax.set_ylabel(f"1 - worst cosine to {report['reference_dtype']}")
    ax.set_yscale("log")
    ax.set_title(f"ViCLIP {report['size']} video tower on {report['device']}")
    ax.legend()
    fig.tight_layout()
    with atomic_path(png_path) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)
    return [json_path, md_path, png_path]


def _int_list(text: str, field: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise InputError(f"must be comma-separated integers, got {text!r}", field=field) from None
    if not values or min(values) < 0:
        raise InputError(f"must be non-negative integers, got {text!r}", field=field)
    return values


def run_bench_viclip(args: argparse.Namespace) -> int:
    from fourlegs_engine.fileio import check_outputs
    real = args.dataset is not None
    if args.threads:
        torch.set_num_threads(args.threads)
    batches = _int_list(args.batch_sizes or ("1,2" if real else "1,4"), "--batch-sizes")
    clips = args.clips if args.clips is not None else (2 if real else 4)
    phrases = args.phrases if args.phrases is not None else (8 if real else 16)
    if min(batches) < 1 or clips < 1 or phrases < 1 or args.repeats < 1:
        raise InputError("batch sizes, --clips, --phrases and --repeats must be positive", field="--batch-sizes")
    dtypes = [d.strip() for d in (args.dtypes or ("float32,bfloat16,float16" if real else "float32,bfloat16"))
              .split(",") if d.strip()]
    prefix = Path(args.out or ("bench/viclip_real" if real else "bench/viclip"))
    check_outputs([prefix.with_suffix(s) for s in (".json", ".md", ".png")], overwrite=args.overwrite)
    if real:
        from .viclip_real import DEFAULT_SUBSETS, bench_viclip_real, write_real_report
        if args.checkpoint:
            raise InputError("the real-frames mode measures random weights only (timing depends on shapes); "
                             "drop --checkpoint or --dataset", field="--checkpoint")
        report = bench_viclip_real(args.dataset, size=args.size or "l",
                                   cameras=[c.strip() for c in args.cameras.split(",") if c.strip()],
                                   timesteps=_int_list(args.timesteps, "--timesteps"), dtypes=dtypes,
                                   batch_sizes=batches, reference=args.reference, clips=clips, phrases=phrases,
                                   subsets=args.subsets or DEFAULT_SUBSETS, device=args.device, seed=args.seed,
                                   progress=True)
        command = "fourlegs " + shlex.join(sys.argv[1:]) if sys.argv[1:3] == ["bench", "viclip"] else None
        paths = write_real_report(report, prefix, command=command, overwrite=args.overwrite)
    else:
        report = bench_viclip(size=args.size or "b", checkpoint=args.checkpoint, dtypes=dtypes, batch_sizes=batches,
                              reference=args.reference, clips=clips, phrases=phrases, repeats=args.repeats,
                              device=args.device, seed=args.seed)
        paths = write_report(report, prefix)
    print(paths[1].read_text())
    print("written: " + ", ".join(map(str, paths)), file=sys.stderr)
    return 0
