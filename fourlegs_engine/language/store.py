"""Per-timestep result files with a manifest that pins the configuration (resume, shard, check).

A stage (feature extraction, distillation) writes one ``.npy`` per timestep into its directory,
atomically (temp file + rename), so a killed process never leaves a half-written result and a
restarted one skips what is finished. ``manifest.json`` records the stage's configuration and its
hash; opening the store with a different configuration raises :class:`ConfigMismatchError` unless
``overwrite=True`` (then the old results are removed first). Independent workers (``--shard i/n``)
share one store: they write the identical manifest and disjoint timestep files.
"""
from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from ..errors import ConfigMismatchError, InputError
from ..fileio import load_npy, read_json, save_npy_atomic, write_json_atomic

MANIFEST = "manifest.json"
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
            if _STEP_FILE.match(p.name) or _ROWS_FILE.match(p.name) or p.name == MANIFEST \
                    or p.name.endswith(".part.npy"):
                p.unlink()

    # ---------------------------------------------------------------------- per timestep
    def is_done(self, t: int) -> bool:
        return self.step_path(t).is_file()

    def save(self, t: int, array: np.ndarray) -> None:
        """Store timestep ``t``; an array whose rows are mostly all-zero (views without evidence) is stored
        as its other rows plus their indices, so those views cost no disk."""
        array = np.asarray(array)
        path, rows_path = self.step_path(t), self.rows_path(t)
        path.unlink(missing_ok=True)  # unfinished while its files change
        kept = _nonzero_rows(array)
        if kept is not None and kept.size <= (1.0 - SPARSE_ZERO_SHARE) * array.shape[0]:
            save_npy_atomic(rows_path, np.concatenate([[array.shape[0]], kept]).astype(np.int64))
            save_npy_atomic(path, np.ascontiguousarray(array[kept]))
        else:
            rows_path.unlink(missing_ok=True)
            save_npy_atomic(path, array)

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
        """Verify every finished file opens and has ``expected_shape``; report missing/bad timesteps."""
        bad: list[dict[str, Any]] = []
        for t in self.done():
            try:
                arr = self.load(t)
                if expected_shape is not None and tuple(arr.shape) != tuple(expected_shape):
                    bad.append({"t": t, "problem": f"shape {tuple(arr.shape)}, expected {tuple(expected_shape)}"})
            except InputError as exc:
                bad.append({"t": t, "problem": str(exc)})
        missing = self.missing()
        return {"stage": self.stage, "root": str(self.root), "config_hash": self.hash,
                "num_timesteps": self.num_timesteps, "done": len(self.done()) - len(bad),
                "missing": missing, "bad": bad, "complete": not missing and not bad}


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
