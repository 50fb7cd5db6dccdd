"""Spatio-temporal teacher features: crop-pyramid encodings per timestep (paper §3.1, eq. 1-2).

For every timestep t and training camera, the 8-frame tube t-4..t+3 (edges repeat the first/last
frame) is cut into the crop pyramid of :mod:`.pyramid`; each crop tube is resized and encoded by the
video-text encoder in batches. The result of one timestep is one float16 array
``features/tNNNNNN.npy`` of shape (Σ_cameras num_crops, D) — crop-level features of all cameras and
scales, written atomically. Per-pixel features are never stored: they are interpolated on the fly
(:func:`.pyramid.interpolate_grid`), which keeps a 60-timestep, 12-camera scene at ~10 MB per
timestep instead of tens of GB.

Frames: ``input_kind == "rgb"`` encoders (ViCLIP) see the scene rendered in RGB from the training
cameras (black background), crops resized to 224 and CLIP-normalized. ``input_kind == "labels"``
encoders (the simulated encoder) see per-pixel label coverage: the scene's one-hot ground-truth
labels rendered as feature channels, i.e. channel l of pixel p = Σ_i α_i T_i [label_i = l].

Cost knobs (:mod:`.skipping`; :mod:`.budget` prices them): a camera subset, a timestep stride whose
in-between timesteps are filled from their encoded neighbours, the crop stride and pyramid levels, and
early exits that copy the features of crops that see an unchanged clip.
"""
from __future__ import annotations

import threading
import time
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import InputError
from ..scene.scene import Scene
from ..threads import torch_threads
from .pyramid import (DEFAULT_STRIDE_FRACTION, TUBE_OFFSETS, PyramidLayout, crop_layout, pyramid_ratios,
                      resize_crops, scale_crops, tube_indices)
from .skipping import (DEFAULT_UNCHANGED_BELOW, EARLY_EXITS, FILL_MODES, comparison_frames, encoded_timesteps,
                       fill_features, fill_sources, foreground_values, render_foreground, timestep_work,
                       unchanged_crops)
from .store import StepStore, format_ranges, parse_shard, select_timesteps

FEATURES_DIR = "features"
RGB_CROP_SIZE = 224
COVERAGE_MEANS = "means"  # label encoders with ``encode_coverage``: exact per-frame crop means


