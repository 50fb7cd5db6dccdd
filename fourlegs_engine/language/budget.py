"""The extraction plan and its price, before the work: clips, TFLOP and the time on this device.

An :class:`ExtractPlan` names the cost knobs of :mod:`.skipping` in scene-independent terms (k cameras,
a timestep stride, pyramid levels, a crop stride, an early exit); :meth:`ExtractPlan.extract_config`
turns it into the :class:`~.extract.ExtractOptions` of one scene. :func:`count_plan` counts, exactly,
what that configuration encodes and renders over the selected timesteps (the early exits' share is
measured on a few sampled camera-timesteps); :func:`calibrate` times the real network on the chosen
device and precision for a few seconds, with the extraction's own cropping, resizing and batching;
:func:`estimate_plan` puts both together. :func:`check_budget` refuses a plan above a time budget.

The plans themselves (:class:`ExtractPlan`, the named :data:`PLANS`) live in :mod:`.plans`, which is cheap
to import; they are re-exported here.
"""
from __future__ import annotations

import math
import re
import time
from dataclasses import asdict, dataclass
from typing import Any, Sequence

import numpy as np
import torch

from ..errors import InputError
from ..scene.scene import Scene
from .crop_encoding import COVERAGE_MEANS
from .extract import ExtractOptions, camera_layouts, extract_config_dict
from .frames import ChangeSignals, FrameSource
from .plans import ExtractPlan, resolve_plan
from .pyramid import pyramid_ratios, resize_crops, scale_crops, tube_indices
from .skipping import comparison_frames, encoded_timesteps, timestep_work
from .store import parse_shard, select_timesteps

#: seconds the calibration spends on the network, at least (one warm-up call is not counted)
CALIBRATION_SECONDS = 3.0
#: camera-timesteps sampled to measure the share of crops an early exit copies
EXIT_SAMPLES = 3


@dataclass
class PlanCounts:
    """What a configuration encodes over the selected timesteps (exact, except the early exits' share).

    Attributes:
        timesteps: the timesteps whose features the run writes; encoded: those it encodes (the selected
            ones on the stride's grid and the grid neighbours the others are filled from); filled: the others.
        cameras: training cameras; cameras_encoded: those the plan encodes.
        clips_per_view: crops of one camera-timestep (plan's pyramid; cameras of one size: one value).
        clips_full: clips the paper's extraction encodes over the selected timesteps.
        clips_planned: clips of the plan before early exits.
        exit_share: measured share of crops an early exit copies (0 without one), and the
            camera-timesteps it was measured on.
        clips_expected: clips the encoder is expected to see.
        frames: frames rendered (or read).
        signal_frames: extra per-frame renders an early exit needs (foreground coverage).
    """

    timesteps: list[int]
    encoded: list[int]
    filled: list[int]
    cameras: int
    cameras_encoded: list[int]
    clips_per_view: int
    clips_full: int
    clips_planned: int
    exit_share: float = 0.0
    exit_samples: int = 0
    clips_expected: float = 0.0
    frames: int = 0
    signal_frames: int = 0

    @property
    def reduction(self) -> float:
        """How many times fewer clips than the paper's extraction."""
        return self.clips_full / max(self.clips_expected, 1e-9)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["reduction"] = self.reduction
        return d


