"""Synthetic 4D grounding scenes with exact space-time ground truth.

A Panoptic-like capture, generated deterministically from a seed:

* a dome of cameras (OpenCV convention, aimed at the centre; world up is +z, metres),
* static background Gaussians: a court-like floor, the dome wall, a wooden box and a bench,
* three people made of Gaussians (ellipsoid body parts on an articulated skeleton) and a ball, playing a
  scripted scene: a throw-and-catch exchange (the ball flies twice), a person walking across, jumps
  (repeated, overlapping another person's jump), a wave, holding the ball.

Every Gaussian carries a ground-truth label per timestep (``GaussianSequence.labels`` (T,N) int32) that
indexes ``LABELS`` (stored as ``scene.json["metadata"]["labels"]``); people carry the label of the action
they perform at that timestep ("person jumping", ...), the ball "ball flying in the air" while in flight.
``queries.json`` beside ``scene.json`` maps each benchmark query text to the label names it refers to.

The script is defined on normalized time u = t / (T-1) in [0, 1], so every size plays the same scene
(about six seconds: ``fps = T / 6``). Sizes (train cameras + held-out test cameras; the benchmark is
evaluated on the test cameras):

======  ==========  ===========  =====  =========
size    Gaussians   cameras      T      image
======  ==========  ===========  =====  =========
tiny    ~2k         4 + 2        12     96x54
demo    ~30k        8 + 2        48     320x180
bench   ~100k       12 + 3       60     320x180
full    ~300k       27 + 4       150    640x360
======  ==========  ===========  =====  =========
"""
from __future__ import annotations

import hashlib
import math
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import InputError, OutputExistsError
from ..fileio import read_json, write_json_atomic
from ..scene.bundle import is_bundle, write_bundle
from ..scene.camera import Camera, CameraRig
from ..scene.gaussians import GaussianSequence
from ..scene.scene import Scene
from .parts import Part, box_surface, ellipsoid_surface, floor_part, matrix_to_quaternion, person_parts, \
    person_transforms, rot_x, rot_z, wall_part
from .script import BALL_RADIUS, LABEL_INDEX, LABELS, QUERIES, SCRIPT, Actor, ball_state

GENERATOR_VERSION = 4
QUERIES_FILE = "queries.json"
SCENE_SECONDS = 6.0


@dataclass(frozen=True)
class SizeSpec:
    """Scale of a generated scene."""

    num_gaussians: int
    num_train_cameras: int
    num_test_cameras: int
    num_timesteps: int
    width: int
    height: int


SIZES: dict[str, SizeSpec] = {
    "tiny": SizeSpec(2_000, 4, 2, 12, 96, 54),
    "demo": SizeSpec(30_000, 8, 2, 48, 320, 180),
    "bench": SizeSpec(100_000, 12, 3, 60, 320, 180),
    "full": SizeSpec(300_000, 27, 4, 150, 640, 360),
}

#: share of the Gaussian budget per scene element (the remainder goes to the floor)
_BUDGET = {"wall": 0.16, "box": 0.04, "bench": 0.04, "person": 0.17, "ball": 0.03}

DOME_RADIUS = 4.5
LOOK_TARGET = (0.0, 0.0, 1.0)
FOV_Y_DEG = 52.0
PERSON_SALIENCE = 6.0   # simulated video-model response per unit of crop coverage (background: 1)
BALL_SALIENCE = 20.0    # the ball is small, yet a video model notices it
BACKGROUND_LABELS = ("floor", "wall", "wooden box", "bench")

# ------------------------------------------------------------------------------------ cameras


def dome_cameras(spec: SizeSpec, rng: np.random.Generator) -> tuple[list[Camera], list[Camera]]:
    """Train and test cameras on a dome around the centre, all aimed at ``LOOK_TARGET``."""
    offset = rng.uniform(0, 2 * np.pi / max(spec.num_train_cameras, 1))
    heights = (1.3, 2.4, 3.2)
    train = []
    for i in range(spec.num_train_cameras):
        az = offset + 2 * np.pi * i / spec.num_train_cameras
        h = heights[i % len(heights)]
        r = math.sqrt(max(DOME_RADIUS ** 2 - (h - 1.0) ** 2 * 0.3, 1.0))
        eye = (r * math.cos(az), r * math.sin(az), h)
        train.append(Camera.look_at(eye, LOOK_TARGET, width=spec.width, height=spec.height,
                                    fov_y=math.radians(FOV_Y_DEG), name=f"cam{i:02d}"))
    test = []
    for j in range(spec.num_test_cameras):
        az = offset + 2 * np.pi * (j + 0.37) / spec.num_test_cameras + np.pi / max(spec.num_train_cameras, 1)
        eye = (DOME_RADIUS * math.cos(az), DOME_RADIUS * math.sin(az), 1.8)
        test.append(Camera.look_at(eye, LOOK_TARGET, width=spec.width, height=spec.height,
                                   fov_y=math.radians(FOV_Y_DEG), name=f"test{j:02d}"))
    return train, test


