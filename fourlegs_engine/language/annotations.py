"""Annotation masks as the teacher: a language field from per-pixel masks instead of a video-text network.

This is not a language model. An editor (or a segmentation tool) supplies, for each phrase, a folder of
per-pixel masks, one PNG per camera and timestep: ``{folder}/{camera name}/{t:06d}.png`` (the layout of
the Panoptic capture's ``seg/`` folder); any nonzero pixel is "set". The encoder turns them into the same
crop-pyramid features a video-text encoder would produce, so the masks go through the same
extract -> autoencoder -> distil/lift -> query path and come out as a 4D field that renders from any
viewpoint and timestep.

Embeddings (768-d, L2-normalized, deterministic)
    A configured or queried phrase (lower case, whitespace collapsed) gets
    ``sqrt(g) * generic + sqrt(1 - g) * h(phrase)`` with ``g`` = 0.3 and ``h`` a unit vector drawn from a
    hash of the phrase text (nearly orthogonal to every other phrase); the canonical phrases ("object",
    "things", ...) and the uncovered share ("background") use the simulated encoder's embeddings, which
    are mostly the shared ``generic`` axis. Hence a pixel whose feature is a phrase's embedding has
    relevancy > 0.5 for that phrase and < 0.5 for any other; an unmasked pixel has relevancy < 0.5 for
    every phrase.

Features
    A crop tube's feature mixes the embeddings of what it holds with weights ``w_k = s m_k`` and
    ``w_background = 1 - Σ_k m_k``, with ``m_k`` the share of the crop's pixels set in phrase k's masks
    averaged over the tube's 8 frames and ``s`` the ``salience`` of a masked pixel against an unmasked one
    (default 6, the simulated encoder's foreground salience: a person filling a fifth of the smallest crop
    still dominates its feature, as it would for a video model). Every embedding is a share ``g_k`` of the
    common generic axis plus a phrase-specific part ``p_k``; the mix keeps the two apart
    (:func:`mix_embeddings`): the generic share is the weights' mean of the ``g_k``, the specific part
    points along ``Σ_k w_k p_k`` with the weights' mean of the ``|p_k|`` as its length. A crop inside one
    phrase's mask gets exactly that phrase's embedding, and a crop inside the masks of several
    overlapping phrases ("the ball" inside "a person holding the ball" inside "a person") has relevancy
    above 0.5 for each of them (up to five at once) and below 0.5 for every other phrase. A plain weighted
    sum of the embeddings would not: their generic shares add up coherently while the specific parts do
    not, so a pixel in three masks came out closer to the canonical phrases than to any of its own.

Views without masks
    Real annotations cover a few views only. A missing mask file means "not annotated", never "absent":
    a frame of a camera is *annotated* when every phrase has its mask file there (an empty mask says "not
    in this view"). A crop tube averages its coverage over its annotated frames only; a camera-timestep
    whose 8-frame tube holds no annotated frame contributes no evidence: its feature rows are all zero
    (an encoder's features are unit vectors, so zero rows are unambiguous), and the autoencoder and the
    lift skip that view. Only annotated views vote; Gaussians no voting view sees keep a zero latent, as
    Gaussians no training camera sees. A phrase with no mask file for any training camera and timestep,
    or a set of phrases that no frame holds all of, is an error.
"""
from __future__ import annotations

import hashlib
import math
import os
from functools import lru_cache
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np
import torch

from ..errors import InputError
from .phrase_space import (BACKGROUND_PHRASE, EMBED_DIM, GENERIC_AXIS, GENERIC_SHARE, PhraseEncoder,
                           lemma_embedding, phrase_basis)
from .phrases import CANONICAL_PHRASES

ENCODER_NAME = "masks"
DEFAULT_SALIENCE = 6.0
#: how a crop's feature mixes the embeddings of what it holds (recorded with the features: features made
#: by an earlier rule are stale)
MIX_RULE = "generic-apart"
MASK_PATTERN = "{camera}/{t:06d}.png"


