"""What the encoder sees: the frames of one camera (rendered or read), their crop means, and the per-crop
change signals of the early exits.

- :class:`FrameSource` renders (RGB, or per-pixel label coverage) or reads (annotation masks) and caches
  the (C, H, W) frames of every (timestep, camera), and their crop means.
- :class:`ChangeSignals` says which crops of a camera saw no change over a tube (early exits, :mod:`.skipping`).
- :func:`crop_means` / :func:`frame_crop_means`: per-crop channel means from a float64 summed-area table.
"""
from __future__ import annotations

import threading
import time
from collections import OrderedDict
from typing import Any, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import InputError
from ..scene.scene import Scene
from .pyramid import PyramidLayout, tube_indices
from .skipping import foreground_values, render_foreground, unchanged_crops


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
            from .coverage import render_label_coverage
            return render_label_coverage(self.scene, camera, t, num_labels=self.num_labels).to(torch.float32)
        return out.detach().to(torch.float32).permute(2, 0, 1).contiguous().clamp_(0.0, 1.0)


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
