"""Simulated video-text encoders for synthetic scenes with ground-truth labels.

These stand in for ViCLIP where weights are unavailable: they are *simulations*, built from the
ground-truth labels of :mod:`fourlegs_engine.demo.synthetic` scenes, and named as such.

Text (:class:`SimulatedTextEncoder`)
    Lemma embeddings of the deterministic phrase space (:mod:`fourlegs_engine.language.phrase_space`).

Video (:class:`SimulatedVideoEncoder`)
    Input: clips (B, 8, C, h, w) of per-pixel label coverage in [0, 1] (channel c = the share of the
    pixel's colour contributed by Gaussians of label c, rendered with the rasterizer, see
    :func:`render_label_coverage`). Output: the coverage-weighted embedding of the labels in the crop
    over the tube (the uncovered share weighs the "background" phrase). Like a real video model, which
    notices a person filling a tenth of a crop, foreground labels (people, the ball: every label not
    in ``background_labels``) weigh ``foreground_salience`` (default 6) times their coverage, or the
    per-label ``salience`` the scene lists (synthetic scenes: the ball 20, being small);
    background labels (floor, wall, props) and the uncovered share weigh just their coverage. Three
    documented corruptions follow, all deterministic given ``seed`` (randomness is drawn from a
    counter-based hash of the seed, the camera and the clip's coverage, so the same input always gives
    the same output, as with a real model):

    * wrong-label frames: each of the 8 frames, with probability ``wrong_label_fraction`` (default
      0.1), has its label channels cyclically shifted (every label replaced by another one);
    * additive noise orthogonal to the clean embedding, sized so that the cosine to the clean
      embedding is ``noise_cosine`` (default 0.8);
    * a per-camera bias: a fixed unit vector per camera name, added with weight ``camera_bias``
      (default 0.25) before the final normalization (overall cosine to the clean embedding ~0.78).

    The defaults are fixed; tests must not depend on tuning them.
"""
from __future__ import annotations

import hashlib
import math
from functools import lru_cache
from typing import Any, Mapping, Sequence

import numpy as np
import torch

from ..errors import InputError
from ..language.phrase_space import BACKGROUND_PHRASE, EMBED_DIM, PhraseEncoder, lemma_embedding
from . import simulated_kernels

DEFAULT_NOISE_COSINE = 0.8
DEFAULT_CAMERA_BIAS = 0.25
DEFAULT_WRONG_LABEL_FRACTION = 0.1
DEFAULT_FOREGROUND_SALIENCE = 6.0


class SimulatedTextEncoder(PhraseEncoder):
    """Deterministic 768-d L2-normalized phrase embeddings from lemmas (see the module docstring)."""

    name = "simulated"
    phrase_embedding = staticmethod(lemma_embedding)


