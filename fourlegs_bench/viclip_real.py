"""``fourlegs bench viclip --dataset DIR``: the real-size ViCLIP cost on the real frames of a capture.

The real configuration — ViCLIP-L/14, 8-frame tubes, the 5-scale crop pyramid of the paper — runs on
the captured JPEG frames of a Dynamic 3D Gaussians dataset (``train_meta.json`` + ``ims/``, read with
the fitter's own :class:`~fourlegs_engine.fit.dataset.Capture`), through the crop code of
``fourlegs extract``: the tube ``t-4..t+3`` (:func:`~fourlegs_engine.language.pyramid.tube_indices`),
the layout (:func:`~fourlegs_engine.language.pyramid.crop_layout`), the crops
(:func:`~fourlegs_engine.language.pyramid.scale_crops`) and their resize + CLIP normalization
(:func:`~fourlegs_engine.language.pyramid.resize_crops`) in extraction's batches, then the model's
video tower.

The weights are random (seeded), never trained ones: seconds depend only on the shapes, so the timing
is faithful; the accuracy column is the agreement of each precision with the float64 reference on the
same random model, not retrieval quality.

Measured separately, per camera-timestep: JPEG decoding, crop + resize + normalization of all its
clips (572 at 640x360), and the network on a handful of those clips per (precision, batch size) knob.
A ViT-L/14 clip is tens of CPU seconds, so each knob encodes the same few clips once (no repeats; on
CUDA one warm-up batch first). Seconds per camera-timestep = decoding one new frame (consecutive tubes
share 7 of their 8 frames, which extraction caches) + crop/resize of all clips + clips x seconds per
clip; the whole scene and user-sized subsets are extrapolated from that. Wall seconds and process CPU
seconds (all threads) are both reported: on a shared machine the CPU seconds are the repeatable figure.
"""
from __future__ import annotations

import os
import platform
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from fourlegs_engine.errors import InputError
from fourlegs_engine.language.extract import ExtractOptions
from fourlegs_engine.language.pyramid import (CLIP_MEAN, CLIP_STD, PyramidLayout, crop_layout, resize_crops,
                                              scale_crops, tube_indices)
from fourlegs_engine.language.viclip.model import ViCLIPConfig, ViCLIPModel, l2_normalize, video_clip_flops

from .viclip import DTYPES, _cast, _inputs, _sync

#: crop tubes per encoder call in ``fourlegs extract`` with an RGB encoder (its default batch)
EXTRACT_RGB_BATCH = 32
#: the paper's count of crop clips per camera-timestep at 640x360
PAPER_CLIPS_640x360 = 572
#: (name, cameras, timesteps): the whole Panoptic sequence and what a user would realistically run
DEFAULT_SUBSETS = "all:27x150,8 cameras:8x150,8 cameras 1 s:8x30"
WEIGHTS_NOTE = ("random weights (seed {seed}): no trained ViCLIP weights exist on this machine and none are "
                "faked; seconds depend only on shapes, the cosine columns compare precisions of the same random "
                "model")


@dataclass(frozen=True)
class Subset:
    """``cameras`` x ``timesteps`` camera-timesteps to extrapolate to, under a readable ``name``."""

    name: str
    cameras: int
    timesteps: int

    @property
    def camera_timesteps(self) -> int:
        return self.cameras * self.timesteps


def parse_subsets(text: str) -> list[Subset]:
    """``"name:CxT,name:CxT"`` (name optional) -> subsets; one clear error for a malformed entry."""
    subsets = []
    for item in (s.strip() for s in text.split(",")):
        if not item:
            continue
        name, _, size = item.rpartition(":")
        try:
            cams, steps = (int(v) for v in size.lower().split("x"))
        except ValueError:
            raise InputError(f"{item!r} is not CAMERASxTIMESTEPS (e.g. 'all:27x150')", field="--subsets") from None
        if cams < 1 or steps < 1:
            raise InputError(f"{item!r}: cameras and timesteps must be positive", field="--subsets")
        subsets.append(Subset(name.strip() or f"{cams}x{steps}", cams, steps))
    if not subsets:
        raise InputError("needs at least one CAMERASxTIMESTEPS entry", field="--subsets")
    return subsets


class _Clock:
    """Wall and process-CPU seconds of a block (CPU time counts every thread of this process)."""

    def __init__(self, device: torch.device | None = None):
        self.device = device

    def __enter__(self) -> "_Clock":
        if self.device is not None:
            _sync(self.device)
        self.wall, self.cpu = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc: Any) -> None:
        if self.device is not None:
            _sync(self.device)
        self.wall = time.perf_counter() - self.wall
        self.cpu = time.process_time() - self.cpu


