"""Codebook fast path: k-means the (T,N,d) latents of a scene into K codes once.

A query then decodes only the K codes (once per engine: the decoded codebook does not depend on the
query), scores them, and

* scores every Gaussian by lookup ``R[codes[t]]`` (``gaussian_relevancy``), and
* answers a temporal query from the per-timestep code histogram (T,K): the counts of the temporal
  localization become a (T,K) reduction, so T x N latents are never decoded;
* optionally re-scores exactly the Gaussians of the few codes whose relevancy lies near the temporal
  thresholds (0.5 and R_avg): ``members`` lists, per code, which (t, g) hold it, so those latents
  are read without scanning the field.

K-means stays feasible on a CPU for 300k x 150 latents by training on a sample and, for large K, a
two-level (coarse K1 x fine K2 = K) quantizer: a point is assigned to its nearest coarse centroid, then
to the nearest fine code inside that cell. Assignment streams over timesteps in chunks with torch
matmuls. Each stored code is the mean of the latents assigned to it (over every timestep). Files (inside the
bundle's ``language/`` directory, each written atomically)::

    codebook_K.npz   centroids (K,d) float32, histogram (T,K) int32, coarse (K1,d), meta (json string)
    codes_K.npy      (T,N) uint16 (K <= 65536) or int32 code index of every Gaussian at every timestep
    members_K.npy    (T*N,) flat indices t*N+g sorted by code (int32, or int64 past 2**31 entries);
                     code k's members are members[offsets[k]:offsets[k+1]], offsets from the histogram
"""
from __future__ import annotations

import json
import math
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np
import torch

from ..errors import InputError
from ..fileio import atomic_path, load_npy, save_npy_atomic

CODEBOOK_VERSION = 2  # 2: each code is the mean of its members
MEMBER_MEANS = "member means"  # meta["centroids"] of a codebook whose codes are their members' means
SINGLE_LEVEL_WORK = 4e9  # points x codes below which a flat k-means is affordable
ASSIGN_CHUNK = 1 << 18


