"""Ground truth of the synthetic grounding benchmark: temporal segments, visible masks and boxes.

For a query whose answer is the label set S (``queries.json``):

* **Temporal**: frame t is positive when at least one Gaussian carries a label of S at t (the action
  happens in the scene; the same frames for every view).
* **Spatial** (per camera and frame): the pixel-level *visible* mask. The scene is rendered with one-hot
  label features, so channel c at a pixel is ``Σ_{i: label_i = c} α_i T_i`` over the whole scene's
  front-to-back order: occluders reduce the transmittance of what lies behind them. A pixel belongs
  to the mask when the Gaussians of S contribute more than ``VISIBILITY_THRESHOLD`` = 0.5 of its
  colour (they are what the pixel shows). The box is the tight box of the mask (x1, y1 exclusive,
  :func:`fourlegs_bench.metrics.mask_to_box`); NaN when the mask is empty (fully occluded or out
  of view).

Results are cached in the bundle under ``ground_truth/`` (``meta.json``, ``temporal.json``,
``<camera>.masks.npy`` (T,Q,H,W) bool, ``<camera>.boxes.npy`` (T,Q,4) float64), computed lazily per
camera and rewritten only if the queries, labels, threshold or version change.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np
import torch

from fourlegs_engine.errors import InputError
from fourlegs_engine.fileio import load_npy, read_json, save_npy_atomic, write_json_atomic
from fourlegs_engine.scene.camera import Camera
from fourlegs_engine.scene.scene import Scene
from .metrics import mask_to_box

GT_VERSION = 1
VISIBILITY_THRESHOLD = 0.5
GT_DIR = "ground_truth"
DEFAULT_FRAME_WINDOW = 12


def scene_labels(scene: Scene) -> list[str]:
    labels = (scene.metadata or {}).get("labels")
    if not labels or scene.gaussians.labels is None:
        raise InputError("the scene has no ground-truth labels (generate one with `fourlegs generate`)",
                         file=scene.root, field="labels")
    return [str(x) for x in labels]


def scene_queries(scene: Scene) -> dict[str, list[str]]:
    """{query text: [label names]} from ``queries.json`` (bundle) or the scene metadata."""
    from fourlegs_engine.demo.synthetic import QUERIES_FILE, read_queries

    if scene.root is not None and (Path(scene.root) / QUERIES_FILE).is_file():
        queries = read_queries(scene.root)
    else:
        queries = {k: list(v) for k, v in ((scene.metadata or {}).get("queries") or {}).items()}
    if not queries:
        raise InputError("the scene lists no benchmark queries", file=scene.root, field="queries")
    labels = set(scene_labels(scene))
    for text, names in queries.items():
        unknown = [n for n in names if n not in labels]
        if unknown:
            raise InputError(f"query {text!r} refers to unknown label(s) {unknown}", file=scene.root,
                             field="queries")
    return queries


def label_ids(scene: Scene, names: Iterable[str]) -> list[int]:
    vocab = scene_labels(scene)
    return [vocab.index(n) for n in names]


def temporal_ground_truth(scene: Scene, queries: dict[str, list[str]] | None = None) -> dict[str, np.ndarray]:
    """{query: (T,) bool}: frames where a Gaussian carries one of the query's labels."""
    queries = scene_queries(scene) if queries is None else queries
    labels = scene.gaussians.labels
    out = {}
    for text, names in queries.items():
        ids = np.asarray(label_ids(scene, names))
        out[text] = np.array([bool(np.isin(np.asarray(labels[t]), ids).any())
                              for t in range(scene.num_timesteps)])
    return out