def normalize_phrase(text: str) -> str:
    """Lower case, whitespace collapsed: the key a phrase's embedding is drawn from."""
    if not isinstance(text, str):
        raise InputError(f"a phrase must be a string, got {type(text).__name__}", field="text")
    return " ".join(text.lower().split())


@lru_cache(maxsize=4096)
def phrase_embedding(text: str) -> np.ndarray:
    """(768,) float64 unit embedding of a phrase (see the module docstring)."""
    key = normalize_phrase(text)
    if key in CANONICAL_PHRASES or key == BACKGROUND_PHRASE:
        return lemma_embedding(key)
    digest = hashlib.sha256(("fourlegs-annotations:" + key).encode()).digest()
    h = np.random.default_rng(int.from_bytes(digest[:8], "little")).normal(size=EMBED_DIM)
    e = math.sqrt(GENERIC_SHARE) * phrase_basis()[GENERIC_AXIS] + math.sqrt(1 - GENERIC_SHARE) * h / np.linalg.norm(h)
    return e / np.linalg.norm(e)


def mix_embeddings(weights: torch.Tensor, embeddings: torch.Tensor, generic: torch.Tensor) -> torch.Tensor:
    """Unit features mixing unit embeddings, their generic and specific parts kept apart.

    Args:
        weights: (B, K) non-negative weights (a row of zeros gives the plain mean).
        embeddings: (K, D) unit embeddings e_k = g_k a + p_k, with ``a`` the generic axis and p_k ⟂ a.
        generic: (D,) the unit generic axis ``a``.
    Returns:
        (B, D) unit rows ``normalize(ḡ a + |p̄| p / |p|)`` with ``ḡ`` and ``|p̄|`` the weighted means of
        the g_k and |p_k| and ``p = Σ_k w_k p_k``; a row whose ``p`` vanishes keeps ``ḡ a``. One
        embedding with all the weight comes back unchanged. The dtype is that of ``embeddings``.
    """
    dtype = embeddings.dtype
    w = torch.nan_to_num(weights.to(dtype), nan=0.0).clamp_min(0.0)
    total = w.sum(dim=1, keepdim=True)
    w = torch.where(total > 0, w / total.clamp_min(1e-300), torch.full_like(w, 1.0 / max(w.shape[1], 1)))
    g = embeddings @ generic.to(dtype)                                      # (K,)
    specific = embeddings - g[:, None] * generic.to(dtype)[None]            # (K, D)
    length = specific.norm(dim=1)                                           # (K,)
    direction = w @ specific                                                # (B, D)
    norm = direction.norm(dim=1, keepdim=True)
    unit = torch.where(norm > 1e-12, direction / norm.clamp_min(1e-12), torch.zeros_like(direction))
    out = (w @ g)[:, None] * generic.to(dtype)[None] + (w @ length)[:, None] * unit
    return out / out.norm(dim=1, keepdim=True).clamp_min(1e-12)


def parse_mask_spec(spec: str) -> tuple[str, str]:
    """``"a person=path/to/seg"`` -> ("a person", "path/to/seg"); InputError naming ``--masks`` otherwise."""
    if not isinstance(spec, str) or "=" not in spec:
        raise InputError(f"expected PHRASE=FOLDER, got {spec!r}", field="--masks")
    phrase, folder = spec.split("=", 1)
    phrase, folder = normalize_phrase(phrase), folder.strip()
    if not phrase or not folder:
        raise InputError(f"expected PHRASE=FOLDER with both parts non-empty, got {spec!r}", field="--masks")
    return phrase, folder


def mask_pairs(masks: Mapping[str, Any] | Iterable[Any] | None) -> list[tuple[str, str]]:
    """Phrase -> folder pairs from a mapping, ``(phrase, folder)`` pairs or ``"PHRASE=FOLDER"`` strings."""
    if masks is None:
        return []
    items = masks.items() if isinstance(masks, Mapping) else masks
    pairs: list[tuple[str, str]] = []
    for item in items:
        if isinstance(item, str):
            phrase, folder = parse_mask_spec(item)
        else:
            try:
                phrase, folder = item
            except (TypeError, ValueError):
                raise InputError(f"expected (phrase, folder), got {item!r}", field="--masks") from None
            phrase, folder = parse_mask_spec(f"{phrase}={folder}")
        if any(phrase == p for p, _ in pairs):
            raise InputError(f"the phrase {phrase!r} is given twice", field="--masks")
        pairs.append((phrase, str(folder)))
    return pairs