class SimulatedVideoEncoder:
    """Simulated video-text model over label-coverage clips (``input_kind = "labels"``).

    Args:
        labels: the label vocabulary; channel c of a clip is the coverage of ``labels[c]``.
        seed: seed of every corruption.
        noise_cosine: cosine between the noisy and the clean embedding (1 disables the noise).
        camera_bias: weight of the per-camera bias vector (0 disables it).
        wrong_label_fraction: probability that a frame's labels are replaced by other labels.
        camera: the camera whose bias applies (see :meth:`bind_camera`); None = a shared bias.
        background_labels: labels with salience 1 (default: none, i.e. every label is foreground).
        foreground_salience: weight multiplier of the other labels' coverage.
        salience: per-label multipliers that override both (e.g. a small ball weighs more than its
            area, as a video model notices it anyway).
    """

    name = "simulated"
    dim = EMBED_DIM
    input_kind = "labels"

    def __init__(self, labels: Sequence[str], *, seed: int = 0, noise_cosine: float = DEFAULT_NOISE_COSINE,
                 camera_bias: float = DEFAULT_CAMERA_BIAS,
                 wrong_label_fraction: float = DEFAULT_WRONG_LABEL_FRACTION, camera: str | None = None,
                 background_labels: Sequence[str] = (), foreground_salience: float = DEFAULT_FOREGROUND_SALIENCE,
                 salience: Mapping[str, float] | None = None):
        labels = [str(x) for x in labels]
        if not labels:
            raise InputError("the label vocabulary is empty", field="labels")
        if not 0.0 < noise_cosine <= 1.0:
            raise InputError(f"noise_cosine must be in (0, 1], got {noise_cosine}", field="noise_cosine")
        if not (camera_bias >= 0.0 and math.isfinite(camera_bias)):
            raise InputError(f"camera_bias must be >= 0, got {camera_bias}", field="camera_bias")
        if not 0.0 <= wrong_label_fraction <= 1.0:
            raise InputError(f"wrong_label_fraction must be in [0, 1], got {wrong_label_fraction}",
                             field="wrong_label_fraction")
        if not (foreground_salience > 0 and math.isfinite(foreground_salience)):
            raise InputError(f"foreground_salience must be > 0, got {foreground_salience}",
                             field="foreground_salience")
        self.labels = labels
        self.background_labels = [str(x) for x in background_labels if str(x) in labels]
        self.foreground_salience = float(foreground_salience)
        self.salience_overrides = {str(k): float(v) for k, v in (salience or {}).items() if str(k) in labels}
        if any(not (v > 0 and math.isfinite(v)) for v in self.salience_overrides.values()):
            raise InputError("salience values must be finite and > 0", field="salience")
        self._salience = torch.tensor([self.salience_overrides.get(
            name, 1.0 if name in self.background_labels else self.foreground_salience) for name in labels],
            dtype=torch.float64)
        self.seed = int(seed)
        self.noise_cosine = float(noise_cosine)
        self.camera_bias = float(camera_bias)
        self.wrong_label_fraction = float(wrong_label_fraction)
        self.camera = camera
        self.text = SimulatedTextEncoder()
        self._label_emb = torch.from_numpy(self.text.encode_text64(labels))              # (L, D) float64
        self._background = torch.from_numpy(lemma_embedding(BACKGROUND_PHRASE))       # (D,)

    @property
    def num_labels(self) -> int:
        return len(self.labels)

    def config(self) -> dict[str, Any]:
        """JSON-serializable settings (for config hashes of cached features)."""
        return {"encoder": self.name, "labels": list(self.labels), "seed": self.seed,
                "noise_cosine": self.noise_cosine, "camera_bias": self.camera_bias,
                "wrong_label_fraction": self.wrong_label_fraction,
                "background_labels": list(self.background_labels), "foreground_salience": self.foreground_salience,
                "salience": dict(self.salience_overrides)}

    def bind_camera(self, camera: str | None) -> "SimulatedVideoEncoder":
        """The same encoder with ``camera``'s bias (tables are shared, nothing is recomputed)."""
        other = object.__new__(SimulatedVideoEncoder)
        other.__dict__.update(self.__dict__)
        other.camera = camera
        return other

    def clean(self) -> "SimulatedVideoEncoder":
        """The same encoder without corruptions (the oracle the tests compare against)."""
        return SimulatedVideoEncoder(self.labels, seed=self.seed, noise_cosine=1.0, camera_bias=0.0,
                                     wrong_label_fraction=0.0, camera=self.camera,
                                     background_labels=self.background_labels,
                                     foreground_salience=self.foreground_salience,
                                     salience=self.salience_overrides)

    def encode_text(self, texts: Sequence[str]) -> torch.Tensor:
        return self.text.encode_text(texts)

    # ------------------------------------------------------------------ video
    def encode_video(self, clips: torch.Tensor, camera: str | None = None) -> torch.Tensor:
        """clips (B, 8, C, h, w) label coverage in [0,1] -> (B, 768) float32 L2-normalized.

        ``camera`` overrides the bound camera for this call.
        """
        clips = torch.as_tensor(clips)
        if clips.dim() != 5 or clips.shape[2] != self.num_labels:
            raise InputError(f"clips must be (B, frames, {self.num_labels}, h, w) label coverage, got "
                             f"{tuple(clips.shape)}", field="clips")
        coverage = torch.nan_to_num(clips.detach().to("cpu", torch.float64), nan=0.0).clamp_(0.0, 1.0)
        return self.encode_coverage(coverage.mean(dim=(3, 4)), camera=camera)

    def encode_coverage(self, frame_coverage: torch.Tensor, camera: str | None = None) -> torch.Tensor:
        """Per-frame mean label coverage (B, F, C) in [0,1] -> (B, 768) float32 L2-normalized.

        The same result as :meth:`encode_video` on clips whose per-frame channel means are these.
        """
        cov = torch.nan_to_num(torch.as_tensor(frame_coverage, dtype=torch.float64), nan=0.0).clamp(0.0, 1.0)
        if cov.dim() != 3 or cov.shape[2] != self.num_labels:
            raise InputError(f"frame coverage must be (B, frames, {self.num_labels}), got {tuple(cov.shape)}",
                             field="frame_coverage")
        B, Fr, C = cov.shape
        if B == 0:
            return torch.zeros(0, EMBED_DIM)
        cam = self.camera if camera is None else camera
        keys = self._clip_keys(cov, cam)                                    # (B,) uint64
        if self.wrong_label_fraction > 0 and C > 1:
            wrong = _uniform(keys, np.arange(Fr) + 1_000) < self.wrong_label_fraction       # (B, F)
            shift = np.where(wrong, 1 + np.floor(_uniform(keys, np.arange(Fr) + 2_000) * (C - 1)), 0)
            src = (np.arange(C)[None, None, :] - shift[:, :, None].astype(np.int64)) % C    # roll by shift
            cov = torch.gather(cov, 2, torch.from_numpy(src))
        coverage = cov.mean(dim=1)                                         # (B, C)
        background = (1.0 - coverage.sum(dim=1)).clamp_min(0.0)          # (B,) uncovered share
        weights = coverage * self._salience[None]
        clean = weights @ self._label_emb + background[:, None] * self._background[None]
        clean = clean / clean.norm(dim=1, keepdim=True).clamp_min(1e-12)
        out = clean
        if self.noise_cosine < 1.0:
            noise = torch.from_numpy(_normal(keys, EMBED_DIM))
            noise = noise - (noise * clean).sum(1, keepdim=True) * clean   # orthogonal to the clean one
            noise = noise / noise.norm(dim=1, keepdim=True).clamp_min(1e-12)
            c = self.noise_cosine
            out = c * clean + math.sqrt(max(0.0, 1 - c * c)) * noise
        if self.camera_bias > 0:
            out = out + self.camera_bias * torch.from_numpy(_camera_bias_vector(self.seed, cam))[None]
        out = out / out.norm(dim=1, keepdim=True).clamp_min(1e-12)
        return out.float()

    def _clip_keys(self, cov: torch.Tensor, camera: str | None) -> np.ndarray:
        """(B,) uint64 per-clip keys from (seed, camera, the clip's quantized per-frame coverage)."""
        q = np.round(cov.numpy().reshape(cov.shape[0], -1) * 4096).astype(np.uint64)     # (B, F*C)
        head = hashlib.blake2b(f"{self.seed}|{camera}".encode(), digest_size=8).digest()
        if simulated_kernels.available():
            return simulated_kernels.fold_keys(int.from_bytes(head, "little"), q)
        keys = np.full(q.shape[0], int.from_bytes(head, "little"), dtype=np.uint64)
        for col in q.T:                                                   # fold every value in
            keys = _splitmix64(keys ^ col)
        return keys


