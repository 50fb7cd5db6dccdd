"""Preprocessing on a Ray cluster: feature extraction and distillation as Ray tasks.

The work is split at the grain of the per-timestep result files the stages already write (see
:mod:`.language.store`): a task handles a run of consecutive timesteps of one stage (``--ray-chunk``;
consecutive so extraction's 8-frame tubes reuse their rendered frames inside a task) and each
timestep's file is written atomically as soon as it is finished, by the very function a
single-process or ``--shard i/n`` run calls. A cluster run, a sharded run and a single-process run
therefore produce the same bytes, a killed cluster run resumes (only missing timesteps are
scheduled again) and no partial file ever becomes visible.

Storage: by default every node sees the bundle at the same path (a shared filesystem; each task
checks that it sees the driver's ``scene.json`` and fails with one clear line otherwise). With
``shared_fs=False`` (``--ray-no-shared-fs``) the driver ships the bundle's input files through Ray's
object store (once per node), the workers compute in a node-local copy and return the finished
files' bytes, and the driver writes them, atomically, into the bundle.

Fitting is not split here: a fit's timesteps depend on each other (each starts from the previous
one), so what runs in parallel is several scenes or sequences, one task each (:func:`map_on_ray`).

Ray is optional (``pip install "fourlegs[cluster]"``) and imported only inside these functions.
"""
from __future__ import annotations

import argparse
import hashlib
import math
import os
import shutil
import tempfile
import time
import uuid
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence

from .errors import FourlegsError, InputError

if TYPE_CHECKING:  # heavy modules stay out of `fourlegs --help`
    from .language.distill import DistillConfig, DistillResult
    from .language.extract import ExtractConfig, ExtractReport
    from .scene.scene import Scene

INSTALL_HINT = 'pip install "fourlegs[cluster]"'
#: exceptions raised inside a task that Ray retries (transient: I/O, memory, CUDA runtime errors);
#: a worker process that dies (killed, out of memory) is retried as well. Bad input is not retried.
RETRYABLE = (OSError, MemoryError, RuntimeError)
DEFAULT_RETRIES = 2
#: top-level bundle entries that are stage outputs, never shipped to workers as inputs
OUTPUT_DIRS = ("features", "language", "bench")


class ClusterError(FourlegsError):
    """Ray is missing, cannot be reached, or tasks failed after their retries."""


@dataclass
class RayOptions:
    """How to reach the cluster and what each task asks for.

    Attributes:
        address: None or "local": start a local cluster in this process (``ray.init()``); otherwise a
            Ray address ("auto", "HOST:6379", "ray://HOST:10001").
        num_cpus, num_gpus: resources each task declares (None GPUs: 1 when the encoder device is
            CUDA, or "auto" on a cluster with GPUs; else 0).
        retries: how many times a failed task is retried (worker death or a transient error).
        shared_fs: the bundle is visible at the same path on every node.
        chunk: timesteps per task (None: distillation 1, extraction :func:`auto_chunk`).
        local_cpus: CPUs of a locally started cluster (None: all of the machine's).
    """

    address: str | None = None
    num_cpus: float = 1.0
    num_gpus: float | None = None
    retries: int = DEFAULT_RETRIES
    shared_fs: bool = True
    chunk: int | None = None
    local_cpus: int | None = None

    def check(self) -> "RayOptions":
        if self.num_cpus < 0 or (self.num_gpus is not None and self.num_gpus < 0):
            raise InputError("task resources must be >= 0", field="--ray-cpus/--ray-gpus")
        if self.retries < 0:
            raise InputError(f"must be >= 0, got {self.retries}", field="--ray-retries")
        if self.chunk is not None and self.chunk < 1:
            raise InputError(f"must be >= 1, got {self.chunk}", field="--ray-chunk")
        return self