# ------------------------------------------------------------------------------------ builder


def _spec_for(size: str) -> SizeSpec:
    if size not in SIZES:
        raise InputError(f"unknown size {size!r} (choose from {', '.join(SIZES)})", field="size")
    return SIZES[size]


def generate_scene(size: str = "tiny", seed: int = 0,
                   progress: Callable[[int, int], None] | None = None) -> Scene:
    """Build the synthetic scene of ``size`` deterministically from ``seed`` (in memory).

    Returns a :class:`Scene` whose Gaussians carry ``labels`` (T,N) int32 and whose metadata holds
    ``labels`` (the vocabulary), ``queries`` ({text: [label names]}), ``script`` (the actions with
    their frame ranges), ``generator`` (version, size, seed).
    """
    spec = _spec_for(size)
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"seed must be a non-negative integer, got {seed!r}", field="seed")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), GENERATOR_VERSION, 0x4C454753]))
    layout, actors = _build_parts(rng, spec.num_gaussians)
    gaussians, ball_labels = _animate(layout, actors, spec.num_timesteps, progress)
    train, test = dome_cameras(spec, rng)
    T = spec.num_timesteps
    metadata = {
        "source": "synthetic",
        "generator": {"name": "fourlegs_engine.demo.synthetic", "version": GENERATOR_VERSION,
                      "size": size, "seed": int(seed)},
        "labels": list(LABELS),
        "queries": {text: list(labs) for text, labs in QUERIES},
        "script": [{"actor": a.actor, "label": a.label, "start": a.start, "end": a.end,
                    "frames": _frames_of(a.start, a.end, T)} for a in SCRIPT],
        "ball_labels": ball_labels,
        "background_labels": list(BACKGROUND_LABELS),
        # how strongly a (simulated) video model responds to a label per unit of crop coverage
        "salience": {name: (1.0 if name in BACKGROUND_LABELS else
                            BALL_SALIENCE if name.startswith("ball") else PERSON_SALIENCE) for name in LABELS},
    }
    return Scene(gaussians=gaussians, cameras=CameraRig.static(train, test, T), name=f"synthetic-{size}-seed{int(seed)}",
                 fps=T / SCENE_SECONDS, metadata=metadata)


@dataclass
class _Layout:
    """Every Gaussian of the scene in its part's frame: the static ones first (labelled), then the moving
    parts, each an index range owned by an actor ("A", "B", "C") or the ball."""

    local: np.ndarray                        # (N,3)
    local_rot: np.ndarray                    # (N,3,3)
    log_scales: np.ndarray                   # (N,3)
    colors: np.ndarray                       # (N,3)
    static_labels: np.ndarray                # (n_static,) int32
    moving: list[tuple[str, str, slice]]     # (actor or "ball", part name, index range)

    @property
    def num_static(self) -> int:
        return self.static_labels.shape[0]


