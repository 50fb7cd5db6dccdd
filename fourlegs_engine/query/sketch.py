"""A per-pair sketch of the relevancy head: every (g, t) pair's relevancy margin to any query, with a
bound that holds — the index of the sketch path (``QueryOptions(path="sketch")``).

The head (:class:`~.head.RelevancyHead`) scores a latent z through its last hidden activations
u = R·h(z) + β (H of them): against a unit query q and the fixed references c_k the margin is

    m = scale · min_k (u·Qᵀ(q − c_k) + (q − c_k)·b⊥) / ‖(u, b⊥)‖ = scale · (N_q − A) / n

with N_q = u·Qᵀq + q·b⊥ the only query-dependent part, A = max_k (u·Qᵀc_k + c_k·b⊥) and the norm n
query-independent. The sketch keeps, per pair, A and n exactly (float32) and u as its coordinates in a
rank-r principal basis of the u's (u ≈ μ + V·c) and the norm of what the basis misses
(e = u − μ − V·c, orthogonal to V). For a query direction w = Qᵀq:

    |N_q − (μ + V·c)·w − q·b⊥| = |e·w| ≤ ‖e‖·‖w − VVᵀw‖

(Cauchy–Schwarz: e is orthogonal to V), so :meth:`PairSketch.margins` returns each pair's margin
to within a radius that bounds the exact path's own float32 margin (a small pad covers that path's
rounding). A query then costs one (T·N, r) product; only the pairs whose interval straddles a
decision threshold need the exact head (:mod:`.sketch_path`).

Files in the field's ``language/`` directory (``r`` the rank):

    sketch_r.npz       basis (H, r) float64, mean (H,) float64, meta (JSON: version, rank, the
                       latents' fingerprint, the head's and references' hash)
    sketch_coords_r.npy  (T, N, r) float32 coordinates c
    sketch_scalars_r.npy (T, N, 3) float32: A, n, ‖e‖ (‖e‖ = inf where the exact path's float32 values are
                       not finite: those pairs are always scored exactly)

The .npz is written last and removed first, so a crash in between leaves no sketch that pairs new
arrays with an old header.
"""
from __future__ import annotations

import hashlib
import json
import warnings
import zipfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np
import torch

from ..errors import InputError
from ..fileio import atomic_path, load_npy
from ..language.autoencoder import NORM_EPS
from .codebook import fingerprint, sample_latents
from .head import F32_SAFE

SKETCH_VERSION = 2
#: the basis' rank (the coordinates each pair keeps)
DEFAULT_RANK = 32
#: pairs whose u's fit the basis
FIT_SAMPLES = 32_768
#: latents per block of the build (one block per worker thread at a time)
BUILD_BLOCK_ROWS = 2048
#: columns of u per product of the triangular projection
PROJECT_BLOCK = 128
#: ‖e‖² = ‖u − μ‖² − ‖c‖² is padded by this fraction of ‖u − μ‖² (float32 cancellation)
RESIDUAL_PAD = 1e-5
#: the exact path's float32 rounding of N_q and A, relative to n·(‖w‖ + 1) (a few float32 epsilons per
#: H-term dot product)
NUMERATOR_PAD = 4e-6
#: and of the margin itself: absolute, and relative to |m|
MARGIN_PAD = 1e-5
#: timesteps whose margins are computed together
MARGIN_BLOCK_TIMESTEPS = 8
#: columns of the scalars file
A_COL, NORM_COL, RESIDUAL_COL = range(3)