def _splitmix64(x: np.ndarray) -> np.ndarray:
    """SplitMix64 finalizer, vectorized over uint64 arrays (wrap-around arithmetic)."""
    with np.errstate(over="ignore"):
        z = x + np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        return z ^ (z >> np.uint64(31))


def _uniform(keys: np.ndarray, counters: np.ndarray) -> np.ndarray:
    """(B,) keys x (K,) counters -> (B, K) float64 uniform in (0, 1), counter-based (order independent)."""
    with np.errstate(over="ignore"):
        x = keys[:, None] * np.uint64(0xD1B54A32D192ED03) + np.asarray(counters, dtype=np.uint64)[None, :]
    bits = _splitmix64(_splitmix64(x)) >> np.uint64(11)
    return (bits.astype(np.float64) + 0.5) / float(1 << 53)


def _normal(keys: np.ndarray, dim: int) -> np.ndarray:
    """(B,) keys -> (B, dim) standard normal samples (Box-Muller on counter-based uniforms)."""
    half = (dim + 1) // 2
    if simulated_kernels.available():
        u1 = simulated_kernels.uniforms(keys, 0, half)
        u2 = simulated_kernels.uniforms(keys, half, half)
    else:
        u1 = _uniform(keys, np.arange(half))
        u2 = _uniform(keys, np.arange(half) + half)
    r = np.sqrt(-2.0 * np.log(u1))
    z = np.concatenate([r * np.cos(2 * np.pi * u2), r * np.sin(2 * np.pi * u2)], axis=1)
    return z[:, :dim]