def _build_parts(rng: np.random.Generator, num_gaussians: int) -> tuple[_Layout, dict[str, Actor]]:
    """The static background, three people and the ball, sized to the Gaussian budget."""
    counts = {k: int(v * num_gaussians) for k, v in _BUDGET.items()}
    static_parts: list[tuple[str, Part]] = [
        ("floor", floor_part(rng, num_gaussians - sum(counts.values()) - 2 * counts["person"])),
        ("wall", wall_part(rng, counts["wall"])),
        ("wooden box", box_surface(rng, counts["box"], (2.9 + rng.uniform(-0.2, 0.2), 2.4, 0.35),
                                   (0.7, 0.7, 0.7), (0.62, 0.42, 0.22))),
        ("bench", box_surface(rng, counts["bench"], (-2.7, -2.9 + rng.uniform(-0.2, 0.2), 0.25),
                              (1.6, 0.45, 0.5), (0.25, 0.3, 0.45))),
    ]
    # shirt colours differ per person; small seed-dependent placement offsets
    shirts = [(0.78, 0.16, 0.14), (0.16, 0.36, 0.78), (0.2, 0.62, 0.3)]
    order = rng.permutation(3)
    jit = rng.uniform(-0.15, 0.15, size=(3, 2))
    actors = {
        "A": Actor("A", np.array([-1.3, 0.15]) + jit[0], -math.pi / 2),
        "B": Actor("B", np.array([1.3, -0.15]) + jit[1], math.pi / 2),
        "C": Actor("C", np.array([-1.9, 1.7]) + jit[2], math.pi, path_end=np.array([0.3, 1.9]) + jit[2]),
    }
    per_person = 3 * counts["person"] // 3
    actor_parts = {name: person_parts(rng, per_person, shirts[order[i]]) for i, name in enumerate("ABC")}
    ball_n = num_gaussians - sum(p.local.shape[0] for _, p in static_parts) - \
        sum(p.local.shape[0] for parts in actor_parts.values() for _, p in parts)
    ball = ellipsoid_surface(rng, max(ball_n, 16), (BALL_RADIUS,) * 3, (0, 0, 0), (0.9, 0.42, 0.1), jitter=0.03)
    seam = (np.abs(ball.local[:, 2]) < 0.012) | (np.abs(ball.local[:, 0]) < 0.012)
    ball.colors[seam] = (0.12, 0.06, 0.03)

    blocks = [part for _, part in static_parts]
    moving: list[tuple[str, str, slice]] = []
    cursor = sum(part.local.shape[0] for part in blocks)
    for owner, part_name, part in [(name, pn, pt) for name, parts in actor_parts.items() for pn, pt in parts] + \
            [("ball", "ball", ball)]:
        blocks.append(part)
        moving.append((owner, part_name, slice(cursor, cursor + part.local.shape[0])))
        cursor += part.local.shape[0]
    static_labels = np.concatenate([np.full(part.local.shape[0], LABEL_INDEX[label]) for label, part in static_parts])
    layout = _Layout(np.concatenate([b.local for b in blocks]), np.concatenate([b.local_rot for b in blocks]),
                     np.concatenate([b.log_scales for b in blocks]).astype(np.float32),
                     np.concatenate([b.colors for b in blocks]).astype(np.float32),
                     static_labels.astype(np.int32), moving)
    return layout, actors


def _animate(layout: _Layout, actors: dict[str, Actor], T: int,
             progress: Callable[[int, int], None] | None) -> tuple[GaussianSequence, list[str]]:
    """Pose every moving part at each timestep: the Gaussians (with labels) and the ball's label per timestep."""
    N, n_static = layout.local.shape[0], layout.num_static
    means = np.empty((T, N, 3), np.float32)
    rotations = np.empty((T, N, 4), np.float32)
    labels = np.empty((T, N), np.int32)
    static_q = matrix_to_quaternion(layout.local_rot[:n_static]).astype(np.float32)
    ball_labels: list[str] = []
    for t in range(T):
        u = t / (T - 1) if T > 1 else 0.0
        means[t, :n_static] = layout.local[:n_static]
        rotations[t, :n_static] = static_q
        labels[t, :n_static] = layout.static_labels
        transforms = {name: person_transforms(actor.pose(u)) for name, actor in actors.items()}
        ball_centre, ball_label = ball_state(u, actors)
        ball_labels.append(ball_label)
        for owner, part_name, sl in layout.moving:
            if owner == "ball":
                spin = rot_x(6.0 * u * 2 * np.pi) @ rot_z(2.0 * u * 2 * np.pi)
                R, origin, lab = spin, ball_centre, LABEL_INDEX[ball_label]
            else:
                R, origin = transforms[owner][part_name]
                lab = LABEL_INDEX[actors[owner].label_at(u)]
            means[t, sl] = layout.local[sl] @ R.T + origin
            rotations[t, sl] = matrix_to_quaternion(R[None] @ layout.local_rot[sl]).astype(np.float32)
            labels[t, sl] = lab
        if progress is not None:
            progress(t + 1, T)
    opacity = np.full(N, 3.5, np.float32)  # sigmoid = 0.97
    opacity[:n_static] = 4.0
    foreground = np.zeros(N, bool)
    foreground[n_static:] = True
    return GaussianSequence(means=means, rotations=rotations, log_scales=layout.log_scales, opacity_logits=opacity,
                            colors=layout.colors, foreground=foreground, labels=labels), ball_labels


