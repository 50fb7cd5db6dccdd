"""Reader for calibrated multiview video in the Dynamic 3D Gaussians layout.

Layout::

    DATASET/
      train_meta.json   {"w", "h", "k"[t][c] 3x3, "w2c"[t][c] 4x4 (OpenCV axes), "fn"[t][c], "cam_id"[t][c]}
      test_meta.json    the same for the held-out cameras (optional)
      ims/{cam}/{t:06d}.jpg
      seg/{cam}/{t:06d}.png   foreground masks (optional; training cameras)

Everything is checked before any fitting starts: a missing frame, a malformed calibration or an image
whose size differs from the metadata is one :class:`~fourlegs_engine.errors.InputError` naming the file
and the field.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import InputError
from ..scene.camera import Camera
from ..scene.dynamic3dgs import META_FILES, read_camera_meta

#: Panoptic rigs render with near 1.0, far 100 (Dynamic 3D Gaussians' setting)
NEAR, FAR = 1.0, 100.0


@dataclass
class CaptureSplit:
    """One split (train or test) of a capture.

    Attributes:
        cameras: cameras[t][c] at the dataset's full resolution.
        files: files[t][c] image path relative to ``ims/``.
        cam_ids: cam_ids[t][c] camera ids as strings.
    """

    cameras: list[list[Camera]]
    files: list[list[str]]
    cam_ids: list[list[str]]


class Capture:
    """A calibrated multiview video on disk (see the module docstring for the layout).

    Attributes:
        root: dataset directory. width, height: full image size. num_timesteps: T.
        train, test: :class:`CaptureSplit` (``test`` has empty lists when test_meta.json is absent).
        has_masks: whether ``seg/`` exists.
    """

    def __init__(self, root: str | Path):
        self.root = Path(root)
        if not self.root.is_dir():
            raise InputError("is not a directory", file=self.root)
        train_path = self.root / META_FILES["train"]
        if not train_path.is_file():
            raise InputError("missing (a Dynamic 3D Gaussians dataset needs train_meta.json)", file=train_path)
        self.train, self.width, self.height = _read_split(train_path)
        self.num_timesteps = len(self.train.cameras)
        test_path = self.root / META_FILES["test"]
        if test_path.is_file():
            self.test, w, h = _read_split(test_path)
            if (w, h) != (self.width, self.height):
                raise InputError(f"image size {w}x{h} differs from train_meta.json's {self.width}x{self.height}",
                                 file=test_path, field="w/h")
            if len(self.test.cameras) != self.num_timesteps:
                raise InputError(f"has {len(self.test.cameras)} timesteps, train_meta.json has "
                                 f"{self.num_timesteps}", file=test_path, field="k")
        else:
            self.test = CaptureSplit([[] for _ in range(self.num_timesteps)], [[] for _ in range(self.num_timesteps)],
                                     [[] for _ in range(self.num_timesteps)])
        self.has_masks = (self.root / "seg").is_dir()

    # ----------------------------------------------------------------------- selection
    def timestep_range(self, spec: tuple[int, int] | None) -> range:
        """``(a, b)`` half-open, ``b`` may be None-like via -1 for the end; checked against T."""
        if spec is None:
            return range(self.num_timesteps)
        a, b = spec
        b = self.num_timesteps if b is None or b < 0 else b
        if not 0 <= a < b <= self.num_timesteps:
            raise InputError(f"{a}:{b} is not a non-empty range inside 0:{self.num_timesteps}", field="timesteps")
        return range(a, b)

    def camera_indices(self, split: str, ids: Sequence[str] | None, t: int = 0) -> list[int]:
        """Positions of the cameras called ``ids`` in ``split`` at timestep t (all when None)."""
        s = self.train if split == "train" else self.test
        names = s.cam_ids[t]
        if ids is None:
            return list(range(len(names)))
        out = []
        for cid in ids:
            if str(cid) not in names:
                raise InputError(f"no {split} camera {cid!r} (have {', '.join(names)})", field="cameras")
            out.append(names.index(str(cid)))
        return out

    def check_frames(self, split: str, timesteps: Sequence[int], cams: Sequence[int], masks: bool) -> None:
        """Raise for the first missing, unreadable or wrongly sized image (or mask) among the selected frames.

        Each file's header is read and a PNG's chunks are checked against their checksums (no pixels are
        decoded), so a damaged frame stops the fit before it starts rather than between timesteps.
        """
        s = self.train if split == "train" else self.test
        for t in timesteps:
            for c in cams:
                where = f"timestep {t}, camera {s.cam_ids[t][c]}"
                self._check_file(self.image_path(split, t, c), "frame", where)
                if masks:
                    self._check_file(self.mask_path(split, t, c), "mask", where)

    def _check_file(self, path: Path, what: str, where: str) -> None:
        from PIL import Image

        if not path.is_file():
            raise InputError(f"missing {what} ({where})", file=path)
        try:
            with Image.open(path) as im:
                size = im.size
                im.verify()
        except Image.DecompressionBombError as exc:
            raise InputError(f"is too large to be a {what} ({exc})"[:300], file=path) from None
        except (OSError, SyntaxError, ValueError, EOFError, struct.error) as exc:
            raise InputError(f"is not a readable image ({exc.__class__.__name__}: {str(exc)[:120]})", file=path) from None
        if size != (self.width, self.height):
            raise InputError(f"is {size[0]}x{size[1]} but the metadata says {self.width}x{self.height} ({where})",
                             file=path)

    def image_path(self, split: str, t: int, c: int) -> Path:
        s = self.train if split == "train" else self.test
        return self.root / "ims" / s.files[t][c]

    def mask_path(self, split: str, t: int, c: int) -> Path:
        s = self.train if split == "train" else self.test
        return (self.root / "seg" / s.files[t][c]).with_suffix(".png")

    # ----------------------------------------------------------------------- loading
    def load_image(self, split: str, t: int, c: int, size: tuple[int, int]) -> np.ndarray:
        """(h, w, 3) float32 RGB in [0, 1] resized (area filter) to ``size`` = (w, h)."""
        return self._load_resized(self.image_path(split, t, c), "RGB", size)

    def load_mask(self, split: str, t: int, c: int, size: tuple[int, int]) -> np.ndarray:
        """(h, w) float32 foreground fraction in [0, 1] resized (area filter) to ``size`` = (w, h)."""
        return self._load_resized(self.mask_path(split, t, c), "L", size).clip(0.0, 1.0)

    def _load_resized(self, path: Path, mode: str, size: tuple[int, int]) -> np.ndarray:
        """The image at ``path`` (checked against the metadata's size) in PIL ``mode``, area-resized to
        ``size`` = (w, h), as float32 in [0, 1]: (h, w, 3) for "RGB", (h, w) for "L"."""
        from PIL import Image

        with _open_image(path) as im:
            if im.size != (self.width, self.height):
                raise InputError(f"is {im.size[0]}x{im.size[1]} but the metadata says {self.width}x{self.height}",
                                 file=path)
            im = im.convert(mode)
            if im.size != tuple(size):
                im = im.resize(tuple(size), Image.BOX)
            return np.asarray(im, dtype=np.float32) / 255.0


def _open_image(path: Path):
    from PIL import Image, UnidentifiedImageError

    if not path.is_file():
        raise InputError("missing frame", file=path)
    try:
        im = Image.open(path)
        im.load()
    except Image.DecompressionBombError as exc:
        raise InputError(f"is too large to be a frame ({exc})"[:300], file=path) from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError, EOFError) as exc:
        raise InputError(f"is not a readable image ({exc.__class__.__name__})", file=path) from None
    return im


def _read_split(path: Path) -> tuple[CaptureSplit, int, int]:
    """One split's cameras, image files and names, and the image size (:func:`read_camera_meta`)."""
    meta = read_camera_meta(path, require_files=True, static_rig=True, near=NEAR, far=FAR)
    return CaptureSplit(meta.cameras, meta.files, meta.names), meta.width, meta.height