@dataclass
class PairSketch:
    """The sketch of every (t, g) pair (see the module docstring).

    Attributes:
        mean: (H,) float64 centre μ of the u's. basis: (H, r) float64 orthonormal V.
        coords: (T, N, r) float32 c (memory-mapped when stored). scalars: (T, N, 3) float32 A, n, ‖e‖.
        meta: version, rank, latents fingerprint, head hash.
    """

    mean: np.ndarray
    basis: np.ndarray
    coords: np.ndarray
    scalars: np.ndarray
    meta: dict

    @property
    def rank(self) -> int:
        return int(self.basis.shape[1])

    def margins(self, head: Any, query: torch.Tensor, scale: float, timesteps: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
        """Sketched margins and their radii at the given timesteps.

        Args:
            head: the :class:`~.head.RelevancyHead` the sketch was built from.
            query: (D,) unit query embedding. scale: the relevancy scale.
            timesteps: (S,) timesteps.
        Returns:
            margin (S, N) float32 and radius (S, N) float32 (inf where the pair must be scored exactly):
            the exact path's margin min_k scale·(q − c_k)·φ(z) of every pair lies in margin ± radius.
        """
        q = query.detach().to(torch.float64).cpu()
        w = (head.q64.cpu().T @ q).numpy()                            # (H,)
        const = float(q @ head.b_perp64.cpu()) + float(self.mean @ w)
        g = self.basis.T @ w                                           # (r,)
        w_perp = float(np.linalg.norm(w - self.basis @ g))
        pad = NUMERATOR_PAD * (float(np.linalg.norm(w)) + 1.0)
        g32 = torch.from_numpy(g.astype(np.float32))
        timesteps = np.asarray(timesteps, dtype=np.int64)
        S, N = len(timesteps), self.coords.shape[1]
        margin = np.empty((S, N), dtype=np.float32)
        radius = np.empty((S, N), dtype=np.float32)
        for i in range(0, S, MARGIN_BLOCK_TIMESTEPS):
            rows = timesteps[i:i + MARGIN_BLOCK_TIMESTEPS]
            coords = _rows_of(self.coords, rows)                                    # (s, N, r)
            sc = _rows_of(self.scalars, rows)                                       # (s, N, 3)
            numer = coords @ g32 + const - sc[..., A_COL]
            inv_norm = scale / sc[..., NORM_COL]
            m = numer * inv_norm
            rad = (sc[..., RESIDUAL_COL] * w_perp + pad * sc[..., NORM_COL]) * inv_norm
            rad += MARGIN_PAD * (1.0 + m.abs())
            margin[i:i + len(rows)] = m.numpy()
            radius[i:i + len(rows)] = torch.where(torch.isfinite(m) & torch.isfinite(rad), rad,
                                                  torch.tensor(np.inf)).numpy()
        return margin, radius


def _rows_of(array: np.ndarray, rows: np.ndarray) -> torch.Tensor:
    """``array[rows]`` as a tensor that is only read: consecutive rows are a view of the (memory-mapped)
    array, others a copy."""
    if rows.size and rows[-1] - rows[0] == rows.size - 1:  # sorted and distinct: consecutive
        with warnings.catch_warnings():  # a read-only mapping: torch warns that it cannot write to it
            warnings.simplefilter("ignore", UserWarning)
            return torch.from_numpy(np.asarray(array[int(rows[0]):int(rows[-1]) + 1]))
    return torch.from_numpy(np.array(array[rows]))


def head_key(head: Any, refs: torch.Tensor) -> str:
    """A hash of everything the sketch depends on besides the latents: the head's weights and the
    references."""
    digest = hashlib.sha256()
    tensors = [t for pair in head.hidden for t in pair] + [head.r64, head.beta64, head.q64, head.b_perp64, refs]
    for t in tensors:
        digest.update(np.ascontiguousarray(t.detach().cpu().double().numpy()).tobytes())
    return digest.hexdigest()[:32]


def _u_of(head: Any, latents: np.ndarray) -> torch.Tensor:
    """(M,d) latents -> (M,H) float32 u = R·h + β (non-finite latents count as 0, as on the exact path)."""
    h = torch.from_numpy(np.array(latents, dtype=np.float32))
    if not bool(torch.isfinite(h).all()):
        h = torch.nan_to_num(h, nan=0.0, posinf=0.0, neginf=0.0)
    for w, b in head.hidden:
        h = torch.addmm(b, h, w.T).clamp_min_(0.0)
    # u = h·Rᵀ + β with Rᵀ lower triangular: column block j of u needs only the rows of Rᵀ from j on
    r_t, H = head.r_t, int(head.r_t.shape[0])
    u = torch.empty(h.shape[0], H, dtype=torch.float32)
    for j in range(0, H, PROJECT_BLOCK):
        torch.addmm(head.beta[j:j + PROJECT_BLOCK], h[:, j:], r_t[j:, j:j + PROJECT_BLOCK], out=u[:, j:j + PROJECT_BLOCK])
    return u


def build_sketch(head: Any, refs: torch.Tensor, latents: Any, *, rank: int = DEFAULT_RANK,
                 out_dir: Optional[Path] = None, seed: int = 0,
                 on_progress: Optional[Callable[[float, str], None]] = None) -> PairSketch:
    """Sketch every pair of the (T, N, d) ``latents`` (memmap: streamed a timestep at a time).

    Args:
        head: the field's :class:`~.head.RelevancyHead`. refs: (K, D) unit reference embeddings.
        rank: the basis' rank (at most H, the head's width).
        out_dir: where to store the files (None: in memory).
        on_progress: ``(fraction, stage)`` after each timestep; an exception it raises stops the build
            with nothing stored.
    """
    report = on_progress or (lambda fraction, stage: None)
    T, N, d = (int(s) for s in latents.shape)
    H = int(head.beta64.shape[0])
    report(0.0, "sketch: fitting the basis")
    sample = sample_latents(latents, FIT_SAMPLES, seed) if T * N else torch.zeros(0, d)
    with torch.inference_mode():
        u_fit = _u_of(head, sample.numpy()).double() if sample.shape[0] else torch.zeros(0, H, dtype=torch.float64)
        u_fit = torch.nan_to_num(u_fit, nan=0.0, posinf=0.0, neginf=0.0)
        mean = u_fit.mean(0) if u_fit.shape[0] else torch.zeros(H, dtype=torch.float64)
        r = int(max(1, min(rank, H)))
        centred = u_fit - mean
        # the principal axes: eigenvectors of the (H,H) scatter, largest first
        _, vectors = torch.linalg.eigh(centred.T @ centred)
        basis = vectors.flip(1)[:, :r].contiguous()
    refs64 = refs.detach().cpu().double()
    ref_dirs = (head.q64.cpu().T @ refs64.T).float()                  # (H, K)
    ref_offsets = (refs64 @ head.b_perp64.cpu()).float()              # (K,)
    meta = {"version": SKETCH_VERSION, "rank": r, "latents": fingerprint(latents), "head": head_key(head, refs)}
    coords_path = scalars_path = None
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / f"sketch_{rank}.npz").unlink(missing_ok=True)
        coords_path, scalars_path = out_dir / f"sketch_coords_{rank}.npy", out_dir / f"sketch_scalars_{rank}.npy"
    consts = (mean.float(), basis.float(), ref_dirs, ref_offsets)
    blocks = list(range(0, N, BUILD_BLOCK_ROWS))
    workers = max(1, min(torch.get_num_threads(), len(blocks)))
    threads = torch.get_num_threads()
    with _array_file(coords_path, (T, N, r), np.float32) as coords, \
            _array_file(scalars_path, (T, N, 3), np.float32) as scalars, \
            ThreadPoolExecutor(workers, initializer=torch.set_num_threads, initargs=(1,)) as pool:
        # one block per worker thread, each on one torch thread (OpenMP's thread count is per thread: the
        # workers set their own): no barrier inside the small products
        torch.set_num_threads(1)
        try:
            for t in range(T):
                lat = latents[t]

                def fill(start: int, lat=lat, t=t) -> None:
                    c, block = _sketch_block(head, lat[start:start + BUILD_BLOCK_ROWS], consts)
                    coords[t, start:start + BUILD_BLOCK_ROWS] = c
                    scalars[t, start:start + BUILD_BLOCK_ROWS] = block

                list(pool.map(fill, blocks))
                report((t + 1) / T, f"sketch: {t + 1}/{T} timesteps")
        finally:
            torch.set_num_threads(threads)
    sketch = PairSketch(mean.numpy(), basis.numpy(), coords, scalars, meta)
    if out_dir is not None:
        with atomic_path(out_dir / f"sketch_{rank}.npz") as tmp:
            np.savez(tmp, mean=sketch.mean, basis=sketch.basis, meta=np.array(json.dumps(meta)))
        sketch.coords = load_npy(coords_path, mmap=True, field="sketch coords")
        sketch.scalars = load_npy(scalars_path, mmap=True, field="sketch scalars")
    return sketch


