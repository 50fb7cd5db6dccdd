"""Scattered rows of a (T, N, d) latent array, read without mapping the file.

The codebook path's re-scoring reads a few thousand rows scattered over a latent file of many GB.
Through a memory mapping each row costs a page fault, and the kernel maps up to 16 cached pages around
it, so the process's resident size grows by up to 64 kB per row until the pages are unmapped again
(a ``madvise`` over the whole mapping). Reading the rows with ``os.pread`` instead copies just their
bytes out of the page cache, cheaper than a fault and its release, and nothing of the file stays in
the process. Rows closer than ``GAP_ROWS`` apart are read in one call, the rows between them read and
dropped: a system call costs about as much as copying that many rows, and a dense set of rows (a
re-scored band covers about a tenth of a timestep) is then read at copying speed. The calls are made
in batches of at most ``BATCH_BYTES``.
"""
from __future__ import annotations

import mmap
import os
import weakref
from typing import Any

import numpy as np

from ..errors import InputError

#: wanted rows at most this many rows apart share one read
GAP_ROWS = 32
#: bytes read per batch of reads (the buffer a batch is copied out of)
BATCH_BYTES = 32 << 20


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
        # spans: runs of wanted rows with gaps of at most GAP_ROWS; one read each
        starts = np.flatnonzero(np.diff(flat, prepend=flat[0] - GAP_ROWS - 2) > GAP_ROWS + 1)
        ends = np.append(starts[1:], flat.size) - 1
        span_rows = flat[ends] - flat[starts] + 1
        span_of = np.repeat(np.arange(starts.size), np.diff(np.append(starts, flat.size)))
        base = int(self.latents.offset)
        done = 0
        while done < starts.size:
            stop = done + max(1, int(np.searchsorted(np.cumsum(span_rows[done:]), BATCH_BYTES // row, side="right")))
            offsets = (base + flat[starts[done:stop]] * row).tolist()
            sizes = (span_rows[done:stop] * row).tolist()
            data = b"".join(map(os.pread, [self._fd] * len(sizes), sizes, offsets))
            if len(data) != sum(sizes):
                raise InputError(f"latent file ended early: {len(data)} of {sum(sizes)} bytes read "
                                 "(was it truncated while in use?)", file=self.path, field="language.latents")
            first, last = int(starts[done]), int(ends[stop - 1]) + 1
            spans = span_of[first:last]
            span_start_row = np.cumsum(np.append(0, span_rows[done:stop - 1]))  # each span's first row in data
            at = span_start_row[spans - done] + (flat[first:last] - flat[starts[spans]])
            out[first:last] = np.frombuffer(data, dtype=self.dtype).reshape(-1, d)[at]
            done = stop
        return out