@lru_cache(maxsize=256)
def _camera_bias_vector(seed: int, camera: str | None) -> np.ndarray:
    d = hashlib.sha256(f"fourlegs-camera-bias|{seed}|{camera}".encode()).digest()
    v = np.random.default_rng(int.from_bytes(d[:8], "little")).normal(size=EMBED_DIM)
    return v / np.linalg.norm(v)


def _check_scene_labels(scene: Any, labels: Any) -> None:
    """InputError when the vocabulary is not a list of text or a Gaussian's label is not one of its indices."""
    root = getattr(scene, "root", None)
    meta_file = f"{root}/scene.json" if root is not None else None
    if not isinstance(labels, (list, tuple)) or not all(isinstance(x, str) for x in labels):
        raise InputError("must be a list of text labels", file=meta_file, field="metadata.labels")
    values = getattr(getattr(scene, "gaussians", None), "labels", None)
    if values is None or not np.asarray(values).size:
        return
    low, high = int(np.min(values)), int(np.max(values))
    if low < -1 or high >= len(labels):
        raise InputError(f"holds label {high if high >= len(labels) else low}, the vocabulary has {len(labels)} "
                         f"labels (0..{len(labels) - 1}, -1 for none)",
                         file=f"{root}/labels.npy" if root is not None else None, field="labels")


def create_encoder(*, labels: Sequence[str] | None = None, scene: Any = None, seed: int = 0,
                   **options: Any) -> SimulatedVideoEncoder:
    """Factory used by ``language.encoders.get_encoder("simulated", ...)``.

    The vocabulary comes from ``labels`` or from ``scene.metadata["labels"]`` (synthetic scenes), the
    background labels from ``scene.metadata["background_labels"]`` unless given.
    """
    meta = (getattr(scene, "metadata", None) or {}) if scene is not None else {}
    if labels is None:
        labels = meta.get("labels")
    if "background_labels" not in options and meta.get("background_labels"):
        options["background_labels"] = meta["background_labels"]
    if "salience" not in options and isinstance(meta.get("salience"), dict):
        options["salience"] = meta["salience"]
    if labels is None:
        raise InputError("the simulated encoder needs the scene's label vocabulary (a synthetic scene with "
                         "metadata['labels'])", field="encoder")
    if scene is not None:
        _check_scene_labels(scene, labels)
    allowed = {"noise_cosine", "camera_bias", "wrong_label_fraction", "camera", "background_labels",
               "foreground_salience", "salience"}
    unknown = set(options) - allowed - {"device", "dtype", "batch_size"}
    if unknown:
        raise InputError(f"unknown option(s) for the simulated encoder: {', '.join(sorted(unknown))}",
                         field="encoder")
    return SimulatedVideoEncoder(labels, seed=seed, **{k: v for k, v in options.items() if k in allowed})