def _sketch_block(head: Any, latents: np.ndarray, consts: tuple) -> tuple[np.ndarray, np.ndarray]:
    """(M,d) latents -> their (M,r) coordinates and (M,3) scalars, float32 (see the module docstring)."""
    mean32, basis32, ref_dirs, ref_offsets = consts
    with torch.inference_mode():
        u = _u_of(head, latents)                                       # (M, H) float32
        centred = u - mean32
        c = centred @ basis32                                          # (M, r)
        spread = torch.linalg.vector_norm(centred, dim=1).square()
        residual = torch.sqrt((spread - torch.linalg.vector_norm(c, dim=1).square()).clamp_min(0.0)
                              + RESIDUAL_PAD * spread)
        a_max = torch.addmm(ref_offsets, u, ref_dirs).max(dim=1).values
        norm = torch.sqrt(torch.linalg.vector_norm(u, dim=1).square() + head.perp_sq).clamp_min(NORM_EPS)
        # a non-finite u makes the norm non-finite; the exact path's float32 overflows past F32_SAFE
        finite = torch.isfinite(norm) & torch.isfinite(a_max) & torch.isfinite(residual) & (norm < F32_SAFE ** 0.5)
        block = torch.stack([a_max, norm, residual], 1)
        if not bool(finite.all()):
            block[~finite] = torch.tensor([0.0, 1.0, np.inf])
            c[~finite] = 0.0
        return c.numpy(), block.numpy()


