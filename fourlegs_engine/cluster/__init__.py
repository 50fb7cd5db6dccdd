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

- :mod:`.runner` — the generic runner: :func:`run_chunks`, :func:`map_on_ray`, :class:`RayOptions`,
  :class:`ClusterReport`.
- :mod:`.bundles` — the bundle on the workers (shared filesystem or shipped through the object store).
- :mod:`.stages` — the language stages as tasks: :func:`extract_on_ray`, :func:`distill_on_ray`.

The command-line side (``--ray`` and its options) is :mod:`fourlegs_engine.commands.options`.
"""
from ..lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    **{name: "runner" for name in ("ClusterError", "ClusterReport", "DEFAULT_RETRIES", "INSTALL_HINT", "RETRYABLE",
                                   "RayOptions", "TaskFailure", "connect", "map_on_ray", "plan_chunks", "require_ray",
                                   "run_chunks", "run_task", "worker_slots")},
    **{name: "bundles" for name in ("BundleRef", "OUTPUT_DIRS", "bundle_ref", "release_bundle")},
    **{name: "stages" for name in ("DistillJob", "ExtractJob", "auto_chunk", "distill_on_ray", "extract_on_ray")},
})