# ----------------------------------------------------------------------------------- the CLI side
class _RayAddress(argparse.Action):
    """``--ray [ADDRESS]``; in ``--ray BUNDLE`` (the optional value swallowed the scene argument) the
    value is a scene bundle, not an address: it becomes the scene and the cluster a local one."""

    def __call__(self, parser: Any, namespace: argparse.Namespace, values: Any, option_string: Any = None) -> None:
        if (values not in (None, "local", "auto") and getattr(namespace, "scene", None) is None
                and (Path(values) / "scene.json").is_file()):
            parser.set_defaults(scene=values)   # the scene positional, matched empty afterwards, takes it
            namespace.scene, values = values, "local"
        setattr(namespace, self.dest, values)


def add_ray_arguments(parser: argparse.ArgumentParser) -> None:
    """``--ray [ADDRESS]`` and its task options (shared by extract, distill and language)."""
    g = parser.add_argument_group("cluster (Ray; needs " + INSTALL_HINT + ")")
    g.add_argument("--ray", nargs="?", const="local", default=None, metavar="ADDRESS", action=_RayAddress,
                   help="run the stage as Ray tasks: on a local cluster (no ADDRESS) or the cluster at "
                        "ADDRESS (auto, HOST:6379, ray://HOST:10001)")
    g.add_argument("--ray-cpus", type=float, default=1.0, help="CPUs each task declares (default 1)")
    g.add_argument("--ray-gpus", type=float, default=None,
                   help="GPUs each task declares (default 1 with a CUDA encoder device, else 0)")
    g.add_argument("--ray-retries", type=int, default=DEFAULT_RETRIES,
                   help=f"retries of a failed task (default {DEFAULT_RETRIES})")
    g.add_argument("--ray-chunk", type=int, default=None,
                   help="timesteps per task (default: distillation 1; extraction 1 with RGB encoders such as "
                        "ViCLIP, one run per worker with label encoders, whose cost is rendering)")
    g.add_argument("--ray-no-shared-fs", action="store_true",
                   help="the bundle is not on a filesystem every node sees: ship inputs and results "
                        "through Ray's object store (the driver writes the files)")


def options_from_args(args: argparse.Namespace) -> RayOptions:
    address = getattr(args, "ray", None)
    return RayOptions(address=None if address in (None, "local") else address, num_cpus=args.ray_cpus,
                      num_gpus=args.ray_gpus, retries=args.ray_retries, shared_fs=not args.ray_no_shared_fs,
                      chunk=args.ray_chunk).check()


def uses_ray(args: argparse.Namespace) -> bool:
    return getattr(args, "ray", None) is not None


def cli_extract(args: argparse.Namespace, scene: "Scene", encoder_factory: Callable[["Scene"], Any],
                config: "ExtractConfig", *, timesteps: Any = None, shard: Any = None) -> "ExtractReport":
    """``fourlegs extract|language --ray``: extraction on the cluster; prints a one-line task summary."""
    report, tasks = extract_on_ray(scene, encoder_factory, config, timesteps=timesteps, shard=shard,
                                   overwrite=args.overwrite, progress=not args.no_progress,
                                   options=options_from_args(args), device=getattr(args, "device", None))
    print(tasks.summary(), flush=True)
    return report


def cli_distill(args: argparse.Namespace, scene: "Scene", config: "DistillConfig", *, timesteps: Any = None,
                shard: Any = None) -> "DistillResult":
    """``fourlegs distill|language --ray``: distillation on the cluster, merged when complete."""
    result, tasks = distill_on_ray(scene, config, timesteps=timesteps, shard=shard, overwrite=args.overwrite,
                                   progress=not args.no_progress, options=options_from_args(args))
    print(tasks.summary(), flush=True)
    return result


# ------------------------------------------------------------------------------ ray and scheduling
def require_ray() -> Any:
    """The ``ray`` module, or :class:`ClusterError` naming the extra to install."""
    try:
        import ray
    except ImportError:
        raise ClusterError(f"--ray needs Ray, which is not installed; install it with: {INSTALL_HINT}") from None
    return ray


def connect(options: RayOptions) -> Any:
    """Start (``address`` None) or join the cluster once per process; returns the ``ray`` module."""
    ray = require_ray()
    if ray.is_initialized():
        return ray
    kwargs: dict[str, Any] = {"include_dashboard": False, "logging_level": "WARNING",
                              "configure_logging": True, "log_to_driver": True}
    if options.address is None:
        kwargs["num_cpus"] = options.local_cpus
    try:
        ray.init(address=options.address, **kwargs)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        raise ClusterError(f"cannot reach the Ray cluster at {options.address or 'local'}: {exc}") from None
    return ray


