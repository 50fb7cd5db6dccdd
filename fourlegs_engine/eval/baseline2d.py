"""The "2D Features" baseline (paper §4.4, Table 3): grounding straight from the teacher features.

No 3D at all: for one evaluation view, every frame's 8-frame tube is cut into the crop pyramid, the
crops are encoded by the video-text encoder, per-pixel features are interpolated from the crop
features (mean over scales, eq. 2; :mod:`fourlegs_engine.language.pyramid`), and the LERF relevancy of
every pixel to the query is the spatial prediction. Temporal localization applies the paper's rule
(:func:`fourlegs_engine.query.temporal.localize_relevancy`) with the view's pixels in place of the
Gaussians; the box is the box of the best connected component of relevancy > 0.5
(:func:`fourlegs_engine.query.spatial.best_component_bbox`).

Knob: ``pixel_stride`` — per-pixel features are interpolated on every ``pixel_stride``-th pixel and
the relevancy map is bilinearly upsampled to full resolution (1 = exact eq. 2 at every pixel).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np
import torch

from ..errors import InputError
from ..language.encoders import CANONICAL_PHRASES
from ..language.pyramid import (crop_layout, pixel_features, pyramid_ratios, resize_crops, scale_crops,
                                tube_indices, upsample_to_pixels)
from ..query.relevancy import RELEVANCY_SCALE, l2_normalize, reference_set
from ..query.spatial import best_component_bbox
from ..query.temporal import localize_relevancy
from ..scene.camera import Camera

RGB_CROP_SIZE = 224


@dataclass
class ViewPrediction:
    """A method's answer to one query in one view.

    Attributes:
        frames: (T,) bool predicted frames.
        scores: (T,) per-frame temporal scores s_t (ranked by tAP).
        relevancy_map: t -> (H,W) float relevancy map; called only for frames the metrics need.
        box: t -> (4,) float64 box (x0, y0, x1, y1), x1/y1 exclusive, NaN when there is none.
    """

    frames: np.ndarray
    scores: np.ndarray
    relevancy_map: Callable[[int], np.ndarray]
    box: Callable[[int], np.ndarray]


def inclusive_to_exclusive(box: Sequence[int] | None) -> np.ndarray:
    """Inclusive pixel box (x0, y0, x1, y1) or None -> exclusive float64 box, NaN row for None."""
    if box is None:
        return np.full(4, np.nan)
    x0, y0, x1, y1 = box
    return np.array([x0, y0, x1 + 1, y1 + 1], dtype=np.float64)


class Features2D:
    """Per-view relevancy from the crop-pyramid teacher features of that view alone.

    Args:
        encoder: a video-text encoder (``input_kind`` "labels" or "rgb").
        ratios: crop ratios of the pyramid (default 0.15..0.6, 5 steps).
        pixel_stride: per-pixel features on every ``pixel_stride``-th pixel (1 = every pixel).
        batch_size: crop tubes per encoder call.
    """

    name = "2D features"

    def __init__(self, encoder: Any, *, ratios: Sequence[float] | None = None, pixel_stride: int = 2,
                 batch_size: int = 512):
        if int(pixel_stride) < 1:
            raise InputError(f"pixel_stride must be >= 1, got {pixel_stride}", field="pixel_stride")
        self.encoder = encoder
        self.ratios = tuple(ratios) if ratios is not None else pyramid_ratios()
        self.pixel_stride = int(pixel_stride)
        self.batch_size = int(batch_size)
        self.stats = {"frames_encoded": 0, "crops_encoded": 0}

    # ------------------------------------------------------------------------------ features
    def crop_features(self, video: Any, t: int, camera: Camera) -> torch.Tensor:
        """(num_crops, D) encoder features of the crop pyramid of the tube around ``t``."""
        T = len(video)
        tube = torch.stack([video[k] for k in tube_indices(t, T)])              # (8, C, H, W)
        layout = crop_layout(camera.width, camera.height, self.ratios)
        enc = self.encoder.bind_camera(camera.name) if hasattr(self.encoder, "bind_camera") else self.encoder
        use_means = getattr(self.encoder, "input_kind", "rgb") == "labels" and hasattr(enc, "encode_coverage")
        feats = []
        with torch.no_grad():
            for grid in layout.scales:
                if use_means:
                    from ..language.extract import crop_means
                    means = crop_means(tube, grid)                               # (n, 8, C)
                    for s in range(0, means.shape[0], self.batch_size):
                        feats.append(enc.encode_coverage(means[s:s + self.batch_size]).float())
                else:
                    crops = scale_crops(tube, grid)
                    rgb = getattr(self.encoder, "input_kind", "rgb") == "rgb"
                    for s in range(0, crops.shape[0], self.batch_size):
                        batch = resize_crops(crops[s:s + self.batch_size], RGB_CROP_SIZE if rgb else None,
                                             clip_normalize=rgb)
                        feats.append(enc.encode_video(batch).float())
        self.stats["frames_encoded"] += 1
        self.stats["crops_encoded"] += layout.num_crops
        return torch.cat(feats)

    def relevancy_maps(self, video: Any, t: int, camera: Camera, query_emb: torch.Tensor,
                       canon_emb: torch.Tensor) -> torch.Tensor:
        """(Q, H, W) float32 relevancy of every pixel at ``t`` to each of the Q query embeddings."""
        layout = crop_layout(camera.width, camera.height, self.ratios)
        crops = self.crop_features(video, t, camera)
        feats = pixel_features(layout, crops, self.pixel_stride)                 # (h, w, D)
        h, w, D = feats.shape
        phi = l2_normalize(feats.reshape(-1, D).float())
        refs = reference_set(canon_emb.float())
        q = l2_normalize(query_emb.float())
        margin = RELEVANCY_SCALE * (phi @ q.T - (phi @ refs.T).max(dim=1, keepdim=True).values)  # (hw, Q)
        rel = torch.sigmoid(margin).reshape(h, w, -1)
        rel = upsample_to_pixels(rel, camera.width, camera.height, self.pixel_stride)  # (H, W, Q)
        return rel.permute(2, 0, 1).clamp(0.0, 1.0).contiguous()

    # ------------------------------------------------------------------------------ predict
    def predict_view(self, video: Any, camera: Camera, queries: Sequence[str], text_encoder: Any,
                     *, progress: Callable[[int], None] | None = None) -> dict[str, ViewPrediction]:
        """Predictions of every query in one view (one pass over the frames for all queries)."""
        T = len(video)
        query_emb = text_encoder.encode_text(list(queries)).float()
        canon_emb = text_encoder.encode_text(list(CANONICAL_PHRASES)).float()
        big = T * len(queries) * camera.width * camera.height * 4 > 400 * 2 ** 20
        maps = torch.empty((T, len(queries), camera.height, camera.width),
                           dtype=torch.float16 if big else torch.float32)
        for t in range(T):
            maps[t] = self.relevancy_maps(video, t, camera, query_emb, canon_emb).to(maps.dtype)
            if progress is not None:
                progress(t)
        out = {}
        for qi, text in enumerate(queries):
            qmaps = maps[:, qi]
            temporal = localize_relevancy(qmaps.reshape(T, -1).float(), query=text)
            frames = np.asarray(temporal.positive, dtype=bool)
            out[text] = ViewPrediction(
                frames=frames, scores=np.asarray(temporal.scores, dtype=np.float64),
                relevancy_map=lambda t, m=qmaps: m[int(t)].float().numpy(),
                box=lambda t, m=qmaps: inclusive_to_exclusive(best_component_bbox(m[int(t)].float().numpy())))
        return out
