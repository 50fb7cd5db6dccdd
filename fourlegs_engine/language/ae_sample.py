"""The autoencoder's training sample: per-pixel features drawn from the extracted crop features of the
training views (uniformly, or balanced across clusters of feature directions so a small object's label
is learnt), the held-out camera's sample, and the checks that run before anything is read or replaced.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import torch

if TYPE_CHECKING:
    from .autoencoder import AETrainOptions


def _sample_pixel_features(scene: Any, store: Any, views: list[tuple[int, int]], total: int,
                           rng: np.random.Generator) -> torch.Tensor:
    """(≈total, D) float32 per-pixel features at uniformly random pixels of the given (t, camera) views."""
    from .extract import load_step_features, view_has_evidence
    from .pyramid import interpolate_points
    if not views or total <= 0:
        return torch.zeros((0, int(store.config["dim"])))
    by_t: dict[int, list[int]] = {}
    for t, c in views:
        by_t.setdefault(t, []).append(c)
    loaded = {t: load_step_features(scene, store, t) for t in sorted(by_t)}
    # views without evidence (zero rows: annotation masks that do not cover them) are not sampled
    by_t = {t: [c for c in cams if view_has_evidence(loaded[t][0], loaded[t][2][c])] for t, cams in by_t.items()}
    count = sum(len(cams) for cams in by_t.values())
    if count == 0:
        return torch.zeros((0, int(store.config["dim"])))
    per_view = max(1, -(-total // count))
    out = []
    for t in sorted(by_t):
        feats, layouts, offsets = loaded[t]
        for c in by_t[t]:
            lay = layouts[c]
            crop = torch.from_numpy(np.asarray(feats[offsets[c]:offsets[c] + lay.num_crops], dtype=np.float32))
            xs = torch.from_numpy(rng.integers(0, lay.width, per_view).astype(np.float64))
            ys = torch.from_numpy(rng.integers(0, lay.height, per_view).astype(np.float64))
            out.append(interpolate_points(lay, crop, xs, ys))
    return torch.cat(out)[:total] if len(out) else torch.zeros((0, int(store.config["dim"])))


def check_features_complete(store: Any, steps: list[int]) -> None:
    """InputError naming the missing timesteps, or the first damaged feature file (NaN, truncated, ...)."""
    from ..errors import InputError
    from .store import format_ranges
    missing = [t for t in steps if not store.step_path(t).is_file()]
    if missing:
        raise InputError(f"features of timesteps {format_ranges(missing)} are missing; finish "
                         "`fourlegs extract` first", file=store.root)
    for t in steps:
        problem = store.problem(t)
        if problem is not None:
            raise InputError(f"{problem}; run `fourlegs extract` to compute it again", file=store.step_path(t),
                             field="features")


def check_holdout_camera(config: "AETrainOptions", num_cameras: int) -> None:
    from ..errors import InputError
    if not -max(num_cameras, 1) <= config.holdout_camera < max(num_cameras, 1):
        raise InputError(f"camera {config.holdout_camera} does not exist (the scene has {num_cameras} training "
                         f"cameras: 0..{num_cameras - 1}, or -1 for the last)", field="--holdout-camera")


def training_data(scene: Any, store: Any, config: "AETrainOptions", steps: list[int], balance: str = "none"
                   ) -> tuple[torch.Tensor, torch.Tensor, int | None]:
    """(samples, D) training features of every view but the held-out camera's, (heldout_samples, D) of the
    held-out camera, and its index (None with a single camera)."""
    num_cams = scene.cameras.num_cameras(store.config.get("split", "train"))
    holdout = config.holdout_camera % num_cams if num_cams > 1 else None
    if holdout is not None and config.holdout_camera == -1:
        holdout = _last_camera_with_evidence(scene, store, steps, num_cams)
    rng = np.random.default_rng(np.random.SeedSequence([config.seed, 0xAE]))
    train_views = [(t, c) for t in steps for c in range(num_cams) if c != holdout]
    held_views = [(t, holdout) for t in steps] if holdout is not None else []
    if balance == "directions":
        pool = _sample_pixel_features(scene, store, train_views, BALANCE_POOL * config.samples, rng)
        x_train = balance_directions(pool, config.samples, BALANCE_CLUSTERS, rng)
    else:
        x_train = _sample_pixel_features(scene, store, train_views, config.samples, rng)
    x_held = _sample_pixel_features(scene, store, held_views, config.heldout_samples, rng)
    return x_train, x_held, holdout


BALANCE_POOL = 2  # balanced training: candidates drawn per training sample
BALANCE_CLUSTERS = 32  # balanced training: k-means clusters of feature directions sharing the sample


def balance_directions(pool: torch.Tensor, total: int, clusters: int, rng: np.random.Generator) -> torch.Tensor:
    """(total, D) rows of ``pool`` (M, D) with an equal share from each of ``clusters`` k-means clusters of
    their directions (scipy's k-means++); a cluster smaller than its share is drawn with replacement.
    Rows in random order."""
    from scipy.cluster.vq import kmeans2

    n = pool.shape[0]
    if n == 0 or total <= 0:
        return pool[:0]
    unit = torch.nn.functional.normalize(pool.double(), dim=1).numpy()
    k = max(1, min(int(clusters), n))
    _, labels = kmeans2(unit, k, iter=10, minit="++", seed=rng)
    groups = [np.flatnonzero(labels == c) for c in np.unique(labels)]
    shares = np.full(len(groups), total // len(groups))
    shares[:total % len(groups)] += 1
    rows = np.concatenate([rng.choice(g, size=int(m), replace=g.size < m) for g, m in zip(groups, shares)])
    return pool[torch.from_numpy(rng.permutation(rows))]


HOLDOUT_PROBES = 8  # timesteps looked at to find a camera with evidence to hold out


def _last_camera_with_evidence(scene: Any, store: Any, steps: list[int], num_cams: int) -> int:
    """The default held-out camera: the last one, or when it has no evidence (annotation masks of other
    cameras only) the last camera with evidence at a few spread timesteps, provided another camera has
    some to train on; else the last one."""
    from .extract import load_step_features, view_has_evidence

    probes = steps[::max(1, -(-len(steps) // HOLDOUT_PROBES))] if steps else []
    loaded = [load_step_features(scene, store, t) for t in probes]
    with_evidence = [c for c in range(num_cams)
                     if any(view_has_evidence(feats, offsets[c]) for feats, _, offsets in loaded)]
    return with_evidence[-1] if len(with_evidence) >= 2 else num_cams - 1