@dataclass
class Codebook:
    """K codes of a latent field.

    Attributes:
        centroids: (K,d) float32 code vectors.
        codes: (T,N) integer array (memmap when loaded) of each Gaussian's code per timestep.
        histogram: (T,K) int32 number of Gaussians holding each code at each timestep.
        coarse: (K1,d) coarse centroids of the two-level quantizer (K1 = 1 when flat).
        meta: build settings and the fingerprint of the latents it was built from.
        members: (T*N,) flat indices t*N+g grouped by code (memmap when loaded; built on first use when
            the file is missing).
    """

    centroids: np.ndarray
    codes: Any
    histogram: np.ndarray
    coarse: np.ndarray
    meta: dict
    members: Any = None
    _offsets: Any = field(default=None, repr=False, compare=False)

    @property
    def size(self) -> int:
        return int(self.centroids.shape[0])

    def member_offsets(self) -> np.ndarray:
        """(K+1,) int64 start of each code's run in :attr:`members` (computed once)."""
        if self._offsets is None:
            per_code = np.asarray(self.histogram).sum(axis=0, dtype=np.int64)
            self._offsets = np.concatenate([[0], np.cumsum(per_code)])
        return self._offsets

    def members_with_codes(self, codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every (t, g) holding one of ``codes``: flat indices t*N+g (M,) int64 and their codes (M,) int64,
        grouped by code in the order of ``codes``."""
        if self.members is None:
            self.members = member_index(self.codes)
        off = self.member_offsets()
        codes = np.asarray(codes, dtype=np.int64)
        parts = [np.asarray(self.members[off[k]:off[k + 1]], dtype=np.int64) for k in codes]
        if not parts:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        return np.concatenate(parts), np.repeat(codes, off[codes + 1] - off[codes])

    def sample_members(self, codes: np.ndarray, size: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """A uniform sample without replacement of ``size`` (t, g) pairs among those holding one of ``codes``
        (all of them, in random order, when there are no more than ``size``).

        Returns:
            flat indices t*N+g (M,) int64 and their codes (M,) int64, M = min(size, population).
        """
        if self.members is None:
            self.members = member_index(self.codes)
        off = self.member_offsets()
        codes = np.asarray(codes, dtype=np.int64)
        per_code = off[codes + 1] - off[codes]
        ends = np.cumsum(per_code)
        population = int(ends[-1]) if len(ends) else 0
        picks = rng.permutation(population) if population <= size else rng.choice(population, size, replace=False)
        which = np.searchsorted(ends, picks, side="right")  # the code each pick falls in
        within = picks - (ends[which] - per_code[which])
        return np.asarray(self.members[off[codes[which]] + within], dtype=np.int64), codes[which]

    def quantization_error(self, latents, timesteps=None, max_points: int = 200_000) -> float:
        """Mean squared distance between latents and their codes over (a sample of) the field."""
        T = latents.shape[0]
        ts = range(T) if timesteps is None else timesteps
        err, n = 0.0, 0
        for t in ts:
            x = np.asarray(latents[t], dtype=np.float32)
            c = self.centroids[np.asarray(self.codes[t], dtype=np.int64)]
            err += float(((x - c) ** 2).sum())
            n += x.shape[0]
            if n >= max_points:
                break
        return err / max(n, 1)


# ----------------------------------------------------------------------------- k-means
def _sqnorm(c: torch.Tensor) -> torch.Tensor:
    return (c * c).sum(1)


def nearest(x: torch.Tensor, centroids: torch.Tensor, chunk: int = ASSIGN_CHUNK) -> torch.Tensor:
    """(M,d),(K,d) -> (M,) int64 index of the nearest centroid (squared Euclidean), chunked matmuls."""
    cn = _sqnorm(centroids)
    out = torch.empty(x.shape[0], dtype=torch.int64)
    step = max(1, min(chunk, int(1 << 24) // max(centroids.shape[0], 1)))  # <= 64 MB of distances
    for s in range(0, x.shape[0], step):
        d = torch.addmm(cn[None], x[s:s + step], centroids.T, alpha=-2.0)
        out[s:s + step] = d.argmin(1)
    return out


def _update_centroids(x: torch.Tensor, idx: torch.Tensor, cent: torch.Tensor) -> None:
    """In place: each centroid becomes the mean of its points (segment sums over sorted indices)."""
    k = cent.shape[0]
    counts = np.bincount(idx.numpy(), minlength=k)
    filled = np.nonzero(counts)[0]
    if len(filled) == 0:
        return
    order = np.argsort(idx.numpy(), kind="stable")
    starts = (np.cumsum(counts) - counts)[filled]
    sums = np.add.reduceat(x.numpy()[order], starts, axis=0)
    cent[torch.from_numpy(filled)] = torch.from_numpy(sums / counts[filled, None]).to(cent.dtype)


def kmeans(x: torch.Tensor, k: int, *, iters: int = 10, seed: int = 0) -> torch.Tensor:
    """Lloyd's k-means. (M,d) -> (k,d) centroids; k > M pads with repeated points (never chosen).

    Initialized from k distinct random points (duplicates, e.g. never-seen Gaussians' zero latents,
    are removed first, so data with at most k distinct rows is reproduced exactly); an empty cluster
    keeps its previous centroid.
    """
    M, d = x.shape
    g = torch.Generator().manual_seed(seed)
    if M == 0:
        return torch.zeros(k, d, dtype=x.dtype)
    distinct = torch.unique(x, dim=0)
    if len(distinct) <= k:
        pad = distinct[torch.arange(k - len(distinct)) % len(distinct)]
        return torch.cat([distinct, pad], 0).clone()
    cent = distinct[torch.randperm(len(distinct), generator=g)[:k]].clone()
    for _ in range(iters):
        _update_centroids(x, nearest(x, cent), cent)
    return cent


def kmeans_per_cell(x: torch.Tensor, cell: torch.Tensor, coarse: torch.Tensor, k2: int, *, iters: int = 8,
                    seed: int = 0, batch_cells: int = 32) -> torch.Tensor:
    """Batched Lloyd's k-means of ``k2`` codes inside every coarse cell.

    Args:
        x: (S,d) points; cell: (S,) their coarse cell; coarse: (K1,d) coarse centroids.
    Returns:
        (K1*k2, d) fine codes, code = cell * k2 + j (an empty cell repeats its coarse centroid).
    """
    k1, d = coarse.shape
    fine = coarse.repeat_interleave(k2, 0).clone()
    g = torch.Generator().manual_seed(seed)
    order = torch.argsort(cell, stable=True)
    counts = torch.bincount(cell, minlength=k1)
    starts = torch.cumsum(counts, 0) - counts
    for c0 in range(0, k1, batch_cells):
        cells = torch.arange(c0, min(k1, c0 + batch_cells))
        m = int(counts[cells].max()) if len(cells) else 0
        if m == 0:
            continue
        # padded (B, m, d) members of each cell; padding rows repeat the cell's members
        slot = torch.arange(m)[None, :]
        n = counts[cells][:, None].clamp_min(1)
        rows = order[(starts[cells][:, None] + slot % n).clamp_max(len(order) - 1)]
        valid = (slot < counts[cells][:, None])
        pts = x[rows]  # (B, m, d)
        # init: k2 random members per cell (wrapping when a cell has fewer than k2 points)
        perm = torch.argsort(torch.rand(len(cells), m, generator=g) + (~valid).float(), dim=1)
        pick = perm[:, torch.arange(k2) % m]
        pick = torch.where(torch.arange(k2)[None, :] < counts[cells][:, None], pick, pick[:, :1] * 0 +
                           (torch.arange(k2)[None, :] % n))
        cent = torch.gather(pts, 1, pick[..., None].expand(-1, -1, d)).clone()  # (B, k2, d)
        for _ in range(iters):
            dist = (cent * cent).sum(-1)[:, None, :] - 2 * torch.bmm(pts, cent.transpose(1, 2))
            j = dist.argmin(-1)  # (B, m)
            flat = (torch.arange(len(cells))[:, None] * k2 + j)[valid]
            flat_cent = cent.reshape(-1, d)
            _update_centroids(pts[valid], flat, flat_cent)
            cent = flat_cent.reshape(len(cells), k2, d)
        has = counts[cells] > 0
        for b in torch.nonzero(has).reshape(-1).tolist():
            c = int(cells[b])
            fine[c * k2:(c + 1) * k2] = cent[b]
    return fine


def split_levels(k: int, num_points: int) -> tuple[int, int]:
    """(K1, K2) with K1 * K2 = k: flat (1, k) when affordable, else K1 the largest divisor <= sqrt(k)."""
    if num_points * k <= SINGLE_LEVEL_WORK:
        return 1, k
    k1 = int(math.isqrt(k))
    while k % k1:
        k1 -= 1
    return k1, k // k1


def train(sample: torch.Tensor, k: int, *, num_points: int, seed: int = 0, iters: int = 10
          ) -> tuple[torch.Tensor, torch.Tensor]:
    """Train a (possibly two-level) quantizer on ``sample`` (S,d).

    Returns:
        coarse (K1,d), fine (K1*K2, d) with code = cell * K2 + j.
    """
    k1, k2 = split_levels(k, num_points)
    if k1 == 1:
        fine = kmeans(sample, k, iters=iters, seed=seed)
        return sample.mean(0, keepdim=True) if len(sample) else torch.zeros(1, sample.shape[1]), fine
    coarse = kmeans(sample, k1, iters=iters, seed=seed)
    cell = nearest(sample, coarse)
    return coarse, kmeans_per_cell(sample, cell, coarse, k2, iters=max(4, iters - 2), seed=seed + 1)


def assign(x: torch.Tensor, coarse: torch.Tensor, fine: torch.Tensor) -> torch.Tensor:
    """(M,d) -> (M,) code index under the two-level quantizer (flat when ``coarse`` has one row)."""
    k1 = coarse.shape[0]
    if k1 == 1:
        return nearest(x, fine)
    k2 = fine.shape[0] // k1
    cell = nearest(x, coarse)
    out = torch.empty_like(cell)
    order = torch.argsort(cell)
    bounds = torch.searchsorted(cell[order], torch.arange(k1 + 1))
    for c in range(k1):
        a, b = int(bounds[c]), int(bounds[c + 1])
        if a == b:
            continue
        rows = order[a:b]
        out[rows] = nearest(x[rows], fine[c * k2:(c + 1) * k2]) + c * k2
    return out


# ----------------------------------------------------------------------------- build / load
def member_means(centroids: torch.Tensor, sums: torch.Tensor, counts: np.ndarray) -> torch.Tensor:
    """(K,d) each code moved to the mean of its members (``sums`` (K,d) float64 of their latents, ``counts``
    (K,) of them); a code without members keeps its centroid. Then Σ over a code's members of (z − c_k)
    is 0, which :mod:`.refined_counts` uses: a first-order expansion of the relevancy around each code sums,
    over the code's members, to the code's own relevancy times their count."""
    n = torch.as_tensor(counts, dtype=torch.float64)
    held = n > 0
    out = centroids.double().clone()
    out[held] = sums[held] / n[held, None]
    return out.to(centroids.dtype)


def member_index(codes) -> np.ndarray:
    """(T,N) codes -> (T*N,) flat indices t*N+g ordered by code (stable: by t, then g, within a code)."""
    flat = np.asarray(codes).reshape(-1)
    order = np.argsort(flat, kind="stable")
    return order.astype(np.int32) if flat.size < 2 ** 31 else order.astype(np.int64)


def fingerprint(latents) -> dict:
    """What the codebook depends on: the latents' shape, dtype, file identity and a few sampled values."""
    T, N, d = (int(s) for s in latents.shape)
    fp: dict[str, Any] = {"shape": [T, N, d], "dtype": str(latents.dtype)}
    fname = getattr(latents, "filename", None)
    if fname:
        st = Path(fname).stat()
        fp["file_size"] = int(st.st_size)
        fp["mtime_ns"] = int(st.st_mtime_ns)
    if T and N:
        # nine rows read one by one: fancy indexing a memmap's timesteps would read three whole timesteps
        probe = np.array([[latents[t, g] for g in (0, N // 2, N - 1)] for t in (0, T // 2, T - 1)],
                         dtype=np.float64)
        fp["probe"] = float(np.round(probe.sum(), 6))
    return fp


def sample_latents(latents, size: int, seed: int = 0) -> torch.Tensor:
    """(S,d) float32 uniform sample of (t, g) pairs, read timestep by timestep from the memmap."""
    T, N, d = latents.shape
    M = T * N
    rng = np.random.default_rng(seed)
    if M <= size:
        return torch.from_numpy(np.asarray(latents, dtype=np.float32).reshape(M, d).copy())
    flat = np.sort(rng.choice(M, size=size, replace=False))
    ts, gs = np.divmod(flat, N)
    out = np.empty((size, d), dtype=np.float32)
    for t in np.unique(ts):
        sel = ts == t
        out[sel] = np.asarray(latents[int(t)], dtype=np.float32)[gs[sel]]
    return torch.from_numpy(out)


def build_codebook(latents, k: int, *, out_dir: Optional[Path] = None, seed: int = 0, sample_size: Optional[int] = None,
                   iters: int = 10, progress: bool = False,
                   on_progress: Optional[Callable[[float, str], None]] = None) -> Codebook:
    """K-means the (T,N,d) latents into ``k`` codes and assign every Gaussian at every timestep.

    Args:
        latents: (T,N,d) array-like (memmap; streamed a timestep at a time).
        k: number of codes (<= 2**31).
        out_dir: where to store ``codebook_k.npz`` and ``codes_k.npy`` (None: keep in memory).
        sample_size: training sample (default min(T*N, clip(16 k, 50k, 400k))).
        progress: a tqdm bar over the assignment.
        on_progress: ``(fraction, stage)`` before the training and after each assigned chunk of
            timesteps; an exception it raises stops the build before anything is stored.
    """
    report = on_progress or (lambda fraction, stage: None)
    if k < 1:
        raise InputError(f"codebook size must be >= 1, got {k}", field="codebook")
    T, N, d = (int(s) for s in latents.shape)
    M = T * N
    if sample_size is None:
        sample_size = int(min(M, min(max(16 * k, 50_000), 400_000)))
    torch.manual_seed(seed)
    report(0.0, f"codebook K={k}: training")
    sample = sample_latents(latents, max(1, sample_size), seed) if M else torch.zeros(0, d)
    coarse, fine = train(sample, k, num_points=M, seed=seed, iters=iters)
    report(0.3, f"codebook K={k}: assigning")
    code_dtype = np.uint16 if k <= 65536 else np.int32
    codes_path = None if out_dir is None else Path(out_dir) / f"codes_{k}.npy"
    hist = np.zeros((T, k), dtype=np.int32)
    codes = np.zeros((T, N), dtype=code_dtype)
    steps = range(T)
    if progress:
        from tqdm import tqdm
        steps = tqdm(steps, desc=f"codebook K={k}: assigning", unit="t")
    per_chunk = max(1, ASSIGN_CHUNK * 4 // max(N, 1))
    member_sums = torch.zeros(k, d, dtype=torch.float64)
    for t0 in range(0, T, per_chunk):
        t1 = min(T, t0 + per_chunk)
        x = torch.from_numpy(np.array(latents[t0:t1], dtype=np.float32).reshape(-1, d))
        assigned = assign(x, coarse, fine)
        member_sums.index_add_(0, assigned, x.double())
        c = assigned.numpy().reshape(t1 - t0, N)
        codes[t0:t1] = c.astype(code_dtype)
        for i, t in enumerate(range(t0, t1)):
            hist[t] = np.bincount(c[i], minlength=k)
        if progress:
            steps.update(t1 - t0)  # type: ignore[attr-defined]
        report(0.3 + 0.7 * t1 / T, f"codebook K={k}: assigned {t1}/{T} timesteps")
    if progress:
        steps.close()  # type: ignore[attr-defined]
    fine = member_means(fine, member_sums, hist.sum(axis=0, dtype=np.int64))
    meta = {"version": CODEBOOK_VERSION, "k": k, "levels": [int(coarse.shape[0]), k // int(coarse.shape[0])],
            "seed": seed, "sample_size": int(sample_size), "iters": iters, "latents": fingerprint(latents),
            "centroids": MEMBER_MEANS}
    book = Codebook(centroids=fine.numpy().astype(np.float32), codes=codes, histogram=hist,
                    coarse=coarse.numpy().astype(np.float32), meta=meta, members=member_index(codes))
    if out_dir is not None:
        save_codebook(book, Path(out_dir), k)
        book.codes = load_npy(codes_path, mmap=True, field="codes")
        book.members = load_npy(Path(out_dir) / f"members_{k}.npy", mmap=True, field="members")
    return book


def save_codebook(book: Codebook, out_dir: Path, k: int) -> None:
    """Write the codebook's files; the .npz goes last and is removed first, so a crash in between
    leaves no codebook that pairs new codes with an old header."""
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / f"codebook_{k}.npz").unlink(missing_ok=True)
    save_npy_atomic(out_dir / f"codes_{k}.npy", np.asarray(book.codes))
    if book.members is None:
        book.members = member_index(book.codes)
    save_npy_atomic(out_dir / f"members_{k}.npy", np.asarray(book.members))
    with atomic_path(out_dir / f"codebook_{k}.npz") as tmp:
        np.savez(tmp, centroids=book.centroids, histogram=book.histogram, coarse=book.coarse,
                 meta=np.array(json.dumps(book.meta)))


def load_codebook(out_dir: Path, k: int, latents=None) -> Optional[Codebook]:
    """The stored codebook of size ``k``, or None when missing or built from different latents."""
    npz_path = Path(out_dir) / f"codebook_{k}.npz"
    codes_path = Path(out_dir) / f"codes_{k}.npy"
    if not npz_path.is_file() or not codes_path.is_file():
        return None
    try:
        with np.load(npz_path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            book = Codebook(centroids=z["centroids"], codes=None, histogram=z["histogram"], coarse=z["coarse"],
                            meta=meta)
    except (ValueError, KeyError, OSError, EOFError, MemoryError, zipfile.BadZipFile, json.JSONDecodeError) as exc:
        raise InputError(f"corrupt codebook ({type(exc).__name__}: {exc}); delete it to rebuild",
                         file=npz_path) from None
    if not isinstance(meta, dict):
        raise InputError("corrupt codebook (meta is not an object); delete it to rebuild", file=npz_path)
    if meta.get("version") != CODEBOOK_VERSION or meta.get("k") != k:
        return None
    if latents is not None and meta.get("latents") != fingerprint(latents):
        return None
    if book.centroids.ndim != 2 or book.centroids.dtype.kind != "f" or not np.isfinite(book.centroids).all():
        raise InputError("corrupt codebook (centroids must be a finite 2D array); delete it to rebuild",
                         file=npz_path, field="centroids")
    book.codes = load_npy(codes_path, mmap=True, field="codes")
    expected = tuple(latents.shape[:2]) if latents is not None else book.codes.shape
    if book.codes.dtype.kind not in "iu" or tuple(book.codes.shape) != expected or (
            book.codes.size and not 0 <= int(book.codes.min()) <= int(book.codes.max()) < book.centroids.shape[0]):
        raise InputError(f"corrupt codes (must be integers 0..{book.centroids.shape[0] - 1} of shape {expected}); "
                         "delete them to rebuild", file=codes_path, field="codes")
    members_path = Path(out_dir) / f"members_{k}.npy"
    if members_path.is_file():
        book.members = load_npy(members_path, mmap=True, field="members")
        if book.members.shape != (int(np.prod(book.codes.shape)),):
            book.members = None  # a stale index is rebuilt in memory on first use
    return book


def ensure_codebook(latents, k: int, out_dir: Optional[Path], **kw) -> Codebook:
    """Load the stored codebook for these latents, or build (and store) it."""
    if out_dir is not None:
        book = load_codebook(out_dir, k, latents)
        if book is not None:
            return book
    return build_codebook(latents, k, out_dir=out_dir, **kw)
