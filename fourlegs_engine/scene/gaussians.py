"""The in-memory dynamic Gaussian scene: T timesteps x N Gaussians.

Arrays are numpy (possibly memory-mapped); ``GaussianSequence.at(t)`` converts one timestep to torch.
Conventions: quaternions are (w, x, y, z); scales are stored as logs; opacity as logits; colours are
linear RGB in [0, 1] (or SH coefficients, Inria layout, evaluated per camera by the renderer).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Optional

import numpy as np

from ..errors import InputError

SH_C0 = 0.28209479177387814
QUAT_ZERO_TOL = 1e-12

if TYPE_CHECKING:  # torch is imported where tensors are made: opening and viewing a scene does not need it
    import torch


def sh_dc_to_rgb(f_dc: np.ndarray) -> np.ndarray:
    """Inria 3DGS DC coefficient -> RGB: ``0.5 + C0 * f_dc``."""
    return 0.5 + SH_C0 * np.asarray(f_dc)


def rgb_to_sh_dc(rgb: np.ndarray) -> np.ndarray:
    return (np.asarray(rgb) - 0.5) / SH_C0


def normalize_quaternions(q: np.ndarray, *, file: str | None = None, field: str = "rotations") -> np.ndarray:
    """Return unit quaternions (..., 4) in float32.

    Raises :class:`InputError` on a zero-length quaternion (the rotation is undefined); warns once
    when the input was not normalized (a recoverable issue, fixed here).
    """
    q64 = np.asarray(q, dtype=np.float64)
    norms = np.linalg.norm(q64, axis=-1, keepdims=True)
    bad = norms[..., 0] <= QUAT_ZERO_TOL
    if np.any(bad):
        idx = np.argwhere(bad)[0].tolist()
        raise InputError(f"zero-length quaternion at index {idx}; the rotation is undefined",
                         file=file, field=field)
    if np.abs(norms - 1.0).max() > 1e-3:
        warnings.warn(f"{file + ': ' if file else ''}{field}: quaternions were not unit length; normalized",
                      stacklevel=2)
    return (q64 / norms).astype(np.float32)


def quaternion_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """(…,4) quaternions w,x,y,z (any norm > 0) -> (…,3,3) rotation matrices."""
    import torch

    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(q.shape[:-1] + (3, 3))


@dataclass
class GaussianFrame:
    """One timestep's Gaussians as tensors on one device.

    Attributes:
        means: (N,3) world positions.
        rotations: (N,4) unit quaternions w,x,y,z.
        log_scales: (N,3).
        opacity_logits: (N,).
        colors: (N,3) RGB, or None when the scene has SH only (then ``sh`` is set).
        sh: (N,K,3) SH coefficients (K = (deg+1)^2), or None.
        latents: (N,d) language latents of this timestep, or None.
        foreground: (N,) bool, or None.
    """

    means: torch.Tensor
    rotations: torch.Tensor
    log_scales: torch.Tensor
    opacity_logits: torch.Tensor
    colors: Optional[torch.Tensor] = None
    sh: Optional[torch.Tensor] = None
    latents: Optional[torch.Tensor] = None
    foreground: Optional[torch.Tensor] = None

    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])


@dataclass
class GaussianSequence:
    """Dynamic Gaussians: T timesteps x N Gaussians (N constant over time).

    Attributes:
        means: (T,N,3) float32.
        rotations: (T,N,4) float32 unit quaternions (w,x,y,z).
        log_scales: (N,3) static or (T,N,3) per timestep.
        opacity_logits: (N,).
        colors: (T,N,3) or (N,3) RGB in [0,1], or None if ``sh`` is given.
        sh: (N,K,3) or (T,N,K,3) SH coefficients, Inria order (DC first), or None.
        foreground: (N,) bool or None.
        latents: (T,N,d) array-like (np.memmap, never loaded whole) or None.
        labels: (T,N) int32 ground-truth labels (synthetic scenes; -1 = none) or None.
    """

    means: np.ndarray
    rotations: np.ndarray
    log_scales: np.ndarray
    opacity_logits: np.ndarray
    colors: Optional[np.ndarray] = None
    sh: Optional[np.ndarray] = None
    foreground: Optional[np.ndarray] = None
    latents: Optional[Any] = None
    labels: Optional[np.ndarray] = None
    source: str | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        self.validate()

    # ------------------------------------------------------------------ shape
    @property
    def num_timesteps(self) -> int:
        return int(self.means.shape[0])

    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[1])

    @property
    def latent_dim(self) -> int | None:
        return None if self.latents is None else int(self.latents.shape[-1])

    def validate(self) -> "GaussianSequence":
        """Check shapes, dtypes and finiteness; raise :class:`InputError` naming the field."""
        f = self.source
        means = self.means
        if means.ndim != 3 or means.shape[2] != 3:
            raise InputError(f"has shape {means.shape}, expected (T,N,3)", file=f, field="means")
        T, N = means.shape[:2]
        if T < 1:
            raise InputError("needs at least one timestep", file=f, field="means")

        def check(name: str, arr: Any, shapes: list[tuple], *, finite: bool = True) -> None:
            if arr is None:
                return
            if arr.dtype.hasobject:
                raise InputError("object arrays are refused", file=f, field=name)
            if tuple(arr.shape) not in [tuple(s) for s in shapes]:
                exp = " or ".join(str(tuple("T" if d == T and i == 0 and len(s) > 2 else d for i, d in enumerate(s)))
                                  for s in shapes)
                raise InputError(f"has shape {tuple(arr.shape)}, expected {exp} (T={T}, N={N})",
                                 file=f, field=name)
            if finite and np.issubdtype(arr.dtype, np.floating) and arr.size and not _all_finite(arr):
                raise InputError("contains NaN or Inf", file=f, field=name)

        for name in ("means", "rotations", "log_scales", "opacity_logits", "colors", "sh"):
            arr = getattr(self, name)
            if arr is not None and not np.issubdtype(np.asarray(arr).dtype, np.floating):
                raise InputError(f"has dtype {np.asarray(arr).dtype}, expected a float type", file=f, field=name)
        check("means", means, [(T, N, 3)])
        check("rotations", self.rotations, [(T, N, 4)])
        check("log_scales", self.log_scales, [(N, 3), (T, N, 3)])
        check("opacity_logits", self.opacity_logits, [(N,)])
        check("colors", self.colors, [(T, N, 3), (N, 3)])
        if self.sh is not None:
            if self.sh.ndim not in (3, 4) or self.sh.shape[-1] != 3 or self.sh.shape[-2] not in (1, 4, 9, 16):
                raise InputError(f"has shape {self.sh.shape}, expected (N,K,3) or (T,N,K,3) with K in 1,4,9,16",
                                 file=f, field="sh")
            check("sh", self.sh, [(N,) + self.sh.shape[-2:], (T, N) + self.sh.shape[-2:]])
        if self.colors is None and self.sh is None:
            raise InputError("neither colors nor SH coefficients are present", file=f, field="colors")
        if self.foreground is not None:
            check("foreground", self.foreground, [(N,)], finite=False)
        if self.labels is not None:
            check("labels", self.labels, [(T, N)], finite=False)
        if self.latents is not None:
            if len(self.latents.shape) != 3 or tuple(self.latents.shape[:2]) != (T, N):
                raise InputError(f"has shape {tuple(self.latents.shape)}, expected (T={T},N={N},d)",
                                 file=f, field="latents")
        if N and T and np.any(np.linalg.norm(np.asarray(self.rotations[0], dtype=np.float64), axis=-1) <= QUAT_ZERO_TOL):
            raise InputError("zero-length quaternion; the rotation is undefined", file=f, field="rotations")
        return self

    def check_timestep(self, t: int) -> int:
        if not isinstance(t, (int, np.integer)) or not 0 <= int(t) < self.num_timesteps:
            raise InputError(f"timestep {t} is out of range 0..{self.num_timesteps - 1}", file=self.source,
                             field="t")
        return int(t)

    # ---------------------------------------------------------------- access
    def at(self, t: int, device: str | torch.device = "cpu", dtype: Optional[torch.dtype] = None,
           *, with_latents: bool = False) -> GaussianFrame:
        """One timestep's tensors (``dtype`` default float32). Latents (memory-mapped) are read only if
        ``with_latents``."""
        import torch

        dtype = torch.float32 if dtype is None else dtype
        t = self.check_timestep(t)

        def tens(a: Any) -> Optional[torch.Tensor]:
            if a is None:
                return None
            arr = np.ascontiguousarray(a)
            if not arr.flags.writeable:  # read-only memory map: torch must not alias it
                arr = arr.copy()
            return torch.as_tensor(arr, dtype=dtype, device=device)

        def pick(a: Any, static_ndim: int) -> Any:
            if a is None:
                return None
            return a[t] if a.ndim > static_ndim else a

        return GaussianFrame(
            means=tens(self.means[t]),
            rotations=tens(self.rotations[t]),
            log_scales=tens(pick(self.log_scales, 2)),
            opacity_logits=tens(self.opacity_logits),
            colors=tens(pick(self.colors, 2)),
            sh=tens(pick(self.sh, 3)),
            latents=tens(self.latents[t]) if (with_latents and self.latents is not None) else None,
            foreground=None if self.foreground is None else torch.as_tensor(
                np.array(self.foreground, dtype=bool), device=device),
        )

    def rgb(self, t: int) -> np.ndarray:
        """(N,3) RGB of timestep t (from colours, else from the SH DC term)."""
        t = self.check_timestep(t)
        if self.colors is not None:
            return np.asarray(self.colors[t] if self.colors.ndim == 3 else self.colors)
        sh = self.sh[t] if self.sh.ndim == 4 else self.sh
        return np.clip(sh_dc_to_rgb(sh[:, 0, :]), 0.0, 1.0)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds over all timesteps: (min (3,), max (3,)). Empty scene -> zeros."""
        if self.num_gaussians == 0:
            return np.zeros(3), np.zeros(3)
        lo = np.full(3, np.inf)
        hi = np.full(3, -np.inf)
        for t in range(self.num_timesteps):
            m = np.asarray(self.means[t])
            lo = np.minimum(lo, m.min(0))
            hi = np.maximum(hi, m.max(0))
        return lo, hi

    def nbytes(self) -> dict[str, int]:
        """Bytes of each array (latents counted at their on-disk size, not loaded)."""
        out = {}
        for name in ("means", "rotations", "log_scales", "opacity_logits", "colors", "sh", "foreground",
                     "latents", "labels"):
            a = getattr(self, name)
            if a is not None:
                out[name] = int(np.prod(a.shape)) * np.dtype(a.dtype).itemsize
        return out


