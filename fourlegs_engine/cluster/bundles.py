"""The bundle as Ray tasks see it: on a shared filesystem (checked per task), or shipped through Ray's
object store into a node-local copy whose finished result files travel back to the driver.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence

from ..errors import InputError
from .runner import RayOptions

if TYPE_CHECKING:
    from ..scene.scene import Scene

#: top-level bundle entries that are stage outputs, never shipped to workers as inputs
OUTPUT_DIRS = ("features", "language", "bench")


@dataclass
class BundleRef:
    """How a task finds the bundle: its path and identity, or (no shared filesystem) its files."""

    path: str
    scene_json_sha: str
    snapshot: Any = None          # ObjectRef of {relative path: bytes}; None on a shared filesystem
    snapshot_digest: str = ""

    @property
    def shared(self) -> bool:
        return self.snapshot is None


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def bundle_ref(ray: Any, root: Path, options: RayOptions, extra: Sequence[str] = ()) -> BundleRef:
    """The bundle as tasks see it; without a shared filesystem its input files (everything but the
    stage outputs, plus ``extra`` relative paths) are put into the object store once."""
    root = Path(root).resolve()
    sha = _sha((root / "scene.json").read_bytes())
    if options.shared_fs:
        return BundleRef(str(root), sha)
    files: dict[str, bytes] = {}
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root)
        if not p.is_file() or rel.parts[0] in OUTPUT_DIRS or any(part.startswith(".") for part in rel.parts):
            continue
        files[rel.as_posix()] = p.read_bytes()
    for rel in extra:
        files[rel] = (root / rel).read_bytes()
    digest = hashlib.sha256()
    for rel, data in files.items():
        digest.update(rel.encode() + b"\0" + hashlib.sha256(data).digest())
    return BundleRef(str(root), sha, ray.put(files), digest.hexdigest()[:24])


def _task_bundle(ref: BundleRef, payload: dict[str, bytes] | None = None) -> Path:
    """The bundle directory inside a task: the shared one (checked), or a node-local copy."""
    if ref.shared:
        root = Path(ref.path)
        scene_json = root / "scene.json"
        if not scene_json.is_file() or _sha(scene_json.read_bytes()) != ref.scene_json_sha:
            import socket
            raise InputError(f"the bundle is not visible (or differs) on node {socket.gethostname()}; put it on a "
                             "filesystem every node mounts at the same path, or run with --ray-no-shared-fs",
                             file=root)
        return root
    import ray
    from ..fileio import write_bytes_atomic
    root = _snapshot_dir(ref.snapshot_digest) / "bundle"
    if not (root / "scene.json").is_file():
        files = ray.get(ref.snapshot)
        root.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=".bundle.", suffix=".part", dir=root.parent))
        try:
            for rel, data in files.items():
                (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
                (tmp / rel).write_bytes(data)
            tmp.rename(root)          # never replaces a copy another worker of this node finished first
        except OSError:
            if not (root / "scene.json").is_file():
                raise
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    for rel, data in (payload or {}).items():
        write_bytes_atomic(root / rel, data)
    return root


def _snapshot_dir(digest: str) -> Path:
    return Path(tempfile.gettempdir()) / "fourlegs-cluster" / digest


def _remove_snapshot(digest: str) -> None:
    shutil.rmtree(_snapshot_dir(digest), ignore_errors=True)


def release_bundle(ray: Any, ref: BundleRef) -> None:
    """Remove the node-local copies of a ``shared_fs=False`` bundle: one small task pinned to each node."""
    if ref.shared:
        return
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy
    remote = ray.remote(_remove_snapshot)
    try:
        refs = [remote.options(num_cpus=0, scheduling_strategy=NodeAffinitySchedulingStrategy(node["NodeID"], soft=True))
                .remote(ref.snapshot_digest) for node in ray.nodes() if node.get("Alive")]
        ray.get(refs, timeout=60)
    except Exception:  # noqa: BLE001 - best effort: temporary files on a node that may be gone
        pass


_WORKER_CACHE: dict[str, Any] = {}


def cached(key: str, build: Callable[[], Any]) -> Any:
    """Per worker process: the scene and encoder of the current run (workers outlive tasks)."""
    if key not in _WORKER_CACHE:
        if len(_WORKER_CACHE) > 4:
            _WORKER_CACHE.clear()
        _WORKER_CACHE[key] = build()
    return _WORKER_CACHE[key]


def task_scene(ref: BundleRef, run_id: str, payload: dict[str, bytes] | None = None) -> "Scene":
    """The scene inside a task (loaded once per worker process and run)."""
    from ..scene.bundle import load_bundle
    root = _task_bundle(ref, payload)
    return cached(f"{run_id}:scene:{root}", lambda: load_bundle(root))


def take_files(scene_root: Path, rels: Sequence[str]) -> dict[str, bytes]:
    """Bytes of finished result files of a node-local copy, removed from it afterwards."""
    out = {}
    for rel in rels:
        p = scene_root / rel
        out[rel] = p.read_bytes()
        p.unlink()
    return out


def write_results(root: Path, files: dict[str, bytes]) -> None:
    """Driver side of ``shared_fs=False``: the returned files, each written atomically (fsync'd)."""
    from ..fileio import atomic_path
    for rel, data in files.items():
        with atomic_path(root / rel) as tmp:
            with open(tmp, "wb") as fh:
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())


def gpus_for(options: RayOptions, ray: Any, device: str | None) -> float:
    """GPUs each task declares: the option, else 1 for a CUDA encoder device (or "auto" on a GPU cluster)."""
    if options.num_gpus is not None:
        return float(options.num_gpus)
    device = (device or "auto").lower()
    if device.startswith("cuda"):
        return 1.0
    if device == "auto" and ray.cluster_resources().get("GPU", 0.0) > 0:
        return 1.0
    return 0.0