def segments_of(frames: np.ndarray) -> list[tuple[int, int]]:
    """Inclusive (start, end) runs of True in a (T,) bool array."""
    f = np.asarray(frames, dtype=bool)
    edges = np.diff(np.concatenate([[0], f.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    return [(int(a), int(b)) for a, b in zip(starts, ends)]


class CoverageVideo:
    """Lazily rendered label-coverage frames of one camera: ``video[t] -> (C,H,W)`` float32.

    Keeps a sliding window of recent frames (enough for the 8-frame tubes of a forward sweep) so a
    full-size scene never holds all frames in memory.
    """

    def __init__(self, scene: Scene, camera: Camera, *, window: int = DEFAULT_FRAME_WINDOW):
        self.scene = scene
        self.camera = camera
        self.num_labels = len(scene_labels(scene))
        self.window = max(int(window), 8)
        self._frames: dict[int, torch.Tensor] = {}
        self.renders = 0

    def __len__(self) -> int:
        return self.scene.num_timesteps

    def __getitem__(self, t: int) -> torch.Tensor:
        from fourlegs_engine.language.coverage import render_label_coverage

        t = int(t)
        if t not in self._frames:
            self._frames[t] = render_label_coverage(self.scene, self.camera, t, num_labels=self.num_labels)
            self.renders += 1
            if len(self._frames) > self.window:
                for old in sorted(self._frames, key=lambda k: abs(k - t), reverse=True)[:len(self._frames) - self.window]:
                    del self._frames[old]
        return self._frames[t]


def visible_masks(coverage: torch.Tensor, label_sets: Sequence[Sequence[int]],
                  threshold: float = VISIBILITY_THRESHOLD) -> np.ndarray:
    """(C,H,W) label coverage -> (Q,H,W) bool: pixels where the labels of each set contribute > threshold."""
    cov = coverage.detach().to(torch.float64)
    out = np.zeros((len(label_sets),) + tuple(cov.shape[1:]), dtype=bool)
    for q, ids in enumerate(label_sets):
        if len(ids):
            out[q] = (cov[list(ids)].sum(0) > threshold).numpy()
    return out


def boxes_of(masks: np.ndarray) -> np.ndarray:
    """(..., H, W) bool -> (..., 4) float64 tight boxes, NaN rows where the mask is empty."""
    lead = masks.shape[:-2]
    flat = masks.reshape((-1,) + masks.shape[-2:])
    out = np.full((flat.shape[0], 4), np.nan)
    for i, m in enumerate(flat):
        b = mask_to_box(m)
        if b is not None:
            out[i] = b
    return out.reshape(lead + (4,))


@dataclass
class GroundTruth:
    """Benchmark ground truth of one scene.

    Attributes:
        queries: query texts in order (index q).
        labels: {query: [label names]}.
        frames: {query: (T,) bool} temporal ground truth.
        masks: {camera name: (T,Q,H,W) bool} visible masks (memory-mapped when read from the cache).
        boxes: {camera name: (T,Q,4) float64} boxes (NaN rows: empty mask).
        threshold: the visibility threshold used.
    """

    queries: list[str]
    labels: dict[str, list[str]]
    frames: dict[str, np.ndarray]
    masks: dict[str, np.ndarray] = field(default_factory=dict)
    boxes: dict[str, np.ndarray] = field(default_factory=dict)
    threshold: float = VISIBILITY_THRESHOLD

    def segments(self, query: str) -> list[tuple[int, int]]:
        return segments_of(self.frames[query])

    def mask(self, camera: str, query: str, t: int) -> np.ndarray:
        return np.asarray(self.masks[camera][t, self.queries.index(query)])

    def box(self, camera: str, query: str, t: int) -> np.ndarray:
        return np.asarray(self.boxes[camera][t, self.queries.index(query)])


def _config_key(scene: Scene, queries: dict[str, list[str]], threshold: float) -> str:
    gen = (scene.metadata or {}).get("generator", {})
    blob = json.dumps({"version": GT_VERSION, "generator": gen, "labels": scene_labels(scene),
                       "queries": queries, "threshold": threshold, "T": scene.num_timesteps,
                       "N": scene.num_gaussians}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def _safe_name(camera: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in camera) or "camera"


def compute_camera_ground_truth(video: CoverageVideo, label_sets: Sequence[Sequence[int]],
                                threshold: float = VISIBILITY_THRESHOLD,
                                on_frame: Callable[[int, torch.Tensor], None] | None = None
                                ) -> tuple[np.ndarray, np.ndarray]:
    """Masks (T,Q,H,W) bool and boxes (T,Q,4) of one camera; ``on_frame(t, coverage)`` sees each frame."""
    T = len(video)
    cam = video.camera
    masks = np.zeros((T, len(label_sets), cam.height, cam.width), dtype=bool)
    for t in range(T):
        cov = video[t]
        masks[t] = visible_masks(cov, label_sets, threshold)
        if on_frame is not None:
            on_frame(t, cov)
    return masks, boxes_of(masks)


def ensure_ground_truth(scene: Scene, cameras: Sequence[Camera] | None = None, *,
                        threshold: float = VISIBILITY_THRESHOLD, progress: bool = False,
                        videos: dict[str, CoverageVideo] | None = None) -> GroundTruth:
    """The ground truth of ``scene`` for ``cameras`` (default: the test cameras, else the train ones).

    Reads ``ground_truth/`` of the bundle when it matches; renders and stores what is missing (per
    camera, atomically). Scenes without a bundle directory are computed in memory only.
    """
    queries = scene_queries(scene)
    texts = list(queries)
    label_sets = [label_ids(scene, queries[q]) for q in texts]
    if cameras is None:
        cameras = default_eval_cameras(scene)
    key = _config_key(scene, queries, threshold)
    gt = GroundTruth(texts, queries, temporal_ground_truth(scene, queries), threshold=threshold)
    root = Path(scene.root) / GT_DIR if scene.root is not None else None
    meta: dict[str, Any] = {"format": "fourlegs-ground-truth", "version": GT_VERSION, "key": key,
                            "threshold": threshold, "queries": queries, "cameras": []}
    if root is not None and (root / "meta.json").is_file():
        try:
            old = read_json(root / "meta.json")
        except InputError:
            old = None
        if isinstance(old, dict) and old.get("key") == key:
            meta["cameras"] = [c for c in old.get("cameras", []) if isinstance(c, str)]
    computed = False
    iterator: Iterable[Camera] = cameras
    if progress:
        from tqdm import tqdm
        iterator = tqdm(cameras, desc="ground truth", unit="camera", leave=False)
    for cam in iterator:
        name = cam.name
        stem = _safe_name(name)
        if root is not None and name in meta["cameras"]:
            try:
                m = load_npy(root / f"{stem}.masks.npy", mmap=True, field="masks")
                b = load_npy(root / f"{stem}.boxes.npy", mmap=False, field="boxes")
                if m.shape == (scene.num_timesteps, len(texts), cam.height, cam.width):
                    gt.masks[name], gt.boxes[name] = m, b
                    continue
            except InputError:
                pass
        video = (videos or {}).get(name) or CoverageVideo(scene, cam)
        masks, boxes = compute_camera_ground_truth(video, label_sets, threshold)
        gt.masks[name], gt.boxes[name] = masks, boxes
        computed = True
        if root is not None:
            save_npy_atomic(root / f"{stem}.masks.npy", masks)
            save_npy_atomic(root / f"{stem}.boxes.npy", boxes)
            if name not in meta["cameras"]:
                meta["cameras"].append(name)
            write_json_atomic(root / "meta.json", meta)
    if root is not None and (computed or not (root / "temporal.json").is_file()):
        write_json_atomic(root / "temporal.json",
                          {"queries": {q: {"labels": queries[q], "segments": [list(s) for s in gt.segments(q)]}
                                       for q in texts}, "num_timesteps": scene.num_timesteps})
    return gt


def default_eval_cameras(scene: Scene) -> list[Camera]:
    """The benchmark's views: the held-out test cameras (the train cameras when there are none)."""
    cams = scene.cameras.cameras(0, "test")
    return cams if cams else scene.cameras.cameras(0, "train")
