"""Feature extraction and distillation as Ray tasks (see the package docstring): one task per run of
consecutive timesteps, each timestep's file written by the very function a single-process run calls.
"""
from __future__ import annotations

import math
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from ..errors import InputError
from .bundles import (BundleRef, bundle_ref, cached, gpus_for, release_bundle, take_files, task_scene,
                      write_results)
from .runner import ClusterReport, RayOptions, connect, plan_chunks, run_chunks, worker_slots

if TYPE_CHECKING:
    from ..language.distill import DistillOptions, DistillResult
    from ..language.extract import ExtractOptions, ExtractReport
    from ..scene.scene import Scene


def auto_chunk(num_timesteps: int, slots: int, input_kind: str = "rgb") -> int:
    """Timesteps per extraction task when ``--ray-chunk`` is not given.

    A task renders (chunk + 7) frames per camera for its chunk's 8-frame tubes. For RGB encoders
    (ViCLIP) encoding dominates by far, so one timestep per task balances best; for label encoders
    (the simulated one) rendering dominates, so each worker slot gets one run of consecutive timesteps.
    """
    if input_kind == "rgb":
        return 1
    return max(1, math.ceil(num_timesteps / max(1, slots)))


# -------------------------------------------------------------------------------------- extraction
@dataclass
class ExtractJob:
    bundle: BundleRef
    run_id: str
    encoder_factory: Callable[["Scene"], Any]
    config: "ExtractOptions"


def _extract_encoder(job: ExtractJob, scene: "Scene") -> Any:
    return cached(f"{job.run_id}:encoder:{scene.root}", lambda: job.encoder_factory(scene))


def extract_config_task(job: ExtractJob, chunk: tuple[int, ...], payload: Any) -> dict[str, Any]:
    from ..language.extract import extract_config_dict
    scene = task_scene(job.bundle, job.run_id)
    return extract_config_dict(scene, _extract_encoder(job, scene), job.config)


def _extract_chunk(job: ExtractJob, chunk: tuple[int, ...], payload: Any) -> dict[str, Any]:
    from ..language.extract import FEATURES_DIR, extract_features
    from ..language.store import step_file_names
    scene = task_scene(job.bundle, job.run_id)
    rep = extract_features(scene, _extract_encoder(job, scene), job.config, timesteps=list(chunk), progress=False)
    files = None
    if not job.bundle.shared:
        root = Path(scene.root)
        files = take_files(root, [f"{FEATURES_DIR}/{name}" for t in rep.timesteps_done
                                  for name in step_file_names(root / FEATURES_DIR, t)])
    return {"done": rep.timesteps_done, "render_seconds": rep.render_seconds,
            "encode_seconds": rep.encode_seconds, "crops": rep.crops_per_timestep, "files": files}


def extract_on_ray(scene: "Scene", encoder_factory: Callable[["Scene"], Any], config: "ExtractOptions | None" = None,
                   *, timesteps: Any = None, shard: Any = None, overwrite: bool = False, progress: bool = False,
                   options: RayOptions | None = None, device: str | None = None
                   ) -> tuple["ExtractReport", ClusterReport]:
    """:func:`~.language.extract.extract_features` with the timesteps spread over Ray tasks.

    ``encoder_factory(scene)`` builds the encoder inside each worker (once per worker process); it
    must be picklable (a module-level function or a ``functools.partial`` of one). The driver never
    builds the encoder: the features' configuration comes from one small task first. With a timestep
    stride the tasks encode the stride's grid timesteps the selection needs, each exactly once, and the
    driver fills the ones in between from them (nothing for ``fill="latents"``: the lift fills those).
    """
    from ..language.extract import ExtractOptions
    from ..language.store import select_timesteps
    options = (options or RayOptions()).check()
    config = config or ExtractOptions()
    if not 0 < config.frame_scale <= 1:
        raise InputError(f"must be in (0, 1], got {config.frame_scale}", field="frame_scale")
    if scene.root is None:
        raise InputError("the scene must be a bundle on disk (write it with "
                         "fourlegs_engine.scene.write_bundle(scene, PATH) first)", field="scene")
    steps = select_timesteps(scene.num_timesteps, timesteps, shard)
    ray = connect(options)
    gpus = gpus_for(options, ray, device)
    root = Path(scene.root)
    job = ExtractJob(bundle_ref(ray, root, options), uuid.uuid4().hex, encoder_factory, config)
    try:
        return _extract_on_ray(ray, scene, job, steps, gpus, overwrite, progress, options)
    finally:
        release_bundle(ray, job.bundle)