def read_mask(path: Path) -> np.ndarray:
    """(H, W) bool mask of one PNG: any nonzero channel of a pixel sets it."""
    from PIL import Image, UnidentifiedImageError
    try:
        with Image.open(path) as img:
            arr = np.asarray(img)
    except Image.DecompressionBombError as exc:
        raise InputError(f"is too large to be a mask ({exc})"[:300], file=path, field="masks") from None
    except (OSError, UnidentifiedImageError) as exc:
        raise InputError(f"not a readable mask image ({exc})", file=path, field="masks") from None
    return arr != 0 if arr.ndim == 2 else np.any(arr != 0, axis=2)


class AnnotationMaskEncoder(PhraseEncoder):
    """Per-pixel annotation masks as crop features (``input_kind = "labels"``: the clips hold coverage).

    Args:
        masks: phrase -> mask folder (a mapping, pairs or ``"PHRASE=FOLDER"`` strings); may be empty for a
            query-only encoder (text embeddings need no masks).
        base_dir: folders given relative are resolved against it (default: the working directory).
        salience: weight of a masked pixel's coverage against an unmasked one's (see the module docstring).

    Channel k of a frame is phrase k's mask; :meth:`coverage_frame` reads it from the folder instead of
    rendering the scene, and :meth:`encode_coverage` maps per-frame crop coverage to features.
    """

    name = ENCODER_NAME
    input_kind = "labels"
    phrase_embedding = staticmethod(phrase_embedding)

    def __init__(self, masks: Mapping[str, Any] | Iterable[Any] | None = None, *,
                 base_dir: str | Path | None = None, salience: float = DEFAULT_SALIENCE):
        if not (math.isfinite(salience) and salience > 0):
            raise InputError(f"salience must be finite and > 0, got {salience}", field="salience")
        self.salience = float(salience)
        base = Path(base_dir) if base_dir is not None else Path.cwd()
        pairs = mask_pairs(masks)
        self.labels = [p for p, _ in pairs]
        self.folders = [Path(f) if Path(f).is_absolute() else (base / f) for _, f in pairs]
        self.folders = [f.resolve() for f in self.folders]
        self._label_emb = torch.from_numpy(np.stack([phrase_embedding(p) for p in self.labels])) if pairs \
            else torch.zeros(0, EMBED_DIM, dtype=torch.float64)                    # (C, D) float64
        self._background = torch.from_numpy(phrase_embedding("background"))       # (D,)
        self._generic = torch.from_numpy(phrase_basis()[GENERIC_AXIS])              # (D,) unit
        self._checked = False
        self._available: list[dict[str, frozenset[int]]] | None = None    # per phrase: camera -> timesteps
        self._scanned_cameras: list[str] = []
        self._scanned_timesteps = 0

    @property
    def num_labels(self) -> int:
        return len(self.labels)

    def config(self) -> dict[str, Any]:
        """JSON-serializable settings (recorded with the features and in scene.json's language block)."""
        config = {"encoder": self.name, "masks": {p: str(f) for p, f in zip(self.labels, self.folders)},
                  "mask_pattern": MASK_PATTERN, "salience": self.salience, "mix": MIX_RULE}
        if self._available is not None:  # features made before masks were added or removed are stale
            config["mask_files"] = self.mask_files_digest()
        return config

    def mask_files_digest(self) -> str:
        """Short hash of which mask files exist (after :meth:`check_masks`), per phrase, camera and timestep."""
        listing = [[p, c, sorted(avail[c])] for p, avail in zip(self.labels, self._available or [])
                   for c in self._scanned_cameras]
        return hashlib.sha256(repr(listing).encode()).hexdigest()[:16]

    # ----------------------------------------------------------------------------- text
    # ----------------------------------------------------------------------------- masks
    def mask_path(self, phrase_index: int, camera: str, t: int) -> Path:
        return self.folders[phrase_index] / MASK_PATTERN.format(camera=camera, t=int(t))

    def _scan(self, cameras: Sequence[Any], num_timesteps: int) -> None:
        """Which mask files exist: per phrase, camera name -> set of timesteps (one directory listing per
        phrase and camera)."""
        self._available = []
        for folder in self.folders:
            per_camera: dict[str, frozenset[int]] = {}
            for cam in cameras:
                found: set[int] = set()
                try:
                    names = os.listdir(folder / str(cam.name))
                except (FileNotFoundError, NotADirectoryError):
                    names = []
                for name in names:
                    stem, dot, ext = name.partition(".")
                    if ext == "png" and len(stem) == 6 and stem.isdigit() and int(stem) < num_timesteps:
                        found.add(int(stem))
                per_camera[str(cam.name)] = frozenset(found)
            self._available.append(per_camera)
        self._scanned_cameras = [str(c.name) for c in cameras]
        self._scanned_timesteps = int(num_timesteps)

    def annotated(self, camera: str, t: int) -> bool:
        """Whether every phrase has its mask file for ``camera`` at timestep ``t``."""
        available = self._available
        if available and str(camera) in available[0] and 0 <= int(t) < self._scanned_timesteps:
            return all(int(t) in per_camera[str(camera)] for per_camera in available)
        return all(self.mask_path(k, camera, t).is_file() for k in range(self.num_labels))

    def evidence_summary(self) -> dict[str, Any]:
        """What the scanned masks cover (after :meth:`check_masks`): per phrase the camera-timesteps with its
        mask, the annotated camera-timesteps (every phrase's mask present: the views that vote) and the
        camera-timesteps in all."""
        if self._available is None:
            raise RuntimeError("check_masks() first")
        cams, T = self._scanned_cameras, self._scanned_timesteps
        per_phrase = {p: sum(len(avail[c]) for c in cams) for p, avail in zip(self.labels, self._available)}
        annotated = sum(len(frozenset.intersection(*(avail[c] for avail in self._available))) for c in cams)
        return {"per_phrase": per_phrase, "annotated": annotated, "camera_timesteps": len(cams) * T,
                "cameras": len(cams), "timesteps": T}

    def evidence_line(self) -> str:
        """One line of :meth:`evidence_summary` for the command line."""
        summary = self.evidence_summary()
        total = summary["camera_timesteps"]
        phrases = ", ".join(f"{p!r} {n}/{total}" for p, n in summary["per_phrase"].items())
        return (f"annotation masks ({summary['cameras']} training cameras x {summary['timesteps']} timesteps): "
                f"camera-timesteps with a mask: {phrases}; {summary['annotated']}/{total} annotated for every "
                "phrase (only these vote)")

    def check_masks(self, cameras: Sequence[Any], num_timesteps: int) -> None:
        """Fail early with one line: no phrase, a missing folder, a phrase without any mask file, no frame
        annotated for every phrase, a mask of the wrong size, or all masks of a phrase empty. Missing files
        are allowed otherwise (see "Views without masks" in the module docstring). Reads masks only until
        it finds one set pixel per phrase (cheap on real masks)."""
        if not self.labels:
            raise InputError("the annotation-mask encoder needs at least one PHRASE=FOLDER", field="--masks")
        for phrase, folder in zip(self.labels, self.folders):
            if not folder.is_dir():
                raise InputError(f"mask folder of {phrase!r} does not exist", file=folder, field="--masks")
        self._scan(cameras, num_timesteps)
        summary = self.evidence_summary()
        for k, (phrase, folder) in enumerate(zip(self.labels, self.folders)):
            if summary["per_phrase"][phrase] == 0:
                raise InputError(f"no mask of {phrase!r} for any of the {len(cameras)} training cameras at timesteps "
                                 f"0..{num_timesteps - 1} (expected {MASK_PATTERN} inside the folder)",
                                 file=folder, field="--masks")
            found = False
            by_camera = {str(c.name): c for c in cameras}
            for name, steps in self._available[k].items():
                for t in sorted(steps):
                    path = self.mask_path(k, name, t)
                    mask = read_mask(path)
                    self._check_size(mask, by_camera[name], path)
                    if mask.any():
                        found = True
                        break
                if found:
                    break
            if not found:
                raise InputError(f"every mask of {phrase!r} is empty (no pixel set)", file=folder, field="--masks")
        if summary["annotated"] == 0:
            counts = ", ".join(f"{p!r}: {n}" for p, n in summary["per_phrase"].items())
            raise InputError(f"no camera-timestep has the masks of every phrase ({counts} camera-timesteps); a "
                             "view votes only where all phrases are annotated: add empty masks where a phrase "
                             "is absent", field="--masks")
        self._checked = True

    def _check_size(self, mask: np.ndarray, camera: Any, path: Path) -> None:
        if mask.shape != (camera.height, camera.width):
            raise InputError(f"mask is {mask.shape[1]}x{mask.shape[0]}, camera {camera.name!r} images are "
                             f"{camera.width}x{camera.height}", file=path, field="--masks")

    def coverage_frame(self, t: int, camera: Any) -> torch.Tensor | None:
        """(C, H, W) float32 in {0, 1}: channel k = phrase k's mask of ``camera`` at timestep ``t``; None
        where the frame is not annotated (some phrase has no mask file there)."""
        if not self.annotated(camera.name, t):
            return None
        planes = []
        for k in range(self.num_labels):
            path = self.mask_path(k, camera.name, t)
            mask = read_mask(path)
            self._check_size(mask, camera, path)
            planes.append(torch.from_numpy(mask.astype(np.float32)))
        return torch.stack(planes)

    # ----------------------------------------------------------------------------- video
    def encode_coverage(self, frame_coverage: torch.Tensor) -> torch.Tensor:
        """Per-frame crop coverage (B, F, C) in [0, 1] -> (B, 768) float32 L2-normalized."""
        cov = torch.nan_to_num(torch.as_tensor(frame_coverage, dtype=torch.float64), nan=0.0).clamp(0.0, 1.0)
        if cov.dim() != 3 or cov.shape[2] != self.num_labels:
            raise InputError(f"frame coverage must be (B, frames, {self.num_labels}), got {tuple(cov.shape)}",
                             field="frame_coverage")
        coverage = cov.mean(dim=1)                                          # (B, C)
        background = (1.0 - coverage.sum(dim=1)).clamp_min(0.0)           # (B,)
        weights = torch.cat([self.salience * coverage, background[:, None]], dim=1)          # (B, C+1)
        embeddings = torch.cat([self._label_emb, self._background[None]], dim=0)            # (C+1, D)
        return mix_embeddings(weights, embeddings, self._generic).float()

    def encode_video(self, clips: torch.Tensor) -> torch.Tensor:
        """clips (B, 8, C, h, w) mask coverage in [0, 1] -> (B, 768) float32 L2-normalized."""
        clips = torch.as_tensor(clips)
        if clips.dim() != 5 or clips.shape[2] != self.num_labels:
            raise InputError(f"clips must be (B, frames, {self.num_labels}, h, w) mask coverage, got "
                             f"{tuple(clips.shape)}", field="clips")
        return self.encode_coverage(clips.to(torch.float64).mean(dim=(3, 4)))


def create_encoder(*, masks: Any = None, scene: Any = None, base_dir: str | Path | None = None,
                   salience: float = DEFAULT_SALIENCE, **unused: Any) -> AnnotationMaskEncoder:
    """Factory of ``get_encoder("masks", ...)``. Without ``masks`` the ones recorded in ``scene``'s
    language block are reused (a later query reopens the field's encoder)."""
    unknown = set(unused) - {"device", "dtype", "batch_size"}
    if unknown:
        raise InputError(f"unknown option(s) for the annotation-mask encoder: {', '.join(sorted(unknown))}",
                         field="encoder")
    if not masks and scene is not None:
        lang = getattr(scene, "language", None) or {}
        recorded = (lang.get("encoder_config") or {}).get("masks")
        if isinstance(recorded, dict):
            masks = recorded
    return AnnotationMaskEncoder(masks, base_dir=base_dir, salience=salience)
