"""Encoding one timestep's crop pyramid: the crops of every training camera, batched through the encoder.

:class:`TimestepEncoder` fills the (num_crops_total, D) float16 features of one timestep, camera by camera
(on parallel streams for label-coverage encoders), copying the rows an early exit finds unchanged from
the previous encoded timestep; :class:`CropBatcher` collects crop tubes and encodes them a batch at a time.
"""
from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from typing import Any, Sequence

import numpy as np
import torch

from ..errors import InputError
from ..scene.scene import Scene
from ..threads import torch_threads
from .frames import ChangeSignals, FrameSource
from .pyramid import PyramidLayout, resize_crops, scale_crops, tube_indices
from .skipping import comparison_frames

#: crop sizes: RGB encoders see crops resized to this; label encoders with ``encode_coverage`` read exact
#: per-frame crop means instead
RGB_CROP_SIZE = 224
COVERAGE_MEANS = "means"


def extract_streams() -> int:
    """Cameras encoded concurrently: one per torch thread (torch's default is the core count)."""
    return max(1, min(torch.get_num_threads(), 8))


class TimestepEncoder:
    """Encodes the crops of every selected camera of one timestep at a time.

    Args:
        scene, encoder: the scene and the video-text (or label) encoder.
        source: the frames the encoder sees. config: the :class:`~.extract.ExtractOptions`.
        crop_size: RGB crop side, or :data:`COVERAGE_MEANS`.
    Attributes:
        encoded, copied: clips the encoder saw / clips an early exit copied, over all calls.
        seconds: encoder seconds over all calls.
    """

    def __init__(self, scene: Scene, encoder: Any, source: FrameSource, config: Any, crop_size: Any):
        self.scene, self.encoder, self.source, self.config = scene, encoder, source, config
        self.crop_size = crop_size
        self.coverage = crop_size == COVERAGE_MEANS
        self.clip_normalize = encoder.input_kind == "rgb"
        num_cameras = scene.cameras.num_cameras(config.split)
        self.selected = set(range(num_cameras) if config.cameras is None else config.cameras)
        self.signals = (ChangeSignals(scene, source, config.early_exit, config.split)
                        if config.early_exit != "none" else None)
        self.batch_size = config.batch_size or (32 if encoder.input_kind == "rgb" else 256)
        self.encoded = self.copied = 0
        self.seconds = 0.0
        self._lock = threading.Lock()
        # label-coverage cameras are independent small jobs (a rasterization, crop means, a few encoder
        # calls): they run on parallel streams with one torch thread each, which keeps every core busy
        # where intra-op threads would mostly wait on each other; each camera's rows are its own, so the
        # features do not depend on the number of streams
        streams = extract_streams() if self.coverage else 1
        self.pool = ThreadPoolExecutor(streams) if streams > 1 else None

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown()

    def encode(self, t: int, layouts: Sequence[PyramidLayout], offsets: Sequence[int],
               prior: tuple[int, np.ndarray] | None) -> np.ndarray:
        """(num_crops_total, D) float16 features of timestep ``t``; ``prior`` = (timestep, features) of the
        previous encoded timestep, which early exits copy unchanged crops from (None: encode every crop).
        Rows of a camera without any annotated frame in its tube stay zero: no evidence."""
        out = np.zeros((sum(l.num_crops for l in layouts), int(self.encoder.dim)), dtype=np.float16)
        cameras = self.scene.cameras.cameras(t, self.config.split)

        def one(c: int) -> float:
            return self._camera(t, c, cameras[c], layouts[c], offsets[c], out, prior)

        with torch_threads(1) if self.pool is not None else nullcontext():
            cams = range(len(layouts))
            self.seconds += sum(self.pool.map(one, cams) if self.pool is not None else map(one, cams))
        if not np.all(np.isfinite(out)):
            raise InputError(f"the encoder produced NaN/Inf features at timestep {t}", field="encoder")
        return out

    def _unchanged(self, t: int, c: int, layout: PyramidLayout, offset: int, out: np.ndarray,
                   prior: tuple[int, np.ndarray] | None) -> torch.Tensor | None:
        """Copy the rows an early exit finds unchanged since ``prior``; (num_crops,) bool of those copied."""
        if self.signals is None or prior is None:
            return None
        before, features = prior
        same = self.signals.unchanged(c, layout, comparison_frames(t, before, self.scene.num_timesteps),
                                      self.config.unchanged_below)
        if same is None:
            return None
        rows = offset + np.flatnonzero(same.numpy())
        out[rows] = features[rows]
        with self._lock:
            self.copied += int(same.sum())
        return same

    def _camera(self, t: int, c: int, camera: Any, layout: PyramidLayout, offset: int, out: np.ndarray,
                prior: tuple[int, np.ndarray] | None) -> float:
        """Encode camera c's crops of timestep t into its rows of ``out``; returns encoder seconds."""
        if c not in self.selected:
            return 0.0
        same = self._unchanged(t, c, layout, offset, out, prior)
        keep = None if same is None else ~same          # crops to encode; the others were copied
        # one camera per batch: encoders may depend on the camera (the simulated one's bias)
        encoder = self.encoder.bind_camera(camera.name) if hasattr(self.encoder, "bind_camera") else self.encoder
        batcher = CropBatcher(encoder, out, self.batch_size, coverage=self.coverage)
        if self.coverage:
            # crop means depend on one frame only: computed once per frame, shared by 8 tubes
            frames = [self.source.crop_means(k, c, layout) for k in tube_indices(t, self.scene.num_timesteps)]
            frames = [m for m in frames if m is not None]
            if not frames:
                return 0.0
            idx = np.arange(layout.num_crops) if keep is None else np.flatnonzero(keep.numpy())
            batcher.add(torch.stack(frames, 1)[idx], offset + idx)  # (n, L, C)
        else:
            tube = self.source.tube(t, c)
            if tube is None:
                return 0.0
            for grid in layout.scales:
                idx = np.arange(grid.num_crops)
                crops = scale_crops(tube, grid)
                if keep is not None:
                    idx = np.flatnonzero(keep[grid.offset:grid.offset + grid.num_crops].numpy())
                    crops = crops[idx]
                # raw crops are small; resizing to 224 happens per batch (a 224 px tube is 4.8 MB)
                batcher.add(crops, offset + grid.offset + idx,
                            transform=lambda x: resize_crops(x, self.crop_size, clip_normalize=self.clip_normalize))
        batcher.flush()
        with self._lock:
            self.encoded += batcher.encoded
        return batcher.seconds


class CropBatcher:
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