def _extract_on_ray(ray: Any, scene: "Scene", job: ExtractJob, steps: list[int], gpus: float, overwrite: bool,
                    progress: bool, options: RayOptions) -> tuple["ExtractReport", ClusterReport]:
    from ..language.extract import ExtractReport, feature_store, fill_timesteps
    from ..language.skipping import LATENT_FILLS, encoded_timesteps, timestep_work
    root = Path(scene.root)
    configs: list[dict[str, Any]] = []
    probe = run_chunks(extract_config_task, job, [()], options=options, stage="extract-config", num_gpus=gpus,
                       progress=False, on_result=lambda chunk, value: configs.append(value))
    probe.raise_failures()
    store = feature_store(scene, configs[0]).open(overwrite=overwrite)
    stride, fill = job.config.timestep_stride, job.config.fill
    encode, to_fill = timestep_work(scene.num_timesteps, steps, stride, fill)
    if fill in LATENT_FILLS:
        to_fill = []
    # a task given only grid timesteps encodes exactly those: no two tasks write the same file
    todo = [t for t in encode if not store.is_done(t)]
    slots = worker_slots(ray, options, gpus)
    chunks = plan_chunks(todo, options.chunk or auto_chunk(len(todo), slots, configs[0]["input_kind"]))
    stats = {"render": 0.0, "encode": 0.0, "crops": 0, "done": []}

    def collect(chunk: tuple[int, ...], value: dict[str, Any]) -> None:
        if value["files"]:
            write_results(root, value["files"])
        stats["render"] += value["render_seconds"]
        stats["encode"] += value["encode_seconds"]
        stats["crops"] = value["crops"] or stats["crops"]
        stats["done"] += value["done"]

    start = time.perf_counter()
    tasks = run_chunks(_extract_chunk, job, chunks, options=options, stage="extract", num_gpus=gpus,
                       progress=progress, on_result=collect)
    tasks.skipped = [t for t in sorted(encode + to_fill) if t not in set(todo) and store.is_done(t)]
    tasks.setup = probe
    tasks.raise_failures()
    filled = fill_timesteps(store, [t for t in to_fill if not store.is_done(t)],
                            encoded_timesteps(scene.num_timesteps, stride), fill)
    report = ExtractReport(sorted(stats["done"]), tasks.skipped, time.perf_counter() - start, stats["render"],
                           stats["encode"], stats["crops"], timesteps_filled=filled)
    return report, tasks


# ------------------------------------------------------------------------------------ distillation
@dataclass
class DistillJob:
    bundle: BundleRef
    run_id: str
    config: "DistillOptions"


def _distill_chunk(job: DistillJob, chunk: tuple[int, ...], payload: dict[str, bytes] | None) -> dict[str, Any]:
    from ..language.distill import distill_scene
    from ..language.latents_file import STEPS_DIR
    from ..language.store import step_file_names
    scene = task_scene(job.bundle, job.run_id, payload)
    result = distill_scene(scene, config=job.config, timesteps=list(chunk), merge=False, progress=False)
    files = None
    if not job.bundle.shared:
        root = Path(scene.root)
        files = take_files(root, [f"{STEPS_DIR}/{name}" for t in result.timings
                                  for name in step_file_names(root / STEPS_DIR, t.t)])
        for rel in (payload or {}):  # this chunk's teacher features are not needed on the node any more
            Path(scene.root, rel).unlink(missing_ok=True)
    return {"timings": result.timings, "files": files}


def distill_on_ray(scene: "Scene", config: "DistillOptions", *, timesteps: Any = None, shard: Any = None,
                   overwrite: bool = False, progress: bool = False, options: RayOptions | None = None
                   ) -> tuple["DistillResult", ClusterReport]:
    """:func:`~.language.distill.distill_scene` (the bundle's own field) with one Ray task per
    ``options.chunk`` timesteps (default 1); the latents are merged here once every timestep is done.

    Without a shared filesystem each task also receives the teacher features of its own timesteps.
    With a ``fill="latents"`` extraction the tasks lift the encoded timesteps only; the in-between ones
    are filled here from their lifted neighbours (they have no features to send).
    """
    from ..language.autoencoder import AE_REPORT, ENCODER_FILE
    from ..language.distill import distill_scene
    from ..language.extract import FEATURES_DIR, feature_store
    from ..language.latent_fill import latent_fill_of, lift_and_fill_work
    from ..language.store import MANIFEST, StepStore, step_file_names
    options = (options or RayOptions()).check()
    config.check()
    ray = connect(options)
    # opens the per-timestep store (refusing or, with overwrite, discarding another configuration's
    # results) without distilling anything; returns at once when the merged latents are current
    opened = distill_scene(scene, config=config, timesteps=[], overwrite=overwrite, merge=False)
    stride = latent_fill_of(feature_store(scene).config)
    steps, to_fill = lift_and_fill_work(scene.num_timesteps, stride, timesteps, shard)
    if opened.latents is not None:
        opened.skipped = sorted(steps + to_fill)
        return opened, ClusterReport("distill", skipped=opened.skipped)
    store = StepStore(Path(opened.out_dir) / "steps", "latents", opened.config, scene.num_timesteps)
    todo = [t for t in steps if not store.is_done(t)]
    gpus = float(options.num_gpus or 0.0)
    root = Path(scene.root)
    ref = bundle_ref(ray, root, options, extra=(f"{FEATURES_DIR}/{MANIFEST}", AE_REPORT, ENCODER_FILE))
    chunks = plan_chunks(todo, options.chunk or 1)
    payloads = None
    if not ref.shared:
        payloads = [{f"{FEATURES_DIR}/{name}": (root / FEATURES_DIR / name).read_bytes()
                     for t in chunk for name in step_file_names(root / FEATURES_DIR, t)} for chunk in chunks]
    timings: list[Any] = []

    def collect(chunk: tuple[int, ...], value: dict[str, Any]) -> None:
        if value["files"]:
            write_results(root, value["files"])
        timings.extend(value["timings"])

    try:
        tasks = run_chunks(_distill_chunk, DistillJob(ref, uuid.uuid4().hex, config), chunks, options=options,
                           stage="distill", num_gpus=gpus, progress=progress, payloads=payloads, on_result=collect)
    finally:
        release_bundle(ray, ref)
    tasks.skipped = [t for t in steps if t not in set(todo)]
    tasks.raise_failures()
    # fills the in-between timesteps (their neighbours are lifted) and merges when every timestep is done
    result = distill_scene(scene, config=config, timesteps=to_fill, merge=True)
    result.timings = sorted(timings, key=lambda t: t.t)
    result.skipped = tasks.skipped
    return result, tasks
