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

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from ..errors import InputError
from ..scene.scene import Scene
from .crop_encoding import COVERAGE_MEANS, RGB_CROP_SIZE, TimestepEncoder
from .frames import FrameSource
from .pyramid import DEFAULT_STRIDE_FRACTION, TUBE_OFFSETS, PyramidLayout, crop_layout, pyramid_ratios
from .skipping import DEFAULT_UNCHANGED_BELOW, EARLY_EXITS, FILL_MODES, LATENT_FILLS, encoded_timesteps, \
    feature_timesteps, fill_features, fill_sources, timestep_work
from .store import StepStore, format_ranges, parse_shard, select_timesteps

FEATURES_DIR = "features"


@dataclass
class ExtractOptions:
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
            "interpolate" between the two encoded neighbours' features or "reuse" the nearer one's; "latents":
            no features, the lift fills those timesteps in the field).
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

    def check(self, num_cameras: int | None = None) -> "ExtractOptions":
        if not 0.01 <= self.frame_scale <= 1:
            raise InputError(f"must be in [0.01, 1], got {self.frame_scale}", field="--frame-scale")
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


def extract_config_dict(scene: Scene, encoder: Any, config: ExtractOptions) -> dict[str, Any]:
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
        store.config = _manifest_config(meta, store.manifest_path)
    else:
        store = StepStore(root, "features", config_dict, scene.num_timesteps)
    config = store.config
    store.shape_of = lambda t: (sum(layout.num_crops for layout in camera_layouts(
        scene, t, config["ratios"], config.get("split", "train"),
        config.get("crop_stride", DEFAULT_STRIDE_FRACTION))[0]), int(config["dim"]))
    store.dtype = "float16"
    return store


def _manifest_config(meta: dict[str, Any], path: Path) -> dict[str, Any]:
    """The features' configuration from their manifest; InputError naming the field when it is malformed."""
    config = meta.get("config")
    if not isinstance(config, dict):
        raise InputError("must be a JSON object", file=path, field="config")
    ratios = config.get("ratios")
    if not (isinstance(ratios, list) and ratios and all(isinstance(r, (int, float)) and not isinstance(r, bool)
                                                        and 0 < r <= 1 for r in ratios)):
        raise InputError("must be a non-empty list of numbers in (0, 1]", file=path, field="config.ratios")
    dim = config.get("dim")
    if not (isinstance(dim, int) and not isinstance(dim, bool) and 0 < dim <= 1 << 16):
        raise InputError("must be an integer in 1..65536", file=path, field="config.dim")
    stride = config.get("crop_stride", DEFAULT_STRIDE_FRACTION)
    if not (isinstance(stride, (int, float)) and not isinstance(stride, bool) and 0 < stride <= 1):
        raise InputError("must be a number in (0, 1]", file=path, field="config.crop_stride")
    return config


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


def extract_features(scene: Scene, encoder: Any, config: ExtractOptions | None = None, *,
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
    config = config or ExtractOptions()
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
    if config.fill in LATENT_FILLS:  # the lift fills these timesteps in the field
        fill_steps = []
    todo = [t for t in encode_steps if not store.is_done(t)]
    skipped = [t for t in sorted(encode_steps + fill_steps) if store.is_done(t)]
    start, cpu_start = time.perf_counter(), time.process_time()
    crops_per_t = 0
    previous: tuple[int, np.ndarray] | None = None
    steps = TimestepEncoder(scene, encoder, source, config, cfg["crop_size"])
    try:
        for t in _progress(todo, progress, "extract"):
            layouts, offsets = camera_layouts(scene, t, config.ratios, config.split, config.crop_stride)
            crops_per_t = sum(l.num_crops for l in layouts)
            before = grid[grid.index(t) - 1] if grid.index(t) > 0 else None
            prior = None
            if config.early_exit != "none" and before is not None:
                prior = (previous if previous is not None and previous[0] == before
                         else (before, store.load(before)) if store.is_done(before) else None)
            out = steps.encode(t, layouts, offsets, prior)
            store.save(t, out)
            previous = (t, out)
            if on_timestep is not None:
                on_timestep(t)
    finally:
        steps.close()
    filled = fill_timesteps(store, [t for t in fill_steps if not store.is_done(t)], grid, config.fill, on_timestep)
    return ExtractReport(todo, skipped, time.perf_counter() - start, source.render_seconds, steps.seconds,
                         crops_per_t, steps.encoded, steps.copied, filled, time.process_time() - cpu_start)


def fill_timesteps(store: StepStore, to_fill: Sequence[int], grid: Sequence[int], fill: str,
                   on_timestep: Callable[[int], None] | None = None) -> list[int]:
    """Write the features of the timesteps off the stride's grid whose encoded neighbours are finished."""
    filled = []
    for t in to_fill:
        sources = fill_sources(t, grid, fill)
        if all(store.is_done(k) for k, _ in sources):
            store.save(t, fill_features([(store.load(k), w) for k, w in sources]))
            filled.append(t)
            if on_timestep is not None:
                on_timestep(t)
    return filled


def stored_timesteps(scene: Scene, config: dict[str, Any]) -> list[int]:
    """The timesteps a complete extraction with this features configuration has files for (all, or the
    stride's grid when the lift fills the others)."""
    return feature_timesteps(scene.num_timesteps, int(config.get("timestep_stride", 1)),
                             str(config.get("fill", "interpolate")))


def check_features(scene: Scene) -> dict[str, Any]:
    """Merge/check step: which timesteps are finished, missing or unreadable."""
    store = feature_store(scene)
    layouts, _ = camera_layouts(scene, 0, store.config["ratios"], store.config.get("split", "train"),
                                store.config.get("crop_stride", DEFAULT_STRIDE_FRACTION))
    report = store.check((sum(l.num_crops for l in layouts), int(store.config["dim"])))
    expected = set(stored_timesteps(scene, store.config))
    report["missing"] = [t for t in report["missing"] if t in expected]
    report["complete"] = not report["missing"] and not report["bad"]
    report["missing_ranges"] = format_ranges(report["missing"])
    return report


def view_has_evidence(feats: np.ndarray, offset: int) -> bool:
    """Whether the camera whose crop rows start at ``offset`` of a timestep's (num_crops_total, D) features
    carries evidence: encoders write unit vectors; the rows of a view without annotation masks are zero."""
    return bool(np.any(np.asarray(feats[offset]) != 0))


def load_step_features(scene: Scene, store: StepStore, t: int) -> tuple[np.ndarray, list[PyramidLayout],
                                                                            list[int]]:
    """Memory-mapped (num_crops_total, D) float16 features of timestep t with the camera layouts."""
    if not store.step_path(t).is_file():
        raise InputError(f"features of timestep {t} are missing; run `fourlegs extract` (or check with "
                         "`fourlegs extract --check`)", file=store.root, field="features")
    problem = store.problem(t)
    if problem is not None:
        raise InputError(f"{problem}; run `fourlegs extract` to compute it again", file=store.step_path(t),
                         field="features")
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