@dataclass
class ExtractConfig:
    """Settings that determine the extracted features (all enter the config hash).

    Attributes:
        ratios: crop side / image height per scale (5 steps 0.15..0.6 by default).
        crop_size: side the crops are resized to before encoding; None = the RGB encoder's
            ``image_size`` (224 for ViCLIP) and,
            for label encoders that offer ``encode_coverage`` (the simulated one, which only looks at
            each frame's mean coverage), ``"means"``: the exact per-frame crop means by average
            pooling instead of cutting and resizing crops.
        batch_size: crop tubes per encoder call (None: 32 for RGB encoders, whose 224 px tubes take
            4.8 MB each, 256 otherwise).
        split: camera split the features are extracted for.
        frame_scale: render the frames at this fraction of the camera resolution and upsample them
            bilinearly to full size before cutting crops (a speed knob; 1 = full resolution).
        cameras: indices of the split's cameras that are encoded (None: all); the others keep zero
            rows (no evidence).
        crop_stride: distance between neighbouring crops as a fraction of the crop side (0.5: paper).
        timestep_stride: encode every n-th timestep (and the last); the others are filled (``fill``:
            "interpolate" between the two encoded neighbours or "reuse" the nearer one).
        early_exit: "none" | "foreground" | "difference": copy the previous encoded timestep's feature
            of crops whose pixels stay unchanged (:func:`.skipping.unchanged_crops`, ``unchanged_below``).
    """

    ratios: tuple[float, ...] = field(default_factory=pyramid_ratios)
    crop_size: int | str | None = None
    batch_size: int | None = None
    split: str = "train"
    frame_scale: float = 1.0
    cameras: tuple[int, ...] | None = None
    crop_stride: float = DEFAULT_STRIDE_FRACTION
    timestep_stride: int = 1
    fill: str = "interpolate"
    early_exit: str = "none"
    unchanged_below: float = DEFAULT_UNCHANGED_BELOW

    def check(self, num_cameras: int | None = None) -> "ExtractConfig":
        if not 0 < self.frame_scale <= 1:
            raise InputError(f"must be in (0, 1], got {self.frame_scale}", field="frame_scale")
        if not 0 < self.crop_stride <= 1:
            raise InputError(f"must be in (0, 1], got {self.crop_stride}", field="--crop-stride")
        if int(self.timestep_stride) < 1:
            raise InputError(f"must be >= 1, got {self.timestep_stride}", field="--timestep-stride")
        if self.fill not in FILL_MODES:
            raise InputError(f"unknown fill {self.fill!r} (choose from {', '.join(FILL_MODES)})", field="--fill")
        if self.early_exit not in EARLY_EXITS:
            raise InputError(f"unknown early exit {self.early_exit!r} (choose from {', '.join(EARLY_EXITS)})",
                             field="--early-exit")
        if not self.unchanged_below >= 0:
            raise InputError(f"must be >= 0, got {self.unchanged_below}", field="unchanged_below")
        if self.cameras is not None:
            if not self.cameras:
                raise InputError("names no camera", field="cameras")
            bad = [c for c in self.cameras if c < 0 or (num_cameras is not None and c >= num_cameras)]
            if bad:
                raise InputError(f"camera index {bad[0]} is out of range 0..{(num_cameras or 1) - 1}",
                                 field="cameras")
        return self

    def knobs_dict(self) -> dict[str, Any]:
        """The cost knobs that differ from the paper's extraction (absent at their default, so the hashes of
        features extracted before the knobs existed stay valid)."""
        out: dict[str, Any] = {}
        if self.cameras is not None:
            out["cameras"] = sorted(int(c) for c in self.cameras)
        if self.crop_stride != DEFAULT_STRIDE_FRACTION:
            out["crop_stride"] = float(self.crop_stride)
        if int(self.timestep_stride) != 1:
            out["timestep_stride"] = int(self.timestep_stride)
            out["fill"] = self.fill
        if self.early_exit != "none":
            out["early_exit"] = self.early_exit
            out["unchanged_below"] = float(self.unchanged_below)
        return out

    def resolved_crop_size(self, input_kind: str, encoder: Any = None) -> int | str:
        if self.crop_size is not None:
            return self.crop_size
        if input_kind == "rgb":
            return int(getattr(encoder, "image_size", RGB_CROP_SIZE))
        return COVERAGE_MEANS if hasattr(encoder, "encode_coverage") else 32


def scene_signature(scene: Scene) -> dict[str, Any]:
    """What identifies the scene's geometry for cache checks (cheap: sizes, names, cameras)."""
    cams = scene.cameras.cameras(0, "train") if scene.cameras.num_timesteps else []
    return {"name": scene.name, "num_timesteps": scene.num_timesteps, "num_gaussians": scene.num_gaussians,
            "cameras": [[c.name, c.width, c.height] for c in cams]}


def extract_config_dict(scene: Scene, encoder: Any, config: ExtractConfig) -> dict[str, Any]:
    if hasattr(encoder, "check_masks"):  # annotation masks: which files exist enters the encoder's config
        encoder.check_masks(scene.cameras.cameras(0, config.split), scene.num_timesteps)
    return {"encoder": str(encoder.name), "dim": int(encoder.dim), "input_kind": str(encoder.input_kind),
            "ratios": [round(float(r), 6) for r in config.ratios], "tube": list(TUBE_OFFSETS),
            "crop_size": config.resolved_crop_size(encoder.input_kind, encoder),
            "frame_scale": float(config.frame_scale),
            "encoder_config": encoder.config() if hasattr(encoder, "config") else None, "split": config.split,
            "frames": ("rendered-rgb" if encoder.input_kind == "rgb" else "annotation-masks"
                       if hasattr(encoder, "coverage_frame") else "rendered-label-coverage"),
            "scene": scene_signature(scene), **config.knobs_dict()}


def camera_layouts(scene: Scene, t: int, ratios: Sequence[float], split: str = "train",
                   crop_stride: float = DEFAULT_STRIDE_FRACTION) -> tuple[list[PyramidLayout], list[int]]:
    """Crop pyramids of the cameras at timestep t and each camera's first row in the feature array."""
    layouts = [crop_layout(c.width, c.height, ratios, crop_stride) for c in scene.cameras.cameras(t, split)]
    offsets = list(np.cumsum([0] + [l.num_crops for l in layouts[:-1]]).astype(int)) if layouts else []
    return layouts, [int(o) for o in offsets]