def count_plan(scene: Scene, config: ExtractOptions, timesteps: str | Sequence[int] | None = None,
               shard: str | None = None, *, exit_share: float | None = None) -> PlanCounts:
    """Count what ``config`` encodes over the selected timesteps; ``exit_share`` is the early exit's share
    of copied crops (measure it with :func:`measure_exit_share`; None: 0)."""
    T = scene.num_timesteps
    selection = select_timesteps(T, timesteps)
    grid = encoded_timesteps(T, config.timestep_stride)
    needed, filled = timestep_work(T, selection, config.timestep_stride, config.fill, parse_shard(shard))
    steps = sorted(set(needed) | set(filled))
    num_cams = scene.cameras.num_cameras(config.split)
    cams = list(range(num_cams)) if config.cameras is None else sorted(config.cameras)
    full_layouts, _ = camera_layouts(scene, 0, pyramid_ratios(), config.split)
    layouts, _ = camera_layouts(scene, 0, config.ratios, config.split, config.crop_stride)
    per_cam = [l.num_crops for l in layouts]
    clips_full = len(steps) * sum(l.num_crops for l in full_layouts)
    clips_planned = len(needed) * sum(per_cam[c] for c in cams)
    share = float(exit_share or 0.0) if config.early_exit != "none" else 0.0
    # a timestep whose previous encoded timestep is not encoded in the same run has nothing to copy from
    needed_set = set(needed)
    first_steps = {t for t in needed if grid.index(t) == 0 or grid[grid.index(t) - 1] not in needed_set}
    clips_expected = (len(first_steps) + (len(needed) - len(first_steps)) * (1.0 - share)) * sum(per_cam[c] for c in cams)
    frames = set()
    signal = set()
    for t in needed:
        frames.update(tube_indices(t, T))
        if config.early_exit != "none" and t not in first_steps:
            span = comparison_frames(t, grid[grid.index(t) - 1], T)
            if config.early_exit == "difference":
                frames.update(span)
            else:
                signal.update(span)
    return PlanCounts(steps, needed, filled, num_cams, cams, int(per_cam[cams[0]]) if cams else 0,
                      int(clips_full), int(clips_planned), share, 0, float(clips_expected),
                      len(frames) * len(cams), len(signal) * len(cams))