def plan_chunks(timesteps: Sequence[int], size: int) -> list[tuple[int, ...]]:
    """Split sorted timesteps into runs of consecutive ones, at most ``size`` long.

    >>> plan_chunks([0, 1, 2, 3, 5, 6, 9], 3)
    [(0, 1, 2), (3,), (5, 6), (9,)]
    """
    chunks: list[tuple[int, ...]] = []
    run: list[int] = []
    for t in sorted(timesteps):
        if run and (t != run[-1] + 1 or len(run) >= size):
            chunks.append(tuple(run))
            run = []
        run.append(int(t))
    if run:
        chunks.append(tuple(run))
    return chunks


def worker_slots(ray: Any, options: RayOptions, num_gpus: float) -> int:
    """How many tasks of this shape the cluster runs at once (at least 1)."""
    res = ray.cluster_resources()
    slots = [res.get("CPU", 1.0) / options.num_cpus] if options.num_cpus > 0 else []
    if num_gpus > 0:
        slots.append(res.get("GPU", 0.0) / num_gpus)
    return max(1, int(min(slots))) if slots else 1


def auto_chunk(num_timesteps: int, slots: int, input_kind: str = "rgb") -> int:
    """Timesteps per extraction task when ``--ray-chunk`` is not given.

    A task renders (chunk + 7) frames per camera for its chunk's 8-frame tubes. For RGB encoders
    (ViCLIP) encoding dominates by far, so one timestep per task balances best; for label encoders
    (the simulated one) rendering dominates, so each worker slot gets one run of consecutive timesteps.
    """
    if input_kind == "rgb":
        return 1
    return max(1, math.ceil(num_timesteps / max(1, slots)))


@dataclass
class TaskFailure:
    chunk: tuple[int, ...]
    error: str

    def describe(self, unit: str) -> str:
        from .language.store import format_ranges
        where = f"{unit} {format_ranges(list(self.chunk))}" if self.chunk else "the set-up task"
        return f"{where}: {self.error}"


@dataclass
class ClusterReport:
    """What :func:`run_chunks` did: tasks, their worker-side seconds, failures, wall-clock time."""

    stage: str
    unit: str = "timestep"
    chunks: list[tuple[int, ...]] = field(default_factory=list)
    done: list[tuple[int, ...]] = field(default_factory=list)
    task_seconds: list[float] = field(default_factory=list)
    task_cpu_seconds: list[float] = field(default_factory=list)
    #: per finished task: (worker pid, start, end, arrival at the driver), wall-clock seconds
    timeline: list[tuple[int, float, float, float]] = field(default_factory=list)
    failures: list[TaskFailure] = field(default_factory=list)
    skipped: list[int] = field(default_factory=list)
    wall_seconds: float = 0.0
    slots: int = 1
    nodes: int = 1
    #: the set-up task run before these (extraction: the features' configuration)
    setup: "ClusterReport | None" = None

    def summary(self) -> str:
        done = sum(len(c) for c in self.done)
        rate = done / self.wall_seconds if self.wall_seconds > 0 else 0.0
        return (f"ray {self.stage}: {len(self.done)}/{len(self.chunks)} task(s), {done} {self.unit}(s) in "
                f"{self.wall_seconds:.1f} s ({rate:.2f} {self.unit}/s) on {self.slots} slot(s), "
                f"{self.nodes} node(s); {len(self.skipped)} already done, {len(self.failures)} failed")

    def raise_failures(self) -> None:
        if self.failures:
            lines = "; ".join(f.describe(self.unit) for f in self.failures)
            raise ClusterError(f"{len(self.failures)} of {len(self.chunks)} {self.stage} task(s) failed "
                               f"after their retries ({lines}); the finished {self.unit}s are kept: run the "
                               "same command again to resume")

    def dispatch_gaps(self) -> list[float]:
        """Seconds between one task's end and the next task's start on the same worker process: the
        per-task cost of the cluster while tasks are queued (scheduling, argument and result transfer)."""
        by_worker: dict[int, list[tuple[float, float]]] = {}
        for pid, start, end, _ in self.timeline:
            by_worker.setdefault(pid, []).append((start, end))
        gaps = []
        for spans in by_worker.values():
            spans.sort()
            gaps += [b[0] - a[1] for a, b in zip(spans, spans[1:])]
        return gaps

    def to_dict(self) -> dict[str, Any]:
        return {"stage": self.stage, "tasks": len(self.chunks), "done": [list(c) for c in self.done],
                "failures": [{"chunk": list(f.chunk), "error": f.error} for f in self.failures],
                "skipped": self.skipped, "task_seconds": self.task_seconds,
                "task_cpu_seconds": self.task_cpu_seconds, "wall_seconds": self.wall_seconds,
                "slots": self.slots, "nodes": self.nodes}