def feature_store(scene: Scene, config_dict: dict[str, Any] | None = None) -> StepStore:
    """The features store of a bundle scene (``config_dict`` None: read it from the manifest)."""
    if scene.root is None:
        raise InputError("the scene must be a bundle on disk (write it with "
                         "fourlegs_engine.scene.write_bundle(scene, PATH) first)", field="scene")
    root = Path(scene.root) / FEATURES_DIR
    if config_dict is None:
        store = StepStore(root, "features", {}, scene.num_timesteps)
        meta = store.read_manifest()
        if meta is None:
            raise InputError("no extracted features; run `fourlegs extract` first", file=root / "manifest.json")
        store.config = meta["config"]
        return store
    return StepStore(root, "features", config_dict, scene.num_timesteps)


# --------------------------------------------------------------------------------- frames
class FrameSource:
    """Renders (and caches) the frames the encoder sees: (C,H,W) float32 per (timestep, camera)."""

    def __init__(self, scene: Scene, input_kind: str, split: str = "train", cache_frames: int = 64,
                 frame_scale: float = 1.0, encoder: Any = None):
        self.scene = scene
        # label encoders that read their own coverage frames (annotation masks) instead of rendered labels
        self.read_frames = encoder if hasattr(encoder, "coverage_frame") else None
        self.frame_scale = float(frame_scale)
        self.input_kind = input_kind
        self.split = split
        self.cache: OrderedDict[tuple, torch.Tensor] = OrderedDict()
        self.cache_frames = cache_frames
        self.render_seconds = 0.0
        self._lock = threading.Lock()  # cameras may be rendered from several threads
        if self.read_frames is not None:
            self.num_labels = int(self.read_frames.num_labels)
            self.read_frames.check_masks(scene.cameras.cameras(0, split), scene.num_timesteps)
        elif input_kind == "labels":
            g = scene.gaussians
            if g.labels is None:
                raise InputError("a label encoder needs per-Gaussian labels (synthetic scenes have them)",
                                 file=scene.root, field="labels")
            vocab = scene.metadata.get("labels")
            self.num_labels = len(vocab) if vocab else int(np.max(np.asarray(g.labels))) + 1
        elif input_kind != "rgb":
            raise InputError(f"unknown encoder input kind {input_kind!r} (expected 'rgb' or 'labels')",
                             field="input_kind")

    @property
    def channels(self) -> int:
        return 3 if self.input_kind == "rgb" else self.num_labels

    def frame(self, t: int, cam_index: int) -> torch.Tensor | None:
        """(C, H, W) frame of camera ``cam_index`` at ``t``; None where annotation masks do not cover it."""
        key = (t, cam_index)
        hit = self.cache.get(key)
        if hit is not None:
            self.cache.move_to_end(key)
            return hit
        start = time.perf_counter()
        img = self._render(t, cam_index)
        self.render_seconds += time.perf_counter() - start
        self.cache[key] = img
        while len(self.cache) > 2 * self.cache_frames:
            self.cache.popitem(last=False)
        return img

    def crop_means(self, t: int, cam_index: int, layout: PyramidLayout) -> torch.Tensor:
        """(num_crops, C) crop means of frame (t, camera), cached like the frames (thread-safe)."""
        key = (t, cam_index, "means")
        with self._lock:
            hit = self.cache.get(key)
            if hit is not None:
                self.cache.move_to_end(key)
                return hit
        start = time.perf_counter()
        frame = self._render(t, cam_index)      # not cached: only its crop means are kept
        seconds = time.perf_counter() - start
        if frame is None:
            return None
        hit = frame_crop_means(frame, layout)
        with self._lock:
            self.render_seconds += seconds
            self.cache[key] = hit
            while len(self.cache) > 2 * self.cache_frames:
                self.cache.popitem(last=False)
        return hit

    def tube(self, t: int, cam_index: int) -> torch.Tensor | None:
        """(L, C, H, W) frames t-4..t+3 of one camera, edge frames repeated (L = 8); frames annotation masks
        do not cover are left out (L < 8), None if none is covered."""
        frames = [self.frame(k, cam_index) for k in tube_indices(t, self.scene.num_timesteps)]
        frames = [f for f in frames if f is not None]
        return torch.stack(frames) if frames else None

    def _render(self, t: int, cam_index: int) -> torch.Tensor:
        if self.read_frames is not None:
            return self.read_frames.coverage_frame(t, self.scene.cameras.cameras(t, self.split)[cam_index])
        g = self.scene.gaussians
        frame = g.at(t)
        full = self.scene.cameras.cameras(t, self.split)[cam_index]
        camera = full if self.frame_scale == 1.0 else full.scaled(self.frame_scale)
        img = self._render_at(frame, camera, t)                       # (C, h, w)
        if camera.width != full.width or camera.height != full.height:
            img = F.interpolate(img[None], size=(full.height, full.width), mode="bilinear",
                                align_corners=False)[0]
        return img.clamp_(0.0, 1.0)

    def _render_at(self, frame: Any, camera: Any, t: int) -> torch.Tensor:
        from ..render import render_frame
        if self.input_kind == "rgb":
            out = render_frame(frame, camera, outputs=("rgb",))["rgb"]
        else:
            from .simulated import render_label_coverage
            return render_label_coverage(self.scene, camera, t, num_labels=self.num_labels).to(torch.float32)
        return out.detach().to(torch.float32).permute(2, 0, 1).contiguous().clamp_(0.0, 1.0)


