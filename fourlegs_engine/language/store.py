"""Per-timestep result files with a manifest that pins the configuration (resume, shard, check).

A stage (feature extraction, distillation) writes one ``.npy`` per timestep into its directory,
atomically (temp file + rename), so a killed process never leaves a half-written result and a
restarted one skips what is finished. ``manifest.json`` records the stage's configuration and its
hash; opening the store with a different configuration raises :class:`ConfigMismatchError` unless
``overwrite=True`` (then the old results are removed first). Independent workers (``--shard i/n``)
share one store: they write the identical manifest and disjoint timestep files.

A finished file is trusted only after it is verified (:meth:`StepStore.problem`): it opens, has the
stage's shape and dtype, holds no NaN or Inf, and matches the SHA-256 written beside it when it was saved
(``tNNNNNN.sha256``; one small file per timestep rather than an entry in the shared manifest, so
workers never rewrite each other's records). A file that fails is not skipped by a resume (it is
computed again) and never merged.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Optional, Sequence

import numpy as np

from ..errors import ConfigMismatchError, InputError
from ..fileio import load_npy, read_json, save_npy_atomic, write_bytes_atomic, write_json_atomic

MANIFEST = "manifest.json"
#: step files this process has verified (:meth:`StepStore.problem`): path -> what the verification holds
#: for; shared by every store object, so the per-unit steps of a field do not verify a file twice
_VERIFIED: dict[str, tuple] = {}
_STEP_FILE = re.compile(r"^t(\d{6})\.npy$")
ROWS_SUFFIX = ".rows.npy"
_ROWS_FILE = re.compile(r"^t(\d{6})\.rows\.npy$")
#: a timestep whose share of all-zero rows is at least this is stored without them
SPARSE_ZERO_SHARE = 0.25


def step_file_names(directory: Path, t: int) -> list[str]:
    """The names of timestep ``t``'s files in a store's ``directory``, the row index first (when the step
    was stored without its zero rows): writing them in this order leaves the timestep unfinished until
    its array is in place."""
    rows = Path(directory) / f"t{int(t):06d}{ROWS_SUFFIX}"
    return ([rows.name] if rows.is_file() else []) + [f"t{int(t):06d}.npy"]


def _nonzero_rows(array: np.ndarray) -> np.ndarray | None:
    """(K,) int64 indices of the rows of a 2-D or higher array that hold a non-zero value (None for 0-D/1-D)."""
    if array.ndim < 2 or array.shape[0] == 0:
        return None
    return np.flatnonzero(np.any(array.reshape(array.shape[0], -1) != 0, axis=1)).astype(np.int64)
_CHECKSUM_FILE = re.compile(r"^t(\d{6})\.sha256$")
#: rows checked for NaN/Inf at a time (bounds the memory of the check on large files)
_FINITE_CHUNK_BYTES = 64 << 20


def config_hash(config: dict[str, Any]) -> str:
    """Stable short hash of a JSON-serializable configuration."""
    text = json.dumps(config, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]


def parse_timesteps(spec: str | None, num_timesteps: int, field: str = "--timesteps") -> list[int]:
    """``None``/``""`` -> all; ``"a:b"`` -> a..b-1 (python slice, negatives allowed); ``"a,b,c"`` -> list;
    ``"a:b:s"`` -> with step s. ``field`` names the option in an InputError."""
    if not spec:
        return list(range(num_timesteps))
    spec = spec.strip()
    try:
        if ":" in spec:
            parts = [int(p) if p.strip() else None for p in spec.split(":")]
            if len(parts) > 3:
                raise ValueError
            steps = list(range(num_timesteps))[slice(*parts)]
        else:
            steps = sorted({int(p) for p in spec.split(",") if p.strip()})
    except ValueError:
        raise InputError(f"cannot parse {spec!r}; use a:b, a:b:step or a,b,c", field=field) from None
    bad = [t for t in steps if not 0 <= t < num_timesteps]
    if bad:
        raise InputError(f"timestep {bad[0]} is out of range 0..{num_timesteps - 1}", field=field)
    if not steps:
        raise InputError(f"{spec!r} selects no timestep of 0..{num_timesteps - 1}", field=field)
    return steps


def parse_shard(spec: str | None) -> tuple[int, int]:
    """``"i/n"`` -> (i, n) with 0 <= i < n; ``None`` -> (0, 1)."""
    if not spec:
        return 0, 1
    m = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", spec)
    if not m or int(m.group(2)) < 1 or int(m.group(1)) >= int(m.group(2)):
        raise InputError(f"cannot parse {spec!r}; use i/n with 0 <= i < n (e.g. 0/4)", field="--shard")
    return int(m.group(1)), int(m.group(2))


def select_timesteps(num_timesteps: int, timesteps: str | Sequence[int] | None = None,
                     shard: str | tuple[int, int] | None = None) -> list[int]:
    """The timesteps one worker handles: the ``timesteps`` selection, then every n-th from index i."""
    steps = (parse_timesteps(timesteps, num_timesteps) if timesteps is None or isinstance(timesteps, str)
             else [int(t) for t in timesteps])
    i, n = parse_shard(shard) if shard is None or isinstance(shard, str) else shard
    return steps[i::n]


@dataclass
class StepStore:
    """A directory of per-timestep arrays ``tNNNNNN.npy`` under one pinned configuration."""

    root: Path
    stage: str
    config: dict[str, Any]
    num_timesteps: int
    #: the shape of timestep t's array (None: any shape) and the dtype every file must have (None: any)
    shape_of: Optional[Callable[[int], tuple[int, ...]]] = None
    dtype: Optional[str] = None

    @property
    def hash(self) -> str:
        return config_hash(self.config)

    @property
    def manifest_path(self) -> Path:
        return self.root / MANIFEST

    def step_path(self, t: int) -> Path:
        return self.root / f"t{int(t):06d}.npy"

    def rows_path(self, t: int) -> Path:
        """Where a timestep stored without its all-zero rows keeps [number of rows, kept row indices...]."""
        return self.root / f"t{int(t):06d}{ROWS_SUFFIX}"

    def step_file_names(self, t: int) -> list[str]:
        """The names (in the store's directory) of timestep ``t``'s files (see :func:`step_file_names`)."""
        return step_file_names(self.root, t)

    def checksum_path(self, t: int) -> Path:
        return self.root / f"t{int(t):06d}.sha256"

    # -------------------------------------------------------------------------- opening
    def open(self, *, overwrite: bool = False) -> "StepStore":
        """Create the store or check that the existing one has this configuration.

        Raises:
            ConfigMismatchError: results of another configuration exist and ``overwrite`` is False.
        """
        existing = self.read_manifest()
        if existing is not None and existing.get("config_hash") != self.hash:
            if not overwrite:
                raise ConfigMismatchError(
                    f"{self.root}: existing {self.stage} results were made with another configuration "
                    f"(hash {existing.get('config_hash')}, now {self.hash}; changed: "
                    f"{', '.join(_changed_keys(existing.get('config', {}), self.config)) or 'unknown'}). "
                    "Pass --overwrite to discard them, or use the same settings to resume.")
            self.clear()
        if existing is None or existing.get("config_hash") != self.hash:
            self.root.mkdir(parents=True, exist_ok=True)
            write_json_atomic(self.manifest_path, {"stage": self.stage, "config_hash": self.hash,
                                                   "num_timesteps": self.num_timesteps, "config": self.config})
        return self

    def read_manifest(self) -> dict[str, Any] | None:
        if not self.manifest_path.is_file():
            return None
        meta = read_json(self.manifest_path)
        if not isinstance(meta, dict):
            raise InputError("manifest must be a JSON object", file=self.manifest_path)
        return meta

    def clear(self) -> None:
        """Remove all timestep files and the manifest."""
        if not self.root.is_dir():
            return
        for p in self.root.iterdir():
            if _STEP_FILE.match(p.name) or _ROWS_FILE.match(p.name) or _CHECKSUM_FILE.match(p.name) \
                    or p.name == MANIFEST \
                    or p.name.endswith(".part.npy"):
                p.unlink()

    # ---------------------------------------------------------------------- per timestep
    def is_done(self, t: int) -> bool:
        """Whether timestep t's file is there and passes :meth:`problem` (a resume skips only those)."""
        return self.step_path(t).is_file() and self.problem(t) is None

    def save(self, t: int, array: np.ndarray) -> None:
        """Store timestep ``t``, then its checksum; an array whose rows are mostly all-zero (views without
        evidence) is stored as its other rows plus their indices, so those views cost no disk."""
        array = np.asarray(array)
        path, rows_path = self.step_path(t), self.rows_path(t)
        self.checksum_path(t).unlink(missing_ok=True)
        path.unlink(missing_ok=True)  # unfinished while its files change
        kept = _nonzero_rows(array)
        if kept is not None and kept.size <= (1.0 - SPARSE_ZERO_SHARE) * array.shape[0]:
            save_npy_atomic(rows_path, np.concatenate([[array.shape[0]], kept]).astype(np.int64))
            save_npy_atomic(path, np.ascontiguousarray(array[kept]))
        else:
            rows_path.unlink(missing_ok=True)
            save_npy_atomic(path, np.ascontiguousarray(array))
        write_bytes_atomic(self.checksum_path(t), (self.files_sha256(t) + "\n").encode())
        _VERIFIED.pop(str(self.step_path(t)), None)

    def load(self, t: int, *, mmap: bool = True) -> np.ndarray:
        """Timestep ``t``'s array (memory-mapped when stored whole; rebuilt with its zero rows otherwise)."""
        field = f"{self.stage} timestep {t}"
        stored = load_npy(self.step_path(t), mmap=mmap, field=field)
        rows_path = self.rows_path(t)
        if not rows_path.is_file():
            return stored
        rows = load_npy(rows_path, mmap=False, field=field)
        if rows.ndim != 1 or rows.dtype.kind not in "iu" or rows.size != stored.shape[0] + 1 or rows.size == 0:
            raise InputError(f"row index does not match the stored rows ({rows.size} entries for "
                             f"{stored.shape[0]} rows)", file=rows_path, field=field)
        total, kept = int(rows[0]), rows[1:]
        if kept.size and (kept.min() < 0 or kept.max() >= total or np.any(np.diff(kept) <= 0)):
            raise InputError(f"row indices must be increasing and below {total}", file=rows_path, field=field)
        dense = np.zeros((total,) + tuple(stored.shape[1:]), dtype=stored.dtype)
        dense[kept] = stored
        return dense

    def files_sha256(self, t: int) -> str:
        """Hex SHA-256 of timestep ``t``'s files, in :meth:`step_file_names` order (the row index, if any,
        then the array)."""
        digest = hashlib.sha256()
        for name in self.step_file_names(t):
            with open(self.root / name, "rb") as fh:
                for block in iter(lambda: fh.read(1 << 20), b""):
                    digest.update(block)
        return digest.hexdigest()

    def load_verified(self, t: int, *, mmap: bool = True) -> np.ndarray:
        """Timestep t's array after :meth:`problem`; InputError naming the file when it fails."""
        problem = self.problem(t)
        if problem is not None:
            raise InputError(f"{problem}; run the {self.stage} stage again to recompute it",
                             file=self.step_path(t), field=f"{self.stage} timestep {t}")
        return self.load(t, mmap=mmap)

    def problem(self, t: int) -> str | None:
        """Why timestep t's file cannot be trusted (None when it can): missing, unreadable, another shape
        or dtype than the stage's, NaN or Inf values, or bytes that differ from its recorded checksum."""
        path = self.step_path(t)
        try:
            stat = path.stat()
        except OSError:
            return "file is missing"
        verified_as = self._verification_key(t, stat)
        if _VERIFIED.get(str(path)) == verified_as:
            return None
        try:
            arr = self.load(t)
        except InputError as exc:
            return exc.problem
        if self.shape_of is not None and tuple(arr.shape) != tuple(self.shape_of(int(t))):
            return f"has shape {tuple(arr.shape)}, expected {tuple(self.shape_of(int(t)))}"
        if self.dtype is not None and arr.dtype != np.dtype(self.dtype):
            return f"has dtype {arr.dtype}, expected {np.dtype(self.dtype)}"
        if arr.dtype.kind not in "fiub":
            return f"has dtype {arr.dtype}, expected numbers"
        if arr.dtype.kind == "f" and not _all_finite(arr):
            return "contains NaN or Inf values"
        recorded = self.checksum_path(t)
        if recorded.is_file():
            try:
                expected = recorded.read_text(encoding="ascii").strip()
            except (OSError, UnicodeDecodeError):
                expected = ""
            if self.files_sha256(t) != expected:
                return "its bytes differ from the checksum recorded when it was written (damaged)"
        _VERIFIED[str(path)] = verified_as
        return None

    def _verification_key(self, t: int, stat: os.stat_result) -> tuple:
        """What a verification of timestep t's files holds for: the files as they are now (identity, size,
        modification time: the row index's and the checksum's too) and the shape and dtype expected."""
        def identity(path: Path) -> tuple:
            try:
                st = path.stat()
            except OSError:
                return ()
            return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)
        return ((stat.st_dev, stat.st_ino, stat.st_size, stat.st_mtime_ns), identity(self.rows_path(t)),
                identity(self.checksum_path(t)), None if self.shape_of is None else tuple(self.shape_of(int(t))),
                self.dtype)

    def done(self) -> list[int]:
        if not self.root.is_dir():
            return []
        out = []
        for p in self.root.iterdir():
            m = _STEP_FILE.match(p.name)
            if m and int(m.group(1)) < self.num_timesteps:
                out.append(int(m.group(1)))
        return sorted(out)

    def missing(self, timesteps: Iterable[int] | None = None) -> list[int]:
        steps = range(self.num_timesteps) if timesteps is None else timesteps
        return [t for t in steps if not self.is_done(t)]

    def check(self, expected_shape: tuple[int, ...] | None = None) -> dict[str, Any]:
        """Verify every finished file (:meth:`problem`; ``expected_shape`` overrides the stage's shape) and
        report missing/bad timesteps."""
        if expected_shape is not None:
            self.shape_of = lambda t: tuple(expected_shape)
        bad: list[dict[str, Any]] = []
        for t in self.done():
            problem = self.problem(t)
            if problem is not None:
                bad.append({"t": t, "problem": f"{self.step_path(t)}: {problem}"})
        done = self.done()
        bad_steps = {b["t"] for b in bad}
        missing = [t for t in range(self.num_timesteps) if t not in done]
        return {"stage": self.stage, "root": str(self.root), "config_hash": self.hash,
                "num_timesteps": self.num_timesteps, "done": len(done) - len(bad_steps),
                "missing": missing, "bad": bad, "complete": not missing and not bad}


def _all_finite(arr: np.ndarray) -> bool:
    flat = arr.reshape(-1) if arr.ndim else arr.reshape(1)
    step = max(1, _FINITE_CHUNK_BYTES // max(arr.dtype.itemsize, 1))
    return all(bool(np.isfinite(flat[i:i + step]).all()) for i in range(0, flat.shape[0], step))


def _changed_keys(old: dict[str, Any], new: dict[str, Any]) -> list[str]:
    keys = sorted(set(old) | set(new))
    return [k for k in keys if old.get(k) != new.get(k)]


def format_ranges(steps: Sequence[int]) -> str:
    """[0,1,2,5,7,8] -> '0-2, 5, 7-8' (for messages)."""
    out: list[str] = []
    steps = sorted(steps)
    i = 0
    while i < len(steps):
        j = i
        while j + 1 < len(steps) and steps[j + 1] == steps[j] + 1:
            j += 1
        out.append(str(steps[i]) if i == j else f"{steps[i]}-{steps[j]}")
        i = j + 1
    return ", ".join(out)