def sample_clips(layout: PyramidLayout, pairs: int, count: int) -> list[tuple[int, int]]:
    """``count`` (camera-timestep, clip index) picks: the crops nearest the image centre, spread over the scales
    (smallest to largest) and the camera-timesteps, so the encoded clips show the scene rather than padding."""
    scales = layout.scales
    picks: list[tuple[int, int]] = []
    for k in range(count):
        s = round(k * (len(scales) - 1) / max(count - 1, 1)) if count <= len(scales) else k % len(scales)
        pair, grid = k % pairs, scales[s]
        centre_row = grid.offset + (grid.ny // 2) * grid.nx
        for shift in range(grid.nx):        # a repeated pick moves one crop to the right
            pick = (pair, centre_row + (grid.nx // 2 + shift) % grid.nx)
            if pick not in picks:
                break
        picks.append(pick)
    return sorted(picks)


def load_tube(capture: Any, t: int, cam: int) -> tuple[torch.Tensor, dict[str, float]]:
    """(8, 3, H, W) float32 frames ``t-4..t+3`` of one training camera in [0, 1], with decode seconds.

    Edge timesteps repeat the first/last frame (as extraction does); each distinct frame is decoded once.
    """
    indices = tube_indices(t, capture.num_timesteps)
    frames: dict[int, torch.Tensor] = {}
    with _Clock() as clock:
        for k in dict.fromkeys(indices):
            image = capture.load_image("train", k, cam, (capture.width, capture.height))
            frames[k] = torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1)))
    tube = torch.stack([frames[k] for k in indices])
    return tube, {"frames": len(frames), "seconds": clock.wall, "cpu_seconds": clock.cpu}


def preprocess_camera_timestep(tube: torch.Tensor, layout: PyramidLayout, crop_size: int, keep: Sequence[int],
                               batch_size: int = EXTRACT_RGB_BATCH) -> tuple[dict[int, torch.Tensor], int]:
    """Cut, resize and CLIP-normalize every clip of one camera-timestep as extraction does, batch by batch.

    Args:
        tube: (8, 3, H, W) frames in [0, 1].
        layout: the camera's crop pyramid.
        crop_size: side the crops are resized to (the encoder's image size).
        keep: clip indices (layout order: scale by scale, row-major) whose clips are returned.
    Returns:
        ({index: (8, 3, crop_size, crop_size) float32 clip}, number of clips produced).
    """
    wanted = set(keep)
    kept: dict[int, torch.Tensor] = {}
    produced = 0
    for grid in layout.scales:
        crops = scale_crops(tube, grid)                                  # (n, 8, 3, k, k) views
        for start in range(0, grid.num_crops, batch_size):
            clips = resize_crops(crops[start:start + batch_size], crop_size, clip_normalize=True)
            for j in range(clips.shape[0]):
                index = grid.offset + start + j
                if index in wanted:
                    kept[index] = clips[j].clone()
            produced += clips.shape[0]
    return kept, produced


def _encode(model: ViCLIPModel, clips: torch.Tensor, batch: int, dtype: torch.dtype,
            device: torch.device) -> torch.Tensor:
    return torch.cat([model.encode_video(chunk.to(device, dtype)) for chunk in clips.split(batch)])