# ------------------------------------------------------------------------------- extraction
@dataclass
class ExtractReport:
    timesteps_done: list[int]
    timesteps_skipped: list[int]
    seconds: float
    render_seconds: float
    encode_seconds: float
    crops_per_timestep: int
    #: clips the encoder saw, clips copied by early exits, timesteps filled from their neighbours,
    #: CPU seconds of the whole call (all threads)
    clips_encoded: int = 0
    clips_copied: int = 0
    timesteps_filled: list[int] = field(default_factory=list)
    cpu_seconds: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return {"done": self.timesteps_done, "skipped": self.timesteps_skipped, "seconds": self.seconds,
                "render_seconds": self.render_seconds, "encode_seconds": self.encode_seconds,
                "crops_per_timestep": self.crops_per_timestep, "clips_encoded": self.clips_encoded,
                "clips_copied": self.clips_copied, "filled": self.timesteps_filled,
                "cpu_seconds": self.cpu_seconds}


def extract_features(scene: Scene, encoder: Any, config: ExtractConfig | None = None, *,
                     timesteps: str | Sequence[int] | None = None, shard: str | tuple[int, int] | None = None,
                     overwrite: bool = False, progress: bool = False,
                     on_timestep: Callable[[int], None] | None = None) -> ExtractReport:
    """Encode the crop pyramid of every selected timestep into ``features/`` of the bundle.

    Finished timesteps are skipped (resume); a features directory made with another configuration
    raises :class:`ConfigMismatchError` unless ``overwrite``. With a timestep stride the selected
    timesteps off the stride's grid are filled from their encoded neighbours, which are encoded too
    (:func:`.skipping.timestep_work`); a shard fills only those whose neighbours are finished (the
    rest: a later run without ``--shard``).
    """
    config = config or ExtractConfig()
    config.check(scene.cameras.num_cameras(config.split))
    cfg = extract_config_dict(scene, encoder, config)
    # built before the store is opened: its input checks (annotation masks) leave nothing behind
    source = FrameSource(scene, encoder.input_kind, config.split,
                         cache_frames=max(64, 9 * scene.cameras.num_cameras(config.split)),
                         frame_scale=config.frame_scale, encoder=encoder)
    store = feature_store(scene, cfg).open(overwrite=overwrite)
    grid = encoded_timesteps(scene.num_timesteps, config.timestep_stride)
    encode_steps, fill_steps = timestep_work(scene.num_timesteps, select_timesteps(scene.num_timesteps, timesteps),
                                             config.timestep_stride, config.fill, parse_shard(shard) if
                                             shard is None or isinstance(shard, str) else tuple(shard))
    todo = [t for t in encode_steps if not store.is_done(t)]
    to_fill = [t for t in fill_steps if not store.is_done(t)]
    skipped = [t for t in sorted(encode_steps + fill_steps) if store.is_done(t)]
    crop_size = cfg["crop_size"]
    clip_norm = encoder.input_kind == "rgb"
    start, cpu_start = time.perf_counter(), time.process_time()
    encode_seconds = 0.0
    crops_per_t = 0
    coverage = crop_size == COVERAGE_MEANS
    selected = set(range(scene.cameras.num_cameras(config.split)) if config.cameras is None else config.cameras)
    signals = (ChangeSignals(scene, source, config.early_exit, config.split)
               if config.early_exit != "none" else None)
    counts = {"encoded": 0, "copied": 0}
    previous: tuple[int, np.ndarray] | None = None
    # label-coverage cameras are independent small jobs (a rasterization, crop means, a few encoder
    # calls): they run on parallel streams with one torch thread each, which keeps every core busy
    # where intra-op threads would mostly wait on each other; each camera's rows are its own, so the
    # features do not depend on the number of streams
    streams = extract_streams() if coverage else 1
    pool = ThreadPoolExecutor(streams) if streams > 1 else None
    lock = threading.Lock()
    bar = _progress(todo, progress, "extract")
    try:
        with torch_threads(1) if pool is not None else nullcontext():
            for t in bar:
                layouts, offsets = camera_layouts(scene, t, config.ratios, config.split, config.crop_stride)
                crops_per_t = sum(l.num_crops for l in layouts)
                # rows of a camera without any annotated frame in its tube stay zero: no evidence
                out = np.zeros((crops_per_t, int(encoder.dim)), dtype=np.float16)
                cameras = scene.cameras.cameras(t, config.split)
                before = grid[grid.index(t) - 1] if grid.index(t) > 0 else None
                prior = None
                if signals is not None and before is not None:
                    prior = (previous[1] if previous is not None and previous[0] == before
                             else store.load(before) if store.is_done(before) else None)

                def encode_camera(c: int) -> float:
                    """Encode camera c's crops of timestep t into its rows of ``out``; returns encoder seconds."""
                    if c not in selected:
                        return 0.0
                    layout = layouts[c]
                    keep = None  # (num_crops,) bool: crops to encode; the others copy the previous timestep's
                    if prior is not None:
                        same = signals.unchanged(c, layout, comparison_frames(t, before, scene.num_timesteps),
                                                 config.unchanged_below)
                        if same is not None:
                            rows = offsets[c] + np.flatnonzero(same.numpy())
                            out[rows] = prior[rows]
                            keep = ~same
                            with lock:
                                counts["copied"] += int(same.sum())
                    # one camera per batch: encoders may depend on the camera (the simulated one's bias)
                    cam_encoder = (encoder.bind_camera(cameras[c].name) if hasattr(encoder, "bind_camera")
                                   else encoder)
                    batch = config.batch_size or (32 if encoder.input_kind == "rgb" else 256)
                    batcher = _Batcher(cam_encoder, out, batch, coverage=coverage)
                    if coverage:
                        # crop means depend on one frame only: computed once per frame, shared by 8 tubes
                        frames = [source.crop_means(k, c, layout) for k in tube_indices(t, scene.num_timesteps)]
                        frames = [m for m in frames if m is not None]
                        if not frames:
                            return 0.0
                        idx = np.arange(layout.num_crops) if keep is None else np.flatnonzero(keep.numpy())
                        batcher.add(torch.stack(frames, 1)[idx], offsets[c] + idx)  # (n, L, C)
                    else:
                        tube = source.tube(t, c)
                        if tube is None:
                            return 0.0
                        for grid_s in layout.scales:
                            idx = np.arange(grid_s.num_crops)
                            crops = scale_crops(tube, grid_s)
                            if keep is not None:
                                idx = np.flatnonzero(keep[grid_s.offset:grid_s.offset + grid_s.num_crops].numpy())
                                crops = crops[idx]
                            # raw crops are small; resizing to 224 happens per batch (a 224 px tube is 4.8 MB)
                            batcher.add(crops, offsets[c] + grid_s.offset + idx,
                                        transform=lambda x: resize_crops(x, crop_size, clip_normalize=clip_norm))
                    batcher.flush()
                    with lock:
                        counts["encoded"] += batcher.encoded
                    return batcher.seconds

                cams = range(len(layouts))
                encode_seconds += sum(pool.map(encode_camera, cams) if pool is not None
                                      else map(encode_camera, cams))
                if not np.all(np.isfinite(out)):
                    raise InputError(f"the encoder produced NaN/Inf features at timestep {t}", field="encoder")
                store.save(t, out)
                previous = (t, out)
                if on_timestep is not None:
                    on_timestep(t)
    finally:
        if pool is not None:
            pool.shutdown()
    filled = []
    for t in to_fill:
        sources = fill_sources(t, grid, config.fill)
        if all(store.is_done(k) for k, _ in sources):
            store.save(t, fill_features([(store.load(k), w) for k, w in sources]))
            filled.append(t)
            if on_timestep is not None:
                on_timestep(t)
    return ExtractReport(todo, skipped, time.perf_counter() - start, source.render_seconds, encode_seconds,
                         crops_per_t, counts["encoded"], counts["copied"], filled, time.process_time() - cpu_start)