def quaternions_need_normalizing(q: Any, tol: float = 1e-3) -> bool:
    """True if any quaternion of (…,4) ``q`` is off unit length by more than ``tol`` (or zero).

    Checks one leading slice at a time, so a memory-mapped (T,N,4) array is never copied whole. The
    squared norms are compared with (1 ± tol)² in float32 (its rounding, ~1e-7, is far below ``tol``);
    a square that overflows is not finite and so counts as needing normalizing."""
    if q.ndim < 2:
        q = q.reshape(1, -1)
    if q.shape[0] == 0:
        return False
    lo, hi = (1.0 - tol) ** 2, (1.0 + tol) ** 2
    release_every = max(1, RELEASE_BYTES // max(1, q[0].nbytes))
    for i in range(q.shape[0]):
        if i % release_every == release_every - 1:
            release_mapped_pages(q)
        block = np.asarray(q[i], dtype=np.float32).reshape(-1, 4)
        if not block.size:
            continue
        with np.errstate(over="ignore", invalid="ignore"):
            squared = np.einsum("ij,ij->i", block, block)
        if not (np.isfinite(squared).all() and lo <= squared.min() and squared.max() <= hi):
            return True
    return False


RELEASE_BYTES = 1 << 25  # whole-file checks of a memory map unmap what they read about every 32 MB


def release_mapped_pages(arr: Any) -> None:
    """Unmap the resident pages of a read-only memory-mapped array from this process (they stay in the
    OS file cache and are read back on the next access), so validating a whole (T,N,·) file does not
    leave it all in the process's resident memory. No-op for other arrays or where unsupported."""
    import mmap

    mapped = getattr(arr, "_mmap", None)
    if isinstance(mapped, mmap.mmap) and hasattr(mmap, "MADV_DONTNEED") and getattr(arr, "mode", None) == "r":
        try:
            mapped.madvise(mmap.MADV_DONTNEED)
        except (OSError, ValueError):
            pass


def _all_finite(arr: np.ndarray, chunk: int = 1 << 22) -> bool:
    """Whether every value is finite, checked in slabs of about ``chunk`` values along the first axis
    (no copy of a memmap or a broadcast view is ever made whole)."""
    if arr.ndim == 0:
        return bool(np.isfinite(arr))
    rows = max(1, chunk // max(1, int(np.prod(arr.shape[1:]))))
    for s in range(0, arr.shape[0], rows):
        if not np.isfinite(arr[s:s + rows]).all():
            return False
        release_mapped_pages(arr)
    return True


def normalize_quaternions_chunked(q: Any, *, file: str | None = None, field: str = "rotations",
                                  chunk: int = 1 << 20) -> np.ndarray:
    """Like :func:`normalize_quaternions` for large (…,4) arrays (e.g. memory-mapped (T,N,4)).

    Works on ``chunk`` rows at a time in float64 (peak memory ~ the float32 result), raises
    :class:`InputError` on a zero-length quaternion naming its full index, and warns once if any
    quaternion was not unit length. Returns float32 (…,4).
    """
    shape = tuple(q.shape)
    if len(shape) < 1 or shape[-1] != 4:
        raise InputError(f"has shape {shape}, expected (...,4)", file=file, field=field)
    flat = q.reshape(-1, 4)
    out = np.empty(flat.shape, np.float32)
    unnormalized = False
    for s in range(0, flat.shape[0], chunk):
        block = np.asarray(flat[s:s + chunk], dtype=np.float64)
        norms = np.linalg.norm(block, axis=1, keepdims=True)
        zero = norms[:, 0] <= QUAT_ZERO_TOL
        if zero.any():
            idx = [int(i) for i in np.unravel_index(s + int(np.argmax(zero)), shape[:-1])]
            raise InputError(f"zero-length quaternion at index {idx}; the rotation is undefined",
                             file=file, field=field)
        unnormalized |= bool(np.abs(norms - 1.0).max() > 1e-3)
        out[s:s + chunk] = block / norms
    if unnormalized:
        warnings.warn(f"{file + ': ' if file else ''}{field}: quaternions were not unit length; normalized",
                      stacklevel=2)
    return out.reshape(shape)