def _run_task(function: Callable[..., Any], job: Any, chunk: tuple[int, ...], payload: Any) -> dict[str, Any]:
    """The remote body of every task: the stage function plus its worker-side wall time."""
    start, wall, cpu = time.perf_counter(), time.time(), time.process_time()
    value = function(job, chunk, payload)
    return {"value": value, "seconds": time.perf_counter() - start, "cpu_seconds": time.process_time() - cpu,
            "pid": os.getpid(), "started": wall, "ended": time.time()}


def run_chunks(function: Callable[..., Any], job: Any, chunks: Sequence[tuple[int, ...]], *,
               options: RayOptions, stage: str, num_gpus: float = 0.0, unit: str = "timestep",
               payloads: Sequence[Any] | None = None, progress: bool = True,
               on_result: Callable[[tuple[int, ...], Any], None] | None = None) -> ClusterReport:
    """Run ``function(job, chunk, payload)`` for every chunk as Ray tasks and wait for all of them.

    ``job`` is put into the object store once and shared by every task. Each task declares
    ``options.num_cpus`` CPUs and ``num_gpus`` GPUs and is retried up to ``options.retries`` times
    when its worker dies or it raises one of :data:`RETRYABLE`. ``on_result(chunk, value)`` runs in
    this process as results arrive (completion order). A task that still fails is recorded in the
    report with its chunk; the other tasks go on. Ctrl-C cancels the tasks not yet finished.

    Returns:
        :class:`ClusterReport` (call :meth:`ClusterReport.raise_failures` to turn failures into an error).
    """
    ray = connect(options)
    report = ClusterReport(stage, unit, [tuple(c) for c in chunks], slots=worker_slots(ray, options, num_gpus),
                           nodes=max(1, len([n for n in ray.nodes() if n.get("Alive")])))
    if not chunks:
        return report
    remote = ray.remote(_run_task).options(num_cpus=options.num_cpus, num_gpus=num_gpus,
                                           max_retries=options.retries, retry_exceptions=list(RETRYABLE),
                                           name=f"fourlegs-{stage}")
    start = time.perf_counter()
    job_ref = ray.put(job)
    payloads = list(payloads) if payloads is not None else [None] * len(chunks)
    pending = {remote.remote(function, job_ref, tuple(c), p): tuple(c) for c, p in zip(chunks, payloads)}
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=sum(len(c) for c in chunks), desc=f"{stage} (ray)", unit=unit)
    try:
        while pending:
            refs = list(pending)
            ready, _ = ray.wait(refs, num_returns=1, timeout=1.0)
            if ready:  # everything else already finished, without waiting
                ready, _ = ray.wait(refs, num_returns=len(refs), timeout=0)
            for ref in ready:
                chunk = pending.pop(ref)
                try:
                    out = ray.get(ref)
                    if on_result is not None:
                        on_result(chunk, out["value"])
                except KeyboardInterrupt:
                    raise
                except Exception as exc:  # noqa: BLE001 - every task failure is reported with its chunk
                    report.failures.append(TaskFailure(chunk, _describe(exc)))
                else:
                    report.done.append(chunk)
                    report.task_seconds.append(float(out["seconds"]))
                    report.task_cpu_seconds.append(float(out["cpu_seconds"]))
                    report.timeline.append((int(out["pid"]), float(out["started"]), float(out["ended"]), time.time()))
                if bar is not None:
                    bar.update(len(chunk))
                    bar.set_postfix_str(f"tasks {len(report.done)}/{len(report.chunks)}"
                                        + (f", {len(report.failures)} failed" if report.failures else ""))
    except BaseException:
        for ref in pending:
            ray.cancel(ref, force=True)
        raise
    finally:
        if bar is not None:
            bar.close()
        report.wall_seconds = time.perf_counter() - start
    return report