class ChangeSignals:
    """Per-frame, per-crop signals of one camera that say whether a crop's clip changed (early exits),
    cached per (frame, camera): mean foreground coverage, or mean absolute change from the frame before."""

    def __init__(self, scene: Scene, source: "FrameSource", mode: str, split: str = "train"):
        self.scene, self.source, self.mode, self.split = scene, source, mode, split
        self.foreground = foreground_values(scene) if mode == "foreground" else None
        if mode == "foreground" and self.foreground is None:
            raise InputError("early exit 'foreground' needs the scene's foreground flags (fitted and synthetic "
                             "scenes have them); use --early-exit difference", file=scene.root, field="foreground")
        self.cache: OrderedDict[tuple, torch.Tensor | None] = OrderedDict()
        self._lock = threading.Lock()

    def unchanged(self, c: int, layout: PyramidLayout, frames: Sequence[int], threshold: float) -> torch.Tensor | None:
        """(num_crops,) bool of camera ``c``: unchanged over ``frames``; None when a frame is unavailable."""
        return unchanged_crops(lambda k: self.signal(k, c, layout), frames, self.mode, threshold)

    def signal(self, k: int, c: int, layout: PyramidLayout) -> torch.Tensor | None:
        key = (k, c)
        with self._lock:
            if key in self.cache:
                return self.cache[key]
        if self.mode == "foreground":
            camera = self.scene.cameras.cameras(k, self.split)[c]
            value = frame_crop_means(render_foreground(self.scene, camera, k, self.foreground), layout)[:, 0]
        else:
            now, before = self.source.frame(k, c), self.source.frame(max(k - 1, 0), c)
            value = (None if now is None or before is None
                     else frame_crop_means((now - before).abs().sum(0, keepdim=True), layout)[:, 0])
        with self._lock:
            self.cache[key] = value
            while len(self.cache) > 64 * max(1, self.scene.cameras.num_cameras(self.split)):
                self.cache.popitem(last=False)
        return value