def measure_exit_share(scene: Scene, encoder: Any, config: ExtractOptions, timesteps: Sequence[int],
                       samples: int = EXIT_SAMPLES) -> tuple[float, int, float, float]:
    """Share of crops the early exit copies, measured on up to ``samples`` camera-timesteps spread over
    the encoded ``timesteps`` (each after the first grid timestep) and cameras; also the number measured
    and the wall and CPU seconds per signal frame (zeros when nothing could be measured)."""
    if config.early_exit == "none":
        return 0.0, 0, 0.0, 0.0
    T = scene.num_timesteps
    grid = encoded_timesteps(T, config.timestep_stride)
    candidates = [t for t in timesteps if t in set(grid) and grid.index(t) > 0]
    if not candidates:
        return 0.0, 0, 0.0, 0.0
    num_cams = scene.cameras.num_cameras(config.split)
    cams = list(range(num_cams)) if config.cameras is None else sorted(config.cameras)
    layouts, _ = camera_layouts(scene, 0, config.ratios, config.split, config.crop_stride)
    source = FrameSource(scene, encoder.input_kind, config.split, frame_scale=config.frame_scale, encoder=encoder)
    signals = ChangeSignals(scene, source, config.early_exit, config.split)
    picks = np.linspace(0, len(candidates) - 1, min(samples, len(candidates))).round().astype(int)
    shares, frames = [], 0
    start, cpu_start = time.perf_counter(), time.process_time()
    for i, p in enumerate(picks):
        t = candidates[int(p)]
        c = cams[(i * max(1, len(cams) // max(1, len(picks)))) % len(cams)]
        span = comparison_frames(t, grid[grid.index(t) - 1], T)
        same = signals.unchanged(c, layouts[c], span, config.unchanged_below)
        frames += len(span)
        if same is not None:
            shares.append(float(same.float().mean()))
    seconds, cpu = time.perf_counter() - start, time.process_time() - cpu_start
    if not shares:
        return 0.0, 0, 0.0, 0.0
    return float(np.mean(shares)), len(shares), seconds / max(frames, 1), cpu / max(frames, 1)


# ---------------------------------------------------------------------------------- calibration
@dataclass
class Calibration:
    """Seconds per clip and per frame of the real pipeline on one device and precision (wall and CPU).

    ``clip_s`` covers resizing, normalizing and the network (the whole per-clip path of extraction);
    ``frame_s`` rendering (or reading) one frame; ``view_s`` cutting one camera-timestep's crops out of
    its tube (every scale).
    """

    device: str
    dtype: str
    batch: int
    clips_timed: int
    clip_s: float
    clip_cpu_s: float
    network_s: float
    frame_s: float
    frame_cpu_s: float
    seconds_spent: float
    flops_per_clip: float | None = None
    view_s: float = 0.0
    view_cpu_s: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _network_batch(encoder: Any, config: ExtractOptions) -> int:
    batch = config.batch_size or (32 if encoder.input_kind == "rgb" else 256)
    return int(min(batch, getattr(encoder, "batch_size", batch)))


def _sync(encoder: Any) -> None:
    device = getattr(encoder, "device", None)
    if device is not None and getattr(device, "type", "cpu") == "cuda":
        torch.cuda.synchronize(device)


def calibrate(scene: Scene, encoder: Any, config: ExtractOptions, *, seconds: float = CALIBRATION_SECONDS,
              timestep: int | None = None) -> Calibration:
    """Time the extraction's per-frame and per-clip work with the real encoder for a few seconds.

    One camera-timestep's tube is rendered (seconds per frame), its crops are cut; then batches of real
    clips (from every scale) go through the transform and the network: first one clip (its call is the
    warm-up), then, as many times as fit in ``seconds`` (at least once), a batch of the size extraction
    uses or, where one such batch would take longer than ``seconds``, as many clips as fit.
    """
    cams = list(range(scene.cameras.num_cameras(config.split))) if config.cameras is None else sorted(config.cameras)
    if not cams:
        raise InputError("the plan encodes no camera", field="--camera-subset")
    c = cams[0]
    t = scene.num_timesteps // 2 if timestep is None else int(timestep)
    cfg = extract_config_dict(scene, encoder, config)
    crop_size = cfg["crop_size"]
    coverage = crop_size == COVERAGE_MEANS
    source = FrameSource(scene, encoder.input_kind, config.split, frame_scale=config.frame_scale, encoder=encoder)
    layouts, _ = camera_layouts(scene, t, config.ratios, config.split, config.crop_stride)
    layout = layouts[c]
    spent = time.perf_counter()
    wall, cpu = time.perf_counter(), time.process_time()
    distinct = sorted(set(tube_indices(t, scene.num_timesteps)))
    if coverage:
        frames = [source.crop_means(k, c, layout) for k in distinct]
    else:
        frames = [source.frame(k, c) for k in distinct]
    frame_s = (time.perf_counter() - wall) / len(distinct)
    frame_cpu_s = (time.process_time() - cpu) / len(distinct)
    if any(f is None for f in frames):
        raise InputError(f"camera {c} has no frame at timestep {t} to calibrate on (annotation masks?)",
                         field="calibration")
    lookup = dict(zip(distinct, frames))
    tube_frames = [lookup[k] for k in tube_indices(t, scene.num_timesteps)]
    if coverage:
        pool = torch.stack(tube_frames, 1)                                   # (n, L, C) crop means
        transform = None
    view_s = view_cpu_s = 0.0
    if not coverage:
        tube = torch.stack(tube_frames)
        w0, c0 = time.perf_counter(), time.process_time()
        per_scale = [scale_crops(tube, g).contiguous() for g in layout.scales]
        view_s, view_cpu_s = time.perf_counter() - w0, time.process_time() - c0
        # real clips from every scale, interleaved so that any prefix mixes the scales
        order = [s[i:i + 1] for i in range(max(len(s) for s in per_scale)) for s in per_scale if i < len(s)]
        pool = None
        transform = lambda x: resize_crops(x, crop_size, clip_normalize=encoder.input_kind == "rgb")  # noqa: E731
    encode = encoder.encode_coverage if coverage else encoder.encode_video
    batch = _network_batch(encoder, config)

    def clips(n: int, start: int = 0) -> list[torch.Tensor]:
        """n real clips as groups of one crop size (extraction also resizes each scale's crops apart)."""
        if coverage:
            return [pool[(torch.arange(n) + start) % pool.shape[0]]]
        picked = [order[(start + i) % len(order)] for i in range(n)]
        sizes = list(dict.fromkeys(p.shape[-1] for p in picked))
        return [torch.cat([p for p in picked if p.shape[-1] == k]) for k in sizes]

    def run(n: int, start: int) -> tuple[float, float, float]:
        """(wall, CPU, network wall) seconds of n clips through transform + network."""
        groups = clips(n, start)
        w0, c0 = time.perf_counter(), time.process_time()
        x = torch.cat([transform(g) for g in groups]) if transform is not None else groups[0]
        n0 = time.perf_counter()
        with torch.no_grad():
            out = encode(x)
        _sync(encoder)
        w1 = time.perf_counter()
        if not bool(torch.isfinite(out).all()):
            raise InputError("the encoder produced NaN/Inf features during calibration", field="encoder")
        return w1 - w0, time.process_time() - c0, w1 - n0

    probe_wall, _, _ = run(1, 0)                                    # warm-up (and a first figure)
    if str(getattr(encoder, "device", "cpu")).startswith("cuda"):
        probe_wall, _, _ = run(1, 0)                                # the first GPU call pays for its set-up
    n = int(max(1, min(batch, math.floor(seconds / max(probe_wall, 1e-6)))))
    if n > 1:
        run(n, 1)                                                    # warm-up of this batch size
    total = [0.0, 0.0, 0.0]
    timed = 0
    while timed == 0 or total[0] < seconds:
        w, cp, net = run(n, 1 + timed)
        total = [total[0] + w, total[1] + cp, total[2] + net]
        timed += n
        if timed >= 64 * n:
            break
    flops = None
    model_config = getattr(encoder, "model_config", None)
    if model_config is not None:
        from .viclip.model import video_clip_flops
        flops = float(video_clip_flops(model_config)["total"])
    device = str(getattr(encoder, "device", "cpu"))
    dtype = (str(encoder.model.temp.dtype).replace("torch.", "") if hasattr(encoder, "model") else "float32")
    return Calibration(device, dtype, n, timed, total[0] / timed, total[1] / timed, total[2] / timed,
                       frame_s, frame_cpu_s, time.perf_counter() - spent, flops, view_s, view_cpu_s)


# ------------------------------------------------------------------------------------- estimate
@dataclass
class PlanEstimate:
    """A plan, what it encodes and what it will cost here (seconds and CPU seconds)."""

    plan: ExtractPlan
    config: ExtractOptions
    counts: PlanCounts
    calibration: Calibration | None
    seconds: float | None
    cpu_seconds: float | None
    encoder: str
    fps: float | None = None

    @property
    def tflop(self) -> float | None:
        fl = self.calibration.flops_per_clip if self.calibration else None
        return None if fl is None else self.counts.clips_expected * fl / 1e12

    def within(self, budget_s: float | None) -> bool:
        return budget_s is None or self.seconds is None or self.seconds <= budget_s

    def lines(self) -> list[str]:
        """The plan as a few lines for a terminal or a panel."""
        k = self.counts
        cal = self.calibration
        levels = ", ".join(f"{r:g}" for r in self.config.ratios)
        lines = [self.plan.describe(self.fps),
                 f"  {len(k.cameras_encoded)} of {k.cameras} cameras x {len(k.encoded)} encoded timesteps"
                 + (f" (+{len(k.filled)} filled by {self.config.fill})" if k.filled else "")
                 + f"; {k.clips_per_view} clips per camera-timestep (ratios {levels}, crop stride "
                 f"{self.config.crop_stride:g}; the paper's pyramid: "
                 f"{int(k.clips_full / max(len(k.timesteps), 1) / max(k.cameras, 1))})"]
        clips = f"  clips: {k.clips_expected:,.0f} of the full extraction's {k.clips_full:,} ({k.reduction:.1f}x fewer)"
        if self.config.early_exit != "none":
            clips += (f"; early exit {self.config.early_exit} copies {100 * k.exit_share:.0f} % of the crops "
                      f"(measured on {k.exit_samples} camera-timesteps)")
        lines.append(clips)
        if self.tflop is not None:
            lines.append(f"  {cal.flops_per_clip / 1e12:.3g} TFLOP per clip: {self.tflop:,.1f} TFLOP")
        if cal is not None and self.seconds is not None:
            lines.append(f"  estimate on {cal.device} ({self.encoder}, {cal.dtype}, batch {cal.batch}): "
                         f"{format_duration(self.seconds)} ({cal.clip_s:.4g} s per clip over {cal.clips_timed} "
                         f"calibration clips, {cal.frame_s:.3g} s per frame x {k.frames:,} frames; "
                         f"calibration took {cal.seconds_spent:.1f} s)")
        return lines

    def to_dict(self) -> dict[str, Any]:
        return {"plan": asdict(self.plan), "config": self.config.knobs_dict() | {"ratios": list(self.config.ratios)},
                "counts": self.counts.to_dict(), "calibration": self.calibration.to_dict() if self.calibration else None,
                "seconds": self.seconds, "cpu_seconds": self.cpu_seconds, "tflop": self.tflop, "encoder": self.encoder}


def estimate_seconds(counts: PlanCounts, calibration: Calibration, signal_frame_s: float = 0.0,
                     signal_frame_cpu_s: float = 0.0) -> tuple[float, float]:
    """(wall, CPU) seconds: frames x seconds per frame + camera-timesteps x seconds to cut their crops +
    clips x seconds per clip (+ early-exit signals)."""
    views = len(counts.encoded) * len(counts.cameras_encoded)
    wall = counts.frames * calibration.frame_s + views * calibration.view_s \
        + counts.clips_expected * calibration.clip_s + counts.signal_frames * signal_frame_s
    cpu = counts.frames * calibration.frame_cpu_s + views * calibration.view_cpu_s \
        + counts.clips_expected * calibration.clip_cpu_s + counts.signal_frames * signal_frame_cpu_s
    return float(wall), float(cpu)


def estimate_plan(scene: Scene, encoder: Any, plan: str | ExtractPlan | None = "auto",
                  base: ExtractOptions | None = None, *, timesteps: str | Sequence[int] | None = None,
                  shard: str | None = None, calibrate_seconds: float = CALIBRATION_SECONDS) -> PlanEstimate:
    """The plan's counts and its estimated time on the encoder's device (calibration included)."""
    resolved = resolve_plan(plan, encoder)
    config = resolved.extract_config(scene, base)
    counts = count_plan(scene, config, timesteps, shard)
    signal_s = signal_cpu_s = 0.0
    if config.early_exit != "none":
        share, samples, signal_s, signal_cpu_s = measure_exit_share(
            scene, encoder, config, counts.encoded or encoded_timesteps(scene.num_timesteps, config.timestep_stride))
        counts = count_plan(scene, config, timesteps, shard, exit_share=share)
        counts.exit_samples = samples
    cal = calibrate(scene, encoder, config, seconds=calibrate_seconds)
    wall, cpu = estimate_seconds(counts, cal, signal_s, signal_cpu_s)
    return PlanEstimate(resolved, config, counts, cal, wall, cpu, str(getattr(encoder, "name", "encoder")),
                        float(scene.fps))


# ---------------------------------------------------------------------------------------- budget
_UNITS = {"s": 1.0, "sec": 1.0, "m": 60.0, "min": 60.0, "h": 3600.0, "d": 86400.0}


def parse_duration(text: str | float | None, field: str = "--budget") -> float | None:
    """"90s", "30m", "2h", "1.5d" or plain seconds -> seconds; None stays None."""
    if text is None:
        return None
    if isinstance(text, (int, float)):
        value = float(text)
    else:
        m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([a-z]*)\s*", str(text).lower())
        if not m or (m.group(2) and m.group(2) not in _UNITS):
            raise InputError(f"cannot parse {text!r}; use e.g. 90s, 30m, 2h or 1.5d", field=field)
        value = float(m.group(1)) * _UNITS.get(m.group(2) or "s", 1.0)
    if not (math.isfinite(value) and value > 0):
        raise InputError(f"must be a positive duration, got {text!r}", field=field)
    return value


def format_duration(seconds: float) -> str:
    """Seconds as the largest sensible unit: "42 s", "12.5 min", "3.2 h", "2.1 days"."""
    if seconds < 120:
        return f"{seconds:.1f} s"
    if seconds < 7200:
        return f"{seconds / 60:.1f} min"
    if seconds < 3 * 86400:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:.1f} days"


class BudgetExceeded(InputError):
    """The plan's estimate is above the time budget and going on was not asked for."""


def check_budget(estimate: PlanEstimate, budget_s: float | None, *, go_on: bool = False) -> None:
    """Raise :class:`BudgetExceeded` when the estimate is above ``budget_s`` (unless ``go_on``)."""
    if go_on or estimate.within(budget_s):
        return
    raise BudgetExceeded(f"plan {estimate.plan.name} is estimated at {format_duration(estimate.seconds)}, above the "
                         f"budget of {format_duration(budget_s)}; choose a cheaper plan (--plan default, "
                         f"--camera-subset, --timestep-stride, --levels, --crop-stride, --early-exit) or pass "
                         f"--over-budget to go on", field="--budget")