def _describe(exc: BaseException) -> str:
    cause = getattr(exc, "cause", None)
    err = cause if isinstance(cause, BaseException) else exc
    text = str(err).strip().splitlines()
    return f"{type(err).__name__}: {text[-1] if text else ''}".strip()


def map_on_ray(function: Callable[[Any], Any], items: Sequence[Any], *, options: RayOptions | None = None,
               stage: str = "map", num_gpus: float = 0.0, progress: bool = True) -> list[Any]:
    """``[function(item) for item in items]`` as one Ray task per item (e.g. one fit per scene).

    Raises:
        ClusterError: naming every item whose task failed after its retries.
    """
    options = (options or RayOptions()).check()
    results: list[Any] = [None] * len(items)

    def keep(chunk: tuple[int, ...], value: Any) -> None:
        results[chunk[0]] = value

    report = run_chunks(_map_item, (function, list(items)), [(i,) for i in range(len(items))], options=options,
                        stage=stage, num_gpus=num_gpus, unit="item", progress=progress, on_result=keep)
    report.raise_failures()
    return results


def _map_item(job: tuple[Callable[[Any], Any], list[Any]], chunk: tuple[int, ...], payload: Any) -> Any:
    function, items = job
    return function(items[chunk[0]])


# ------------------------------------------------------------------------------- bundle on workers
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
    from .fileio import write_bytes_atomic
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


def _cached(key: str, build: Callable[[], Any]) -> Any:
    """Per worker process: the scene and encoder of the current run (workers outlive tasks)."""
    if key not in _WORKER_CACHE:
        if len(_WORKER_CACHE) > 4:
            _WORKER_CACHE.clear()
        _WORKER_CACHE[key] = build()
    return _WORKER_CACHE[key]


def _task_scene(ref: BundleRef, run_id: str, payload: dict[str, bytes] | None = None) -> "Scene":
    from .scene.bundle import load_bundle
    root = _task_bundle(ref, payload)
    return _cached(f"{run_id}:scene:{root}", lambda: load_bundle(root))


def _take_files(scene_root: Path, rels: Sequence[str]) -> dict[str, bytes]:
    """Bytes of finished result files of a node-local copy, removed from it afterwards."""
    out = {}
    for rel in rels:
        p = scene_root / rel
        out[rel] = p.read_bytes()
        p.unlink()
    return out


def _write_results(root: Path, files: dict[str, bytes]) -> None:
    """Driver side of ``shared_fs=False``: the returned files, each written atomically (fsync'd)."""
    from .fileio import atomic_path
    for rel, data in files.items():
        with atomic_path(root / rel) as tmp:
            with open(tmp, "wb") as fh:
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())


def _gpus_for(options: RayOptions, ray: Any, device: str | None) -> float:
    if options.num_gpus is not None:
        return float(options.num_gpus)
    device = (device or "auto").lower()
    if device.startswith("cuda"):
        return 1.0
    if device == "auto" and ray.cluster_resources().get("GPU", 0.0) > 0:
        return 1.0
    return 0.0


# -------------------------------------------------------------------------------------- extraction
@dataclass
class ExtractJob:
    bundle: BundleRef
    run_id: str
    encoder_factory: Callable[["Scene"], Any]
    config: "ExtractConfig"


def _extract_encoder(job: ExtractJob, scene: "Scene") -> Any:
    return _cached(f"{job.run_id}:encoder:{scene.root}", lambda: job.encoder_factory(scene))