def _supported_error(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {str(exc).splitlines()[0][:160] if str(exc) else ''}"


def bench_viclip_real(dataset: str | Path, *, size: str | ViCLIPConfig = "l", cameras: Sequence[str] = ("1",),
                      timesteps: Sequence[int] = (75,), dtypes: Sequence[str] = ("float32", "bfloat16", "float16"),
                      batch_sizes: Sequence[int] = (1, 2), reference: str = "float64", clips: int = 2,
                      phrases: int = 8, subsets: Sequence[Subset] | str = DEFAULT_SUBSETS, device: str = "cpu",
                      seed: int = 0, ratios: Sequence[float] | None = None, progress: bool = False) -> dict[str, Any]:
    """Seconds and accuracy of every (precision, batch size) knob on real crop clips, and the extrapolations.

    Args:
        dataset: Dynamic 3D Gaussians capture directory (``train_meta.json``, ``ims/``).
        size: ViCLIP preset (``"l"`` = L/14, the paper's) or a config (tests use tiny ones).
        cameras, timesteps: training camera ids and timesteps whose pyramids are cut (all their clips
            are preprocessed; ``clips`` of them, spread over cameras and scales, go through the network).
        dtypes, batch_sizes: the knobs; a precision the device cannot run becomes a row saying so.
        reference: precision of the reference embeddings (its own timing is a row of the table).
        subsets: camera x timestep counts to extrapolate to.
    Returns:
        The JSON-serializable report (see :func:`write_real_report`).
    """
    from tqdm import tqdm

    from fourlegs_engine.fit.dataset import Capture
    from fourlegs_engine.language.encoders import resolve_device
    from fourlegs_engine.language.pyramid import pyramid_ratios

    target = resolve_device(device)
    for name in (*dtypes, reference):
        if name not in DTYPES:
            raise InputError(f"unknown dtype {name!r} (choose from {', '.join(DTYPES)})", field="--dtypes")
    if clips < 1 or phrases < 1 or not batch_sizes or min(batch_sizes) < 1:
        raise InputError("clips, phrases and batch sizes must be positive", field="--clips")
    subsets = parse_subsets(subsets) if isinstance(subsets, str) else list(subsets)
    capture = Capture(dataset)
    cam_positions = capture.camera_indices("train", [str(c) for c in cameras])
    for t in timesteps:
        if not 0 <= t < capture.num_timesteps:
            raise InputError(f"timestep {t} is outside 0..{capture.num_timesteps - 1}", field="--timesteps")
    pairs = [(t, c) for t in timesteps for c in cam_positions]
    capture.check_frames("train", sorted({k for t in timesteps for k in tube_indices(t, capture.num_timesteps)}),
                         cam_positions, masks=False)
    config = size if isinstance(size, ViCLIPConfig) else ViCLIPConfig.preset(size)
    crop_size = int(ExtractOptions(crop_size=None).resolved_crop_size("rgb", config))
    ratios = tuple(ratios) if ratios is not None else pyramid_ratios()
    layout = crop_layout(capture.width, capture.height, ratios)
    per_ct = layout.num_crops
    load_before = os.getloadavg()

    # ---- real clips: decode, crop, resize + normalize every clip of each selected camera-timestep
    picks = sample_clips(layout, len(pairs), clips)
    decode, prep, sampled, sources = [], [], [], []
    for p, (t, c) in enumerate(tqdm(pairs, desc="decode + crop", unit="camera-timestep", disable=not progress)):
        tube, decoded = load_tube(capture, t, c)
        decode.append(decoded)
        keep = [i for pair, i in picks if pair == p]
        with _Clock() as clock:
            kept, produced = preprocess_camera_timestep(tube, layout, crop_size, keep)
        if produced != per_ct:
            raise AssertionError(f"extraction cut {produced} clips, the layout says {per_ct}")
        prep.append({"seconds": clock.wall, "cpu_seconds": clock.cpu})
        for i in keep:
            sampled.append(kept[i])
            scale = max(s for s in range(len(layout.scales)) if layout.scales[s].offset <= i)
            sources.append({"timestep": t, "camera": capture.train.cam_ids[t][c], "clip": i, "scale": scale})
    video = torch.stack(sampled)                                       # (clips, 8, 3, crop, crop)
    if not bool(torch.isfinite(video).all()):
        raise InputError("the preprocessed clips contain NaN/Inf", file=dataset, field="ims")
    _, tokens = _inputs(config, 1, phrases, seed)
    decode_frame_s = sum(d["seconds"] for d in decode) / sum(d["frames"] for d in decode)
    decode_frame_cpu = sum(d["cpu_seconds"] for d in decode) / sum(d["frames"] for d in decode)
    prep_s = sum(r["seconds"] for r in prep) / len(prep)
    prep_cpu = sum(r["cpu_seconds"] for r in prep) / len(prep)

    # ---- the network: one seeded float32 master, the reference and every knob cast from it
    flops = video_clip_flops(config)
    torch.manual_seed(seed)
    master = ViCLIPModel(config).eval()
    rows: list[dict[str, Any]] = []
    knobs = [(reference, 1, True)] + [(d, b, False) for d in dtypes for b in batch_sizes]
    ref_video = ref_text = None
    bar = tqdm(knobs, desc="knobs", unit="knob", disable=not progress)
    for dtype_name, batch, is_reference in bar:
        bar.set_postfix_str(f"{dtype_name} b={batch}")
        dtype = DTYPES[dtype_name]
        row: dict[str, Any] = {"dtype": dtype_name, "batch_size": batch, "reference": is_reference,
                               "clips": int(video.shape[0])}
        try:
            model = master if dtype == torch.float32 and target.type == "cpu" else _cast(master, dtype).to(target)
            with torch.inference_mode():
                if target.type == "cuda":  # kernel selection and allocation are not the clip's cost
                    _encode(model, video[:batch], batch, dtype, target)
                with _Clock(target) as video_clock:
                    out_video = _encode(model, video, batch, dtype, target)
                with _Clock(target) as text_clock:
                    out_text = torch.cat([model.encode_tokens(chunk.to(target)) for chunk in tokens.split(batch)])
            model = None
        except (RuntimeError, NotImplementedError) as exc:
            if is_reference:
                raise InputError(f"the reference precision {dtype_name} does not run on {target}: "
                                 f"{_supported_error(exc)}", field="--reference") from None
            rows.append({**row, "supported": False, "error": _supported_error(exc)})
            continue
        # re-normalized in float64: the accuracy of the direction, not of the low-precision norm
        out_video = l2_normalize(out_video.double().cpu())
        out_text = l2_normalize(out_text.double().cpu())
        if is_reference:
            ref_video, ref_text = out_video, out_text
        n = video.shape[0]
        s_clip, cpu_clip = video_clock.wall / n, video_clock.cpu / n
        row.update({
            "supported": True,
            "seconds_per_clip": s_clip, "cpu_seconds_per_clip": cpu_clip,
            "seconds_per_phrase": text_clock.wall / phrases,
            "gflop_per_second": flops["total"] / s_clip / 1e9 if s_clip > 0 else None,
            "gflop_per_cpu_second": flops["total"] / cpu_clip / 1e9 if cpu_clip > 0 else None,
            "video_min_cosine": float((out_video * ref_video).sum(-1).min()),
            "text_min_cosine": float((out_text * ref_text).sum(-1).min()),
            "finite": bool(torch.isfinite(out_video).all() and torch.isfinite(out_text).all()),
            "seconds_per_camera_timestep": decode_frame_s + prep_s + per_ct * s_clip,
            "cpu_seconds_per_camera_timestep": decode_frame_cpu + prep_cpu + per_ct * cpu_clip,
        })
        row["extrapolated_hours"] = {s.name: s.camera_timesteps * row["seconds_per_camera_timestep"] / 3600
                                     for s in subsets}
        row["extrapolated_cpu_hours"] = {s.name: s.camera_timesteps * row["cpu_seconds_per_camera_timestep"] / 3600
                                         for s in subsets}
        rows.append(row)
    del master

    return {
        "benchmark": "viclip-real", "size": config.size_name, "weights": WEIGHTS_NOTE.format(seed=seed),
        "random_weights": True, "reference_dtype": reference, "device": str(target),
        "device_name": (torch.cuda.get_device_name(target) if target.type == "cuda" else platform.processor()
                        or platform.machine()),
        "threads": torch.get_num_threads(), "torch": torch.__version__,
        "load_average_before": [round(v, 2) for v in load_before],
        "load_average_after": [round(v, 2) for v in os.getloadavg()],
        "dataset": str(dataset), "image_size": [capture.width, capture.height],
        "cameras": [str(c) for c in cameras], "timesteps": list(timesteps), "crop_size": crop_size,
        "num_frames": config.num_frames, "layout": layout.to_dict(), "flops_per_clip": flops,
        "clips_per_camera_timestep": per_ct,
        "clips_per_scale": [s.num_crops for s in layout.scales],
        "paper_clips_per_camera_timestep": PAPER_CLIPS_640x360 if (capture.width, capture.height) == (640, 360)
        else None,
        "sampled_clips": sources, "phrases": phrases,
        "preprocess": {"decode_seconds_per_frame": decode_frame_s, "decode_cpu_seconds_per_frame": decode_frame_cpu,
                       "crop_resize_seconds_per_camera_timestep": prep_s,
                       "crop_resize_cpu_seconds_per_camera_timestep": prep_cpu,
                       "extract_batch": EXTRACT_RGB_BATCH},
        "subsets": [{"name": s.name, "cameras": s.cameras, "timesteps": s.timesteps,
                     "camera_timesteps": s.camera_timesteps} for s in subsets],
        "rows": rows,
        "_thumbnails": video[:, [0, -1]],   # dropped from the JSON: the sampled clips' first and last frames
    }


def _fmt(value: float | None, digits: int = 3) -> str:
    if value is None:
        return "–"
    return f"{value:.{digits}g}" if value < 10 ** digits else f"{value:,.0f}"


def real_report_markdown(report: dict[str, Any], command: str | None = None) -> str:
    """The Markdown table of :func:`bench_viclip_real`'s report."""
    pre = report["preprocess"]
    w, h = report["image_size"]
    per_scale = " + ".join(str(n) for n in report["clips_per_scale"])
    paper = report["paper_clips_per_camera_timestep"]
    check = ("" if paper is None else f" (the paper's figure: {paper}; "
             f"{'equal' if paper == report['clips_per_camera_timestep'] else 'DIFFERENT'})")
    ratios = ", ".join(f"{s['ratio']:.4g}" for s in report["layout"]["scales"])
    lines = [f"# ViCLIP {report['size']} on real frames — RANDOM WEIGHTS", ""]
    if command:
        lines += [f"`{command}`", ""]
    lines += [
        f"**Weights:** {report['weights']}.", "",
        f"Frames: {report['dataset']}, training camera(s) {', '.join(report['cameras'])}, timestep(s) "
        f"{', '.join(map(str, report['timesteps']))}, {w}x{h}; {report['num_frames']}-frame tubes; crop pyramid "
        f"ratios {ratios}: {per_scale} = **{report['clips_per_camera_timestep']} clips per camera-timestep**"
        f"{check}, each resized to {report['crop_size']} px. Device {report['device']} ({report['device_name']}), "
        f"{report['threads']} torch threads, torch {report['torch']}; load average "
        f"{report['load_average_before'][0]} before, {report['load_average_after'][0]} after (other jobs share "
        f"the machine when it exceeds the core count: CPU seconds are the repeatable figure).", "",
        "| pre-processing (per camera-timestep) | s | CPU s |", "|---|---:|---:|",
        f"| JPEG decode, per frame (one new frame per camera-timestep) | {pre['decode_seconds_per_frame']:.4f} | "
        f"{pre['decode_cpu_seconds_per_frame']:.4f} |",
        f"| crop + resize to {report['crop_size']} + CLIP normalization, all {report['clips_per_camera_timestep']} "
        f"clips (batches of {pre['extract_batch']}) | {pre['crop_resize_seconds_per_camera_timestep']:.3f} | "
        f"{pre['crop_resize_cpu_seconds_per_camera_timestep']:.3f} |", "",
        f"Network: {report['rows'][0]['clips']} real clips per knob (spread over cameras and scales), "
        f"accuracy = worst cosine to the {report['reference_dtype']} reference embeddings of the same clips "
        f"and of {report['phrases']} random token rows. One clip through the video tower is "
        f"{report['flops_per_clip']['total'] / 1e12:.3g} TFLOP ({report['flops_per_clip']['attention'] / 1e12:.3g} of "
        f"them joint space-time attention); GFLOP/s = that over the wall seconds per clip.", "",
        "| dtype | batch | s / clip | CPU s / clip | GFLOP/s | s / phrase | s / camera-timestep "
        "| CPU s / camera-timestep | video min cos | text min cos | finite |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in report["rows"]:
        name = r["dtype"] + (" (reference)" if r["reference"] else "")
        if not r["supported"]:
            lines.append(f"| {name} | {r['batch_size']} | not supported on {report['device']}: {r['error']} "
                         "| | | | | | | | |")
            continue
        lines.append(f"| {name} | {r['batch_size']} | {_fmt(r['seconds_per_clip'])} | "
                     f"{_fmt(r['cpu_seconds_per_clip'])} | {_fmt(r['gflop_per_second'])} | "
                     f"{r['seconds_per_phrase']:.4f} | "
                     f"{_fmt(r['seconds_per_camera_timestep'])} | {_fmt(r['cpu_seconds_per_camera_timestep'])} | "
                     f"{r['video_min_cosine']:.6f} | {r['text_min_cosine']:.6f} | {'yes' if r['finite'] else 'NO'} |")
    subsets = report["subsets"]
    lines += ["", "Extrapolated extraction time, hours (CPU hours), one process on this device:", "",
              "| dtype | batch | " + " | ".join(f"{s['name']} ({s['cameras']} cams × {s['timesteps']} t)"
                                               for s in subsets) + " |",
              "|---|---:|" + "---:|" * len(subsets)]
    for r in report["rows"]:
        if r["supported"]:
            cells = " | ".join(f"{_fmt(r['extrapolated_hours'][s['name']])} "
                               f"({_fmt(r['extrapolated_cpu_hours'][s['name']])})" for s in subsets)
            lines.append(f"| {r['dtype']} | {r['batch_size']} | {cells} |")
    return "\n".join(lines) + "\n"


def write_real_report(report: dict[str, Any], prefix: Path, *, command: str | None = None,
                      overwrite: bool = True) -> list[Path]:
    """``prefix.json``, ``prefix.md`` and ``prefix.png`` (knob plot, extrapolation, the sampled clips)."""
    from fourlegs_engine.fileio import atomic_path, write_bytes_atomic, write_json_atomic
    prefix.parent.mkdir(parents=True, exist_ok=True)
    json_path, md_path, png_path = (prefix.with_suffix(s) for s in (".json", ".md", ".png"))
    thumbs = report.get("_thumbnails")
    public = {k: v for k, v in report.items() if not k.startswith("_")}
    if command:
        public["command"] = command
    write_json_atomic(json_path, public, overwrite=overwrite)
    write_bytes_atomic(md_path, real_report_markdown(public, command).encode(), overwrite=overwrite)

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    rows = [r for r in public["rows"] if r["supported"]]
    # CPU seconds on the CPU (repeatable on a shared machine); wall seconds on a GPU, whose work the CPU does not see
    on_cpu = public["device"] == "cpu"
    clip_key, hours_key = (("cpu_seconds_per_clip", "extrapolated_cpu_hours") if on_cpu
                           else ("seconds_per_clip", "extrapolated_hours"))
    fig = plt.figure(figsize=(12, 7.5))
    grid = fig.add_gridspec(2, 2, height_ratios=(3, 1.4))
    ax = fig.add_subplot(grid[0, 0])
    for dtype in dict.fromkeys(r["dtype"] for r in rows):
        sel = [r for r in rows if r["dtype"] == dtype]
        xs = [r[clip_key] for r in sel]
        ys = [1 - r["video_min_cosine"] + 1e-16 for r in sel]
        ax.plot(xs, ys, marker="o", label=dtype + (" (reference)" if sel[0]["reference"] else ""))
        for k, (r, x, y) in enumerate(zip(sel, xs, ys)):
            ax.annotate(f"b={r['batch_size']}", (x, y), xytext=(4, 6 - 12 * k), textcoords="offset points", fontsize=7)
    ax.set_xlabel(f"{'CPU' if on_cpu else 'wall'} seconds per {public['num_frames']}-frame clip")
    ax.set_ylabel(f"1 - worst cosine to {public['reference_dtype']}")
    ax.set_yscale("log")
    ax.set_title(f"ViCLIP {public['size']} on {public['device']}, RANDOM weights", fontsize=10)
    ax.legend(fontsize=8)
    bx = fig.add_subplot(grid[0, 1])
    subsets = public["subsets"]
    width = 0.8 / max(1, len(subsets))
    positions = np.arange(len(rows))
    for k, s in enumerate(subsets):
        bx.bar(positions + k * width, [r[hours_key][s["name"]] for r in rows], width,
               label=f"{s['name']} ({s['cameras']}×{s['timesteps']})")
    bx.set_xticks(positions + width * (len(subsets) - 1) / 2,
                  [f"{r['dtype']}\nb={r['batch_size']}" for r in rows], fontsize=7)
    bx.set_yscale("log")
    bx.set_ylabel(f"extrapolated {'CPU ' if on_cpu else ''}hours, one process on this device")
    bx.set_title(f"{public['clips_per_camera_timestep']} clips per camera-timestep", fontsize=10)
    bx.legend(fontsize=7)
    if thumbs is not None and len(thumbs):
        cx = fig.add_subplot(grid[1, :])
        mean = torch.tensor(CLIP_MEAN).view(1, 1, 3, 1, 1)
        std = torch.tensor(CLIP_STD).view(1, 1, 3, 1, 1)
        images = (thumbs.float() * std + mean).clamp(0, 1)               # (n, 2, 3, s, s)
        strip = torch.cat([torch.cat(list(pair), dim=1) for pair in images], dim=2)   # (3, 2s, n*s)
        cx.imshow(strip.permute(1, 2, 0).numpy())
        cx.set_axis_off()
        labels = ", ".join(f"cam {s['camera']} t={s['timestep']} clip {s['clip']} (scale {s['scale']})"
                           for s in public["sampled_clips"])
        cx.set_title(f"the real clips encoded (first frame above, last below): {labels}", fontsize=8)
    fig.tight_layout()
    with atomic_path(png_path, overwrite=overwrite) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return [json_path, md_path, png_path]
