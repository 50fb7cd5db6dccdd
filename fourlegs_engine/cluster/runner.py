"""The generic Ray runner: chunks of work as Ray tasks, retried, reported, cancellable.

:func:`run_chunks` runs ``function(job, chunk, payload)`` for every chunk and collects a
:class:`ClusterReport`; :func:`map_on_ray` is one task per item. Nothing here knows the language
stages (:mod:`.stages`) or the bundle (:mod:`.bundles`).

Ray is optional (``pip install "fourlegs[cluster]"``) and imported only inside these functions.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

from ..errors import FourlegsError, InputError

INSTALL_HINT = 'pip install "fourlegs[cluster]"'
#: exceptions raised inside a task that Ray retries (transient: I/O, memory, CUDA runtime errors);
#: a worker process that dies (killed, out of memory) is retried as well. Bad input is not retried.
RETRYABLE = (OSError, MemoryError, RuntimeError)
DEFAULT_RETRIES = 2


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


@dataclass
class TaskFailure:
    chunk: tuple[int, ...]
    error: str

    def describe(self, unit: str) -> str:
        from ..language.store import format_ranges
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


def run_task(function: Callable[..., Any], job: Any, chunk: tuple[int, ...], payload: Any) -> dict[str, Any]:
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
    remote = ray.remote(run_task).options(num_cpus=options.num_cpus, num_gpus=num_gpus,
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
                    report.failures.append(TaskFailure(chunk, describe_failure(exc)))
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


def describe_failure(exc: BaseException) -> str:
    """One line for a task's exception (Ray wraps it: its cause, type and last message line)."""
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