class _array_file:
    """An array to fill: in memory (``path`` None) or a ``.npy`` memmap written beside ``path`` and renamed
    onto it only when the block succeeds."""

    def __init__(self, path: Optional[Path], shape: tuple[int, ...], dtype: Any):
        self.path, self.shape, self.dtype = path, shape, dtype
        self._atomic = None

    def __enter__(self) -> np.ndarray:
        if self.path is None:
            self.array = np.zeros(self.shape, dtype=self.dtype)
            return self.array
        self._atomic = atomic_path(self.path)
        tmp = self._atomic.__enter__()
        self.array = np.lib.format.open_memmap(tmp, mode="w+", dtype=self.dtype, shape=self.shape)
        return self.array

    def __exit__(self, *exc) -> bool:
        if self._atomic is not None:
            self.array.flush()
            del self.array
            return bool(self._atomic.__exit__(*exc))
        return False


def load_sketch(out_dir: Path, rank: int, latents: Any, key: str) -> Optional[PairSketch]:
    """The stored sketch of rank ``rank`` for these latents and this head (``key``: :func:`head_key`), or None
    when missing or built from something else."""
    npz_path = Path(out_dir) / f"sketch_{rank}.npz"
    if not npz_path.is_file():
        return None
    try:
        with np.load(npz_path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            mean, basis = z["mean"], z["basis"]
    except (ValueError, KeyError, OSError, EOFError, MemoryError, zipfile.BadZipFile, json.JSONDecodeError) as exc:
        raise InputError(f"corrupt sketch ({type(exc).__name__}: {exc}); delete it to rebuild", file=npz_path) from None
    if not isinstance(meta, dict) or meta.get("version") != SKETCH_VERSION or meta.get("head") != key \
            or meta.get("latents") != fingerprint(latents):
        return None
    T, N = (int(s) for s in latents.shape[:2])
    r = int(meta.get("rank", -1))
    if basis.ndim != 2 or basis.shape[1] != r or mean.shape != (basis.shape[0],) \
            or not (np.isfinite(basis).all() and np.isfinite(mean).all()):
        raise InputError("corrupt sketch (basis and mean must be finite, (H, r) and (H,)); delete it to rebuild",
                         file=npz_path, field="basis")
    coords = load_npy(Path(out_dir) / f"sketch_coords_{rank}.npy", mmap=True, field="sketch coords")
    scalars = load_npy(Path(out_dir) / f"sketch_scalars_{rank}.npy", mmap=True, field="sketch scalars")
    if coords.shape != (T, N, r) or coords.dtype != np.float32 or scalars.shape != (T, N, 3) \
            or scalars.dtype != np.float32:
        raise InputError(f"corrupt sketch arrays (need ({T}, {N}, {r}) and ({T}, {N}, 3) float32); delete "
                         "them to rebuild", file=Path(out_dir) / f"sketch_coords_{rank}.npy", field="sketch")
    return PairSketch(mean, basis, coords, scalars, meta)


def ensure_sketch(head: Any, refs: torch.Tensor, latents: Any, out_dir: Optional[Path], rank: int = DEFAULT_RANK,
                  **kw) -> PairSketch:
    """Load the stored sketch for these latents and this head, or build (and store) it."""
    if out_dir is not None:
        sketch = load_sketch(out_dir, rank, latents, head_key(head, refs))
        if sketch is not None:
            return sketch
    return build_sketch(head, refs, latents, rank=rank, out_dir=out_dir, **kw)

