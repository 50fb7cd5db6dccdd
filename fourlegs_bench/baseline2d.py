"""The "2D Features" baseline (paper §4.4, Table 3): grounding straight from the teacher features.

No 3D at all: for one evaluation view, every frame's 8-frame tube is cut into the crop pyramid, the
crops are encoded by the video-text encoder, per-pixel features are interpolated from the crop
features (mean over scales, eq. 2; :mod:`fourlegs_engine.language.pyramid`), and the LERF relevancy of
every pixel to the query is the spatial prediction. Temporal localization applies the paper's rule
(:func:`fourlegs_engine.query.temporal.localize_relevancy`) with the view's pixels in place of the
Gaussians; the box is the box of the best connected component of relevancy > 0.5
(:func:`fourlegs_engine.query.spatial.best_component_bbox`).

Per-pixel relevancy is computed exactly without materializing the (H, W, 768) feature image
(:func:`pixel_relevancy`: interpolated dot products plus a Gram-matrix norm), checked against the
literal path (:func:`~fourlegs_engine.language.pyramid.pixel_features` then
:func:`~fourlegs_engine.query.lerf.relevancy`) in the tests.

Knob: ``pixel_stride`` — relevancy is evaluated on every ``pixel_stride``-th pixel and bilinearly
upsampled to full resolution (1 = exact eq. 2 at every pixel).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np
import torch

from fourlegs_engine.errors import InputError
from fourlegs_engine.language.encoders import CANONICAL_PHRASES
from fourlegs_engine.language.pyramid import (PyramidLayout, crop_layout, lerp_coefficients, pyramid_ratios, resize_crops,
                                sample_positions, scale_crops, tube_indices, upsample_to_pixels)
from fourlegs_engine.query.lerf import RELEVANCY_SCALE, l2_normalize, reference_set
from fourlegs_engine.query.spatial import best_component_bbox
from fourlegs_engine.query.temporal import localize_relevancy
from fourlegs_engine.scene.camera import Camera

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


def pixel_taps(layout: PyramidLayout, stride: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """Which crops, with which weights, make up each sampled pixel's feature (eq. 2).

    Returns:
        idx (M, 4S) int64 crop indices and w (M, 4S) float64 weights (bilinear per scale, divided by
        the number of scales S), M = ceil(H/stride) * ceil(W/stride) pixels in row-major order, such
        that ``pixel_features(layout, F, stride).reshape(M, D) == (w[..., None] * F[idx]).sum(1)``.
    """
    xs = sample_positions(layout.width, stride)
    ys = sample_positions(layout.height, stride)
    my, mx = ys.shape[0], xs.shape[0]
    S = len(layout.scales)
    idx, wts = [], []
    for g in layout.scales:
        iy, wy = lerp_coefficients(g.first_center, g.stride, g.ny, ys)
        ix, wx = lerp_coefficients(g.first_center, g.stride, g.nx, xs)
        iy1, ix1 = torch.clamp(iy + 1, max=g.ny - 1), torch.clamp(ix + 1, max=g.nx - 1)
        for ry, wy_ in ((iy, 1 - wy), (iy1, wy)):
            for rx, wx_ in ((ix, 1 - wx), (ix1, wx)):
                idx.append((g.offset + ry[:, None] * g.nx + rx[None, :]).reshape(-1))
                wts.append((wy_[:, None] * wx_[None, :]).reshape(-1) / S)
    assert idx[0].shape[0] == my * mx
    return torch.stack(idx, 1), torch.stack(wts, 1).to(torch.float64)


def pixel_relevancy(layout: PyramidLayout, crop_features: torch.Tensor, queries: torch.Tensor,
                    canon: torch.Tensor, stride: int = 1, chunk: int = 16384) -> torch.Tensor:
    """LERF relevancy of every sampled pixel's eq.-2 feature, without forming the (H, W, D) features.

    Relevancy needs only the dot products of the normalized pixel feature with the Q query and K
    canonical embeddings; both are linear in the crop features (interpolate the (n, Q+K) crop dot
    products), and the squared norm is ``w^T G w`` with the crops' Gram matrix ``G = F F^T``. The result
    equals :func:`~fourlegs_engine.query.lerf.relevancy` on :func:`pixel_features` (tested), at a
    fraction of the cost.

    Args:
        layout: crop pyramid; crop_features: (n, D); queries: (Q, D); canon: (K, D) (all L2-normalized
            inside); stride: pixel sampling stride; chunk: pixels per block (memory bound).
    Returns:
        (ceil(H/stride), ceil(W/stride), Q) relevancy in [0, 1], float64.
    """
    Fc = crop_features.to(torch.float64)
    q = l2_normalize(queries.to(torch.float64))
    refs = reference_set(canon.to(torch.float64))
    dots = Fc @ torch.cat([q, refs], 0).T                                          # (n, Q+K)
    gram = Fc @ Fc.T                                                               # (n, n)
    idx, w = pixel_taps(layout, stride)
    M, Q = idx.shape[0], q.shape[0]
    out = torch.empty(M, Q, dtype=torch.float64)
    for s in range(0, M, chunk):
        i, ww = idx[s:s + chunk], w[s:s + chunk]
        pd = (ww[..., None] * dots[i]).sum(1)                                      # (m, Q+K)
        g = gram[i[:, :, None], i[:, None, :]]                                      # (m, 4S, 4S)
        norm = torch.einsum("mj,mjl,ml->m", ww, g, ww).clamp_min(0.0).sqrt().clamp_min(1e-12)
        pd = pd / norm[:, None]
        margin = RELEVANCY_SCALE * (pd[:, :Q] - pd[:, Q:].max(dim=1, keepdim=True).values)
        out[s:s + chunk] = torch.sigmoid(margin)
    my = -(-layout.height // stride)
    return out.reshape(my, -1, Q)


class Features2D:
    """Per-view relevancy from the crop-pyramid teacher features of that view alone.

    Args:
        encoder: a video-text encoder (``input_kind`` "labels" or "rgb").
        ratios: crop ratios of the pyramid (default 0.15..0.6, 5 steps).
        pixel_stride: per-pixel features on every ``pixel_stride``-th pixel (1 = every pixel).
        batch_size: crop tubes per encoder call.
    """

    name = "2D features"

    def __init__(self, encoder: Any, *, ratios: Sequence[float] | None = None, pixel_stride: int = 1,
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
                    from fourlegs_engine.language.frames import crop_means
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
        rel = pixel_relevancy(layout, crops, query_emb, canon_emb, self.pixel_stride)   # (h, w, Q)
        rel = upsample_to_pixels(rel, camera.width, camera.height, self.pixel_stride)   # (H, W, Q)
        return rel.permute(2, 0, 1).clamp(0.0, 1.0).float().contiguous()

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