def extract_streams() -> int:
    """Cameras encoded concurrently: one per torch thread (torch's default is the core count)."""
    return max(1, min(torch.get_num_threads(), 8))


def crop_means(tube: torch.Tensor, grid: Any) -> torch.Tensor:
    """Per-frame channel means of every crop, zero padding included: (L,C,H,W) -> (n, L, C).

    Equal to ``scale_crops(tube, grid).mean((3, 4))``, computed from a float64 summed-area table
    (4 lookups per crop instead of k² additions).
    """
    return _sat_crop_means(summed_area_table(tube), grid).to(tube.dtype)


def summed_area_table(tube: torch.Tensor) -> torch.Tensor:
    """(L,C,H,W) -> (L,C,H+1,W+1) float64 inclusive 2-D prefix sums with a zero first row/column."""
    L, C, H, W = tube.shape
    sat = torch.zeros(L, C, H + 1, W + 1, dtype=torch.float64)
    torch.cumsum(tube.to(torch.float64), 2, out=sat[:, :, 1:, 1:])
    sat[:, :, 1:, 1:].cumsum_(3)
    return sat


def _sat_crop_means(sat: torch.Tensor, grid: Any) -> torch.Tensor:
    """Crop means (n, L, C) float64 of one scale from a :func:`summed_area_table`."""
    L, C = sat.shape[:2]
    H, W = sat.shape[2] - 1, sat.shape[3] - 1
    k, p = grid.kernel, grid.padding
    y0 = torch.arange(grid.ny) * grid.stride - p          # crop rows y0 .. y0+k-1 (may leave the image)
    x0 = torch.arange(grid.nx) * grid.stride - p
    ya, yb = y0.clamp(0, H), (y0 + k).clamp(0, H)
    xa, xb = x0.clamp(0, W), (x0 + k).clamp(0, W)
    total = (sat[:, :, yb][:, :, :, xb] - sat[:, :, ya][:, :, :, xb]
             - sat[:, :, yb][:, :, :, xa] + sat[:, :, ya][:, :, :, xa])   # (L, C, ny, nx)
    means = total / float(k * k)
    return means.reshape(L, C, grid.ny * grid.nx).permute(2, 0, 1).contiguous()