def _extract_config_task(job: ExtractJob, chunk: tuple[int, ...], payload: Any) -> dict[str, Any]:
    from .language.extract import extract_config_dict
    scene = _task_scene(job.bundle, job.run_id)
    return extract_config_dict(scene, _extract_encoder(job, scene), job.config)


def _extract_chunk(job: ExtractJob, chunk: tuple[int, ...], payload: Any) -> dict[str, Any]:
    from .language.extract import FEATURES_DIR, extract_features
    scene = _task_scene(job.bundle, job.run_id)
    rep = extract_features(scene, _extract_encoder(job, scene), job.config, timesteps=list(chunk), progress=False)
    files = None
    if not job.bundle.shared:
        files = _take_files(Path(scene.root), [f"{FEATURES_DIR}/t{t:06d}.npy" for t in rep.timesteps_done])
    return {"done": rep.timesteps_done, "render_seconds": rep.render_seconds,
            "encode_seconds": rep.encode_seconds, "crops": rep.crops_per_timestep, "files": files}


def extract_on_ray(scene: "Scene", encoder_factory: Callable[["Scene"], Any], config: "ExtractConfig | None" = None,
                   *, timesteps: Any = None, shard: Any = None, overwrite: bool = False, progress: bool = False,
                   options: RayOptions | None = None, device: str | None = None
                   ) -> tuple["ExtractReport", ClusterReport]:
    """:func:`~.language.extract.extract_features` with the timesteps spread over Ray tasks.

    ``encoder_factory(scene)`` builds the encoder inside each worker (once per worker process); it
    must be picklable (a module-level function or a ``functools.partial`` of one). The driver never
    builds the encoder: the features' configuration comes from one small task first.
    """
    from .language.extract import ExtractConfig
    from .language.store import select_timesteps
    options = (options or RayOptions()).check()
    config = config or ExtractConfig()
    if not 0 < config.frame_scale <= 1:
        raise InputError(f"must be in (0, 1], got {config.frame_scale}", field="frame_scale")
    if scene.root is None:
        raise InputError("the scene must be a bundle on disk (write it with "
                         "fourlegs_engine.scene.write_bundle(scene, PATH) first)", field="scene")
    steps = select_timesteps(scene.num_timesteps, timesteps, shard)
    ray = connect(options)
    gpus = _gpus_for(options, ray, device)
    root = Path(scene.root)
    job = ExtractJob(bundle_ref(ray, root, options), uuid.uuid4().hex, encoder_factory, config)
    try:
        return _extract_on_ray(ray, scene, job, steps, gpus, overwrite, progress, options)
    finally:
        release_bundle(ray, job.bundle)


def _extract_on_ray(ray: Any, scene: "Scene", job: ExtractJob, steps: list[int], gpus: float, overwrite: bool,
                    progress: bool, options: RayOptions) -> tuple["ExtractReport", ClusterReport]:
    from .language.extract import ExtractReport, feature_store
    root = Path(scene.root)
    configs: list[dict[str, Any]] = []
    probe = run_chunks(_extract_config_task, job, [()], options=options, stage="extract-config", num_gpus=gpus,
                       progress=False, on_result=lambda chunk, value: configs.append(value))
    probe.raise_failures()
    store = feature_store(scene, configs[0]).open(overwrite=overwrite)
    todo = [t for t in steps if not store.is_done(t)]
    slots = worker_slots(ray, options, gpus)
    chunks = plan_chunks(todo, options.chunk or auto_chunk(len(todo), slots, configs[0]["input_kind"]))
    stats = {"render": 0.0, "encode": 0.0, "crops": 0, "done": []}

    def collect(chunk: tuple[int, ...], value: dict[str, Any]) -> None:
        if value["files"]:
            _write_results(root, value["files"])
        stats["render"] += value["render_seconds"]
        stats["encode"] += value["encode_seconds"]
        stats["crops"] = value["crops"] or stats["crops"]
        stats["done"] += value["done"]

    start = time.perf_counter()
    tasks = run_chunks(_extract_chunk, job, chunks, options=options, stage="extract", num_gpus=gpus,
                       progress=progress, on_result=collect)
    tasks.skipped = [t for t in steps if t not in set(todo)]
    tasks.setup = probe
    tasks.raise_failures()
    report = ExtractReport(sorted(stats["done"]), tasks.skipped, time.perf_counter() - start, stats["render"],
                           stats["encode"], stats["crops"])
    return report, tasks