def _frames_of(start: float, end: float, T: int) -> list[int]:
    """Inclusive frame range [first, last] of normalized interval [start, end), or [] if no frame falls in it."""
    frames = [t for t in range(T) if start <= (t / (T - 1) if T > 1 else 0.0) < end]
    return [frames[0], frames[-1]] if frames else []


def queries_document(scene_or_metadata: Scene | dict) -> dict:
    """The ``queries.json`` document: ``{"format", "version", "queries": [{"text", "labels"}]}``."""
    meta = scene_or_metadata.metadata if isinstance(scene_or_metadata, Scene) else scene_or_metadata
    return {"format": "fourlegs-queries", "version": 1,
            "queries": [{"text": text, "labels": list(labs)} for text, labs in meta["queries"].items()]}


def read_queries(bundle: str | Path) -> dict[str, list[str]]:
    """Read ``queries.json`` of a bundle: {query text: [label names]}; validated against the labels."""
    path = Path(bundle) / QUERIES_FILE
    doc = read_json(path)
    if not isinstance(doc, dict) or doc.get("format") != "fourlegs-queries":
        raise InputError("not a fourlegs-queries document", file=path, field="format")
    out: dict[str, list[str]] = {}
    for i, q in enumerate(doc.get("queries", [])):
        if not isinstance(q, dict) or not isinstance(q.get("text"), str) or not isinstance(q.get("labels"), list):
            raise InputError("each entry needs 'text' (str) and 'labels' (list)", file=path, field=f"queries[{i}]")
        out[q["text"]] = [str(x) for x in q["labels"]]
    return out


def write_synthetic_bundle(path: str | Path, size: str = "tiny", seed: int = 0, *, overwrite: bool = False,
                           progress: Callable[[int, int], None] | None = None) -> Path:
    """Generate a scene and write it as a bundle (with ``queries.json``) at ``path``, atomically."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise OutputExistsError(path)
    scene = generate_scene(size, seed, progress=progress)
    path.parent.mkdir(parents=True, exist_ok=True)
    staging_root = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".gen", dir=path.parent))
    try:
        staged = write_bundle(scene, staging_root / "bundle")
        write_json_atomic(staged / QUERIES_FILE, queries_document(scene))
        if path.exists():  # overwrite requested
            trash = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".old", dir=path.parent))
            path.rename(trash / "old")
            staged.rename(path)
            shutil.rmtree(trash, ignore_errors=True)
        else:
            os.rename(staged, path)
    finally:
        shutil.rmtree(staging_root, ignore_errors=True)
    scene.root = path
    return path


def demo_bundle_path(size: str = "demo", seed: int = 0) -> Path:
    """Where :func:`ensure_demo_bundle` keeps the scene (keyed by generator version, size and seed)."""
    from ..paths import cache_dir
    _spec_for(size)
    return cache_dir() / "scenes" / f"synthetic-v{GENERATOR_VERSION}-{size}-seed{int(seed)}"


def ensure_demo_bundle(size: str = "demo", seed: int = 0) -> Path:
    """The synthetic scene bundle of ``size``/``seed`` in the cache directory, generated on first use.

    Generation is atomic (staged beside the final directory, then renamed), so concurrent callers and
    interrupted runs never see a half-written bundle; a later call reuses the finished one.
    """
    path = demo_bundle_path(size, seed)
    if is_bundle(path) and (path / QUERIES_FILE).is_file():
        return path
    try:
        write_synthetic_bundle(path, size, seed)
    except (OutputExistsError, OSError):
        if not (is_bundle(path) and (path / QUERIES_FILE).is_file()):
            raise
    return path


def bundle_digest(path: str | Path) -> str:
    """SHA-256 over the relative names and bytes of every file of a bundle (sorted); identical bundles match."""
    root = Path(path)
    h = hashlib.sha256()
    for f in sorted(p for p in root.rglob("*") if p.is_file()):
        rel = f.relative_to(root).as_posix()
        if rel.startswith("ground_truth/") or rel.startswith("features/") or rel.startswith("."):
            continue
        h.update(rel.encode())
        h.update(b"\0")
        with open(f, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
    return h.hexdigest()