def frame_crop_means(frame: torch.Tensor, layout: PyramidLayout) -> torch.Tensor:
    """(C,H,W) one frame -> (num_crops, C) channel means of all its crops (all scales, layout order);
    one summed-area table serves every scale."""
    sat = summed_area_table(frame[None])
    return torch.cat([_sat_crop_means(sat, g)[:, 0] for g in layout.scales]).to(frame.dtype)


class _Batcher:
    """Collects crop tubes of one spatial size and encodes them ``batch_size`` at a time."""

    def __init__(self, encoder: Any, out: np.ndarray, batch_size: int, coverage: bool = False):
        self.encoder = encoder
        self.coverage = coverage
        self.out = out
        self.batch_size = max(1, int(batch_size))
        self.pending: list[tuple[torch.Tensor, np.ndarray]] = []
        self.count = 0
        self.seconds = 0.0
        self.encoded = 0

    def add(self, crops: torch.Tensor, rows: np.ndarray, transform: Any = None) -> None:
        """Queue crops (n, ...) for output ``rows``; ``transform`` (resize, normalize) runs per batch."""
        s = 0
        while s < crops.shape[0]:
            take = min(self.batch_size - self.count, crops.shape[0] - s)
            self.pending.append((crops[s:s + take], rows[s:s + take], transform))
            self.count += take
            s += take
            if self.count >= self.batch_size:
                self.flush()

    def flush(self) -> None:
        if not self.pending:
            return
        clips = torch.cat([t(c) if t is not None else c for c, _, t in self.pending])
        rows = np.concatenate([r for _, r, _ in self.pending])
        start = time.perf_counter()
        with torch.no_grad():
            feats = (self.encoder.encode_coverage(clips) if self.coverage
                     else self.encoder.encode_video(clips))
        self.seconds += time.perf_counter() - start
        self.encoded += int(clips.shape[0])
        if tuple(feats.shape) != (clips.shape[0], self.out.shape[1]):
            raise InputError(f"encoder returned shape {tuple(feats.shape)} for {clips.shape[0]} clips, "
                             f"expected ({clips.shape[0]}, {self.out.shape[1]})", field="encoder")
        self.out[rows] = feats.detach().float().cpu().numpy().astype(np.float16)
        self.pending.clear()
        self.count = 0


def check_features(scene: Scene) -> dict[str, Any]:
    """Merge/check step: which timesteps are finished, missing or unreadable."""
    store = feature_store(scene)
    layouts, _ = camera_layouts(scene, 0, store.config["ratios"], store.config.get("split", "train"),
                                store.config.get("crop_stride", DEFAULT_STRIDE_FRACTION))
    report = store.check((sum(l.num_crops for l in layouts), int(store.config["dim"])))
    report["missing_ranges"] = format_ranges(report["missing"])
    return report


def view_has_evidence(feats: np.ndarray, offset: int) -> bool:
    """Whether the camera whose crop rows start at ``offset`` of a timestep's (num_crops_total, D) features
    carries evidence: encoders write unit vectors; the rows of a view without annotation masks are zero."""
    return bool(np.any(np.asarray(feats[offset]) != 0))


def load_step_features(scene: Scene, store: StepStore, t: int) -> tuple[np.ndarray, list[PyramidLayout],
                                                                            list[int]]:
    """Memory-mapped (num_crops_total, D) float16 features of timestep t with the camera layouts."""
    if not store.is_done(t):
        raise InputError(f"features of timestep {t} are missing; run `fourlegs extract` (or check with "
                         "`fourlegs extract --check`)", file=store.root, field="features")
    feats = store.load(t)
    layouts, offsets = camera_layouts(scene, t, store.config["ratios"], store.config.get("split", "train"),
                                      store.config.get("crop_stride", DEFAULT_STRIDE_FRACTION))
    expected = sum(l.num_crops for l in layouts)
    if feats.shape[0] != expected:
        raise InputError(f"has {feats.shape[0]} crops, the cameras need {expected}", file=store.step_path(t),
                         field="features")
    return feats, layouts, offsets


def _progress(items: Sequence[int], enabled: bool, desc: str):
    if not enabled:
        return items
    from tqdm import tqdm
    return tqdm(items, desc=desc, unit="timestep")