# ------------------------------------------------------------------------------------ distillation
@dataclass
class DistillJob:
    bundle: BundleRef
    run_id: str
    config: "DistillConfig"


def _distill_chunk(job: DistillJob, chunk: tuple[int, ...], payload: dict[str, bytes] | None) -> dict[str, Any]:
    from .language.distill import STEPS_DIR, distill_scene
    scene = _task_scene(job.bundle, job.run_id, payload)
    result = distill_scene(scene, config=job.config, timesteps=list(chunk), merge=False, progress=False)
    files = None
    if not job.bundle.shared:
        files = _take_files(Path(scene.root), [f"{STEPS_DIR}/t{t.t:06d}.npy" for t in result.timings])
        for rel in (payload or {}):  # this chunk's teacher features are not needed on the node any more
            Path(scene.root, rel).unlink(missing_ok=True)
    return {"timings": result.timings, "files": files}


def distill_on_ray(scene: "Scene", config: "DistillConfig", *, timesteps: Any = None, shard: Any = None,
                   overwrite: bool = False, progress: bool = False, options: RayOptions | None = None
                   ) -> tuple["DistillResult", ClusterReport]:
    """:func:`~.language.distill.distill_scene` (the bundle's own field) with one Ray task per
    ``options.chunk`` timesteps (default 1); the latents are merged here once every timestep is done.

    Without a shared filesystem each task also receives the teacher features of its own timesteps.
    """
    from .language.autoencoder import AE_REPORT, ENCODER_FILE
    from .language.distill import distill_scene
    from .language.extract import FEATURES_DIR
    from .language.store import MANIFEST, StepStore, select_timesteps
    options = (options or RayOptions()).check()
    config.check()
    ray = connect(options)
    # opens the per-timestep store (refusing or, with overwrite, discarding another configuration's
    # results) without distilling anything; returns at once when the merged latents are current
    opened = distill_scene(scene, config=config, timesteps=[], overwrite=overwrite, merge=False)
    steps = select_timesteps(scene.num_timesteps, timesteps, shard)
    if opened.latents is not None:
        opened.skipped = steps
        return opened, ClusterReport("distill", skipped=steps)
    store = StepStore(Path(opened.out_dir) / "steps", "latents", opened.config, scene.num_timesteps)
    todo = [t for t in steps if not store.is_done(t)]
    gpus = float(options.num_gpus or 0.0)
    root = Path(scene.root)
    ref = bundle_ref(ray, root, options, extra=(f"{FEATURES_DIR}/{MANIFEST}", AE_REPORT, ENCODER_FILE))
    chunks = plan_chunks(todo, options.chunk or 1)
    payloads = None
    if not ref.shared:
        payloads = [{f"{FEATURES_DIR}/t{t:06d}.npy": (root / FEATURES_DIR / f"t{t:06d}.npy").read_bytes()
                     for t in chunk} for chunk in chunks]
    timings: list[Any] = []

    def collect(chunk: tuple[int, ...], value: dict[str, Any]) -> None:
        if value["files"]:
            _write_results(root, value["files"])
        timings.extend(value["timings"])

    try:
        tasks = run_chunks(_distill_chunk, DistillJob(ref, uuid.uuid4().hex, config), chunks, options=options,
                           stage="distill", num_gpus=gpus, progress=progress, payloads=payloads, on_result=collect)
    finally:
        release_bundle(ray, ref)
    tasks.skipped = [t for t in steps if t not in set(todo)]
    tasks.raise_failures()
    result = distill_scene(scene, config=config, timesteps=[], merge=True)   # merges when every timestep is done
    result.timings = sorted(timings, key=lambda t: t.t)
    result.skipped = tasks.skipped
    return result, tasks
