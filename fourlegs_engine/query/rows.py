"""Scattered rows of a (T, N, d) latent array, read without mapping the file.

The codebook path's re-scoring reads a few thousand rows scattered over a latent file of many GB.
Through a memory mapping each row costs a page fault, and the kernel maps up to 16 cached pages around
it, so the process's resident size grows by up to 64 kB per row until the pages are unmapped again
(a ``madvise`` over the whole mapping). Reading the rows with ``os.pread`` instead copies just their
bytes out of the page cache, cheaper than a fault and its release, and nothing of the file stays in
the process. Runs of consecutive rows are read in one call.
"""
from __future__ import annotations

import mmap
import os
import weakref
from typing import Any

import numpy as np

from ..errors import InputError


class RowReader:
    """Rows ``latents[t, g]`` at flat indices ``t*N + g``.

    Args:
        latents: (T,N,d) array. A C-contiguous ``np.memmap`` opened on a file (e.g. ``np.load(...,
            mmap_mode="r")``) is read with ``os.pread`` where the platform has it; anything else is
            indexed in memory, one timestep at a time.
    """

    def __init__(self, latents: Any):
        self.latents = latents
        self.shape = tuple(int(s) for s in latents.shape)
        self.dtype = np.dtype(latents.dtype)
        self.path = self._file_of(latents)
        self._fd = None
        if self.path is not None:
            self._fd = os.open(self.path, os.O_RDONLY)  # held, so a later rename over the path is not read
            weakref.finalize(self, os.close, self._fd)

    @staticmethod
    def _file_of(latents: Any):
        """The file behind a top-level C-contiguous memmap (None otherwise: a view's ``offset`` attribute
        is its parent's, so only the array that owns the mapping is read from its file)."""
        if not (isinstance(latents, np.memmap) and isinstance(latents.base, mmap.mmap)
                and latents.flags.c_contiguous and getattr(latents, "filename", None) and hasattr(os, "pread")):
            return None
        return str(latents.filename)

    def read(self, flat: np.ndarray, dtype=np.float32) -> np.ndarray:
        """(M,) sorted flat indices t*N+g -> (M,d) rows as ``dtype``."""
        flat = np.asarray(flat, dtype=np.int64)
        N, d = self.shape[1], self.shape[2]
        out = np.empty((flat.shape[0], d), dtype=dtype)
        if flat.size == 0:
            return out
        if self.path is None:
            t_of, g_of = np.divmod(flat, N)
            bounds = np.searchsorted(t_of, np.unique(t_of))
            for a, b in zip(bounds, list(bounds[1:]) + [len(t_of)]):  # one fancy index per timestep
                out[a:b] = self.latents[int(t_of[a])][g_of[a:b]]
            return out
        row = d * self.dtype.itemsize
        # runs of consecutive indices: one read each
        starts = np.flatnonzero(np.diff(flat, prepend=flat[0] - 2) != 1)
        lengths = np.diff(np.append(starts, flat.size))
        offsets = (int(self.latents.offset) + flat[starts] * row).tolist()
        sizes = (lengths * row).tolist()
        data = b"".join(map(os.pread, [self._fd] * len(sizes), sizes, offsets))
        if len(data) != flat.size * row:
            raise InputError(f"latent file ended early: {len(data)} of {flat.size * row} bytes read "
                             "(was it truncated while in use?)", file=self.path, field="language.latents")
        out[:] = np.frombuffer(data, dtype=self.dtype).reshape(flat.size, d)
        return out
