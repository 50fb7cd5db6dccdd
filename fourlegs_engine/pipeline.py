"""The one setup chain every front end uses: open a scene -> choose the encoder -> ensure the language
field -> open the query engine.

The ``fourlegs`` commands, the headless main job and the Blender add-on all go through these functions;
their options are plain dataclasses (:class:`EncoderOptions`, :class:`~fourlegs_engine.query.options.QueryOptions`)
so no command-line type reaches the library::

    from fourlegs_engine import pipeline

    scene = pipeline.open_scene(demo="demo")                       # or a bundle / params.npz dir / .ply
    scene = pipeline.ensure_language_field(scene, progress=True)   # extract -> train-ae -> distil (lift), once
    engine = pipeline.open_query_engine(scene, options=pipeline.QueryOptions(spatial="fast"))
    print(engine.localize("a ball flying in the air", {"temporal"}).temporal.segment)

Heavy modules (torch) are imported on first use, so importing this module is cheap.
"""
from __future__ import annotations

import hashlib
import sys
from contextlib import nullcontext
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, ContextManager, Iterator, Optional

from .errors import InputError
from .query.options import QueryOptions

if TYPE_CHECKING:
    from .language.budget import PlanEstimate
    from .language.encoders import VideoTextEncoder
    from .query.engine import QueryEngine
    from .scene.scene import Scene

__all__ = ["EncoderOptions", "FieldStep", "QueryOptions", "ensure_language_field", "has_language_field",
           "language_field_steps", "open_query_engine",
           "open_scene", "plan_language_field", "text_encoder"]

#: a stage reporter: ``stage("extract features")`` returns a context manager around that stage
StageReporter = Callable[[str], ContextManager[Any]]


#: fraction of each training view's resolution the lift of :func:`ensure_language_field` and
#: :func:`language_field_steps` splats at (``DistillOptions.view_scale``): the lift's cost is per pixel, and
#: the highlight job's answer (segment, peak, best view) is the full-resolution lift's
FIELD_VIEW_SCALE = 0.5


@dataclass(frozen=True)
class EncoderOptions:
    """Which video-text encoder to build, and how.

    Attributes:
        name: a registered encoder name ("simulated", "viclip", "viclip-b16", "masks") or "auto": the encoder the
            scene's field was distilled with, else "simulated" for synthetic scenes (they carry
            ``metadata["labels"]``), else "viclip".
        checkpoint / vocab: ViCLIP weights and CLIP BPE vocabulary (never downloaded).
        size: ViCLIP size, "auto" (read off the checkpoint), "l" or "b".
        device: "auto", "cpu", "cuda", "cuda:1", ...
        dtype: ViCLIP weights precision ("float32", "float16", "bfloat16").
        batch_size: clips or texts per encoder forward pass.
        normalization: pixel statistics ViCLIP sees ("clip" or "imagenet").
        masks: the annotation-mask encoder's ("masks") phrase -> mask folder pairs; empty: the ones
            recorded in the scene's language field.
    """

    name: str = "auto"
    checkpoint: Optional[str] = None
    vocab: Optional[str] = None
    size: str = "auto"
    device: str = "auto"
    dtype: str = "float32"
    batch_size: int = 16
    normalization: str = "clip"
    masks: tuple[tuple[str, str], ...] = ()

    def resolved_name(self, scene: Optional["Scene"] = None) -> str:
        """The concrete encoder name ("auto" decided for ``scene``)."""
        if self.name not in (None, "auto"):
            return self.name
        if scene is None:
            return "viclip"
        return (scene.language or {}).get("encoder") or (
            "simulated" if (scene.metadata or {}).get("labels") else "viclip")

    def replace(self, **changes: Any) -> "EncoderOptions":
        return replace(self, **changes)


def text_encoder(scene: Optional["Scene"] = None, config: EncoderOptions = EncoderOptions()) -> "VideoTextEncoder":
    """Build the encoder ``config`` names for ``scene`` (the simulated encoder reads the scene's labels)."""
    from .language.encoders import get_encoder

    name = config.resolved_name(scene)
    if name == "simulated":  # the demo scenes' encoder: the demo package registers it
        from . import demo  # noqa: F401
        return get_encoder(name, scene=scene)
    if name == "masks":
        return get_encoder(name, masks=list(config.masks), scene=scene)
    if name.startswith("viclip"):
        kwargs: dict[str, Any] = dict(checkpoint=config.checkpoint, vocab=config.vocab, device=config.device,
                                      dtype=config.dtype, batch_size=config.batch_size,
                                      normalization=config.normalization)
        if config.size not in (None, "auto"):
            kwargs["size_override"] = config.size
        return get_encoder(name, **kwargs)
    return get_encoder(name)


def open_scene(source: str | Path | None = None, *, demo: Optional[str] = None) -> "Scene":
    """Load a scene as a bundle: ``source`` (a bundle, a Dynamic 3D Gaussians ``params.npz`` directory, a
    3DGS ``.ply`` file or a directory of per-frame ``.ply`` files) or the synthetic demo scene of size
    ``demo`` ("tiny", "demo", "bench", "full"; generated on first use).

    A scene that is not a bundle is converted once into a bundle in the cache (the language stages
    store their results inside the bundle).
    """
    from .scene import is_bundle, load_scene, write_bundle

    if demo is not None:
        if source is not None:
            raise InputError("give either a demo scene or a scene path, not both", field="scene")
        from .demo.synthetic import ensure_demo_bundle
        source = ensure_demo_bundle(demo)
    elif source is None:
        raise InputError("no scene given (a path, or the demo scene)", field="scene")
    scene = load_scene(source)
    if scene.root is None or not is_bundle(scene.root):
        from .paths import cache_dir
        digest = hashlib.sha256(str(Path(source).resolve()).encode()).hexdigest()[:12]
        target = cache_dir() / "bundles" / f"{scene.name}-{digest}"
        if not is_bundle(target):
            write_bundle(scene, target)
        scene = load_scene(target)
    return scene


def has_language_field(scene: "Scene") -> bool:
    """Whether the bundle holds a distilled language field (its latents file present)."""
    return bool(scene.root is not None and scene.language
                and (Path(scene.root) / str(scene.language.get("latents", ""))).is_file())


def plan_language_field(scene: "Scene", encoder: Any = None, *, encoder_config: EncoderOptions = EncoderOptions(),
                        plan: Any = "auto") -> "PlanEstimate":
    """What building ``scene``'s language field will cost, before the work (a few seconds of calibration).

    Returns a :class:`~fourlegs_engine.language.budget.PlanEstimate`: ``.lines()`` (the plan, clips, TFLOP,
    the estimated time on the encoder's device), ``.seconds``, ``.within(budget_s)``, ``.plan`` (pass it on
    to :func:`language_field_steps` / :func:`ensure_language_field`), ``.to_dict()``. ``plan``: "auto",
    "default", "full" or an ``ExtractPlan``. The field itself is not touched."""
    from .language.budget import estimate_plan

    encoder = encoder if encoder is not None else text_encoder(scene, encoder_config)
    return estimate_plan(scene, encoder, plan)


def _plan_config(scene: "Scene", encoder: Any, plan: Any) -> Any:
    """The extraction configuration of ``plan`` on ``scene`` (no calibration)."""
    from .language.plans import resolve_plan
    return resolve_plan(plan, encoder).extract_config(scene)


def ensure_language_field(scene: "Scene", encoder: Any = None, *, encoder_config: EncoderOptions = EncoderOptions(),
                          mode: str = "lift", progress: bool = False,
                          stage: Optional[StageReporter] = None, plan: Any = "auto") -> "Scene":
    """Return ``scene`` with a distilled language field, building it first if the bundle has none.

    Building runs extract features -> train the autoencoder -> distil (``mode``, by default the
    learning-free lift); every stage resumes where it stopped. ``encoder`` (default: built from
    ``encoder_config``) is the video-text teacher. ``stage`` reports each stage (e.g. a timer).
    ``plan`` is the extraction plan (:func:`plan_language_field` prices it; "auto": the cheap default plan
    for ViCLIP, the full extraction for the simulated and annotation-mask encoders).
    """
    if scene.root is None:
        raise InputError("the scene must be a bundle on disk to hold its language field", field="scene")
    if has_language_field(scene):
        return scene
    from .language.autoencoder import train_autoencoder
    from .language.distill import distill_scene
    from .language.extract import extract_features
    from .runlock import run_lock
    from .scene.bundle import load_bundle

    report = stage or (lambda name: nullcontext())
    encoder = encoder if encoder is not None else text_encoder(scene, encoder_config)
    if progress:
        print(f"{scene.name}: no language field yet; extracting features, training the autoencoder and "
              f"distilling ({mode}) — once per scene", file=sys.stderr)
    with run_lock(scene.root):  # one writer per scene
        with report("extract features"):
            extract_features(scene, encoder, _plan_config(scene, encoder, plan), progress=progress)
        if progress and hasattr(encoder, "evidence_line"):  # annotation masks: which views vote
            print(encoder.evidence_line(), file=sys.stderr)
        with report("train autoencoder"):
            train_autoencoder(scene, progress=progress)
        with report(f"distil ({mode})"):
            distill_scene(scene, mode=mode, progress=progress, view_scale=FIELD_VIEW_SCALE)
    return load_bundle(scene.root)


def open_query_engine(scene: "Scene", encoder: Any = None, *, options: Optional[QueryOptions] = None,
                      encoder_config: EncoderOptions = EncoderOptions(),
                      progress: Optional[Callable[[float, str], None]] = None, **engine_kwargs: Any) -> "QueryEngine":
    """A :class:`~fourlegs_engine.query.engine.QueryEngine` on ``scene``'s language field.

    ``encoder`` (default: built from ``encoder_config``) must be the one the field was distilled with;
    ``engine_kwargs`` are the engine's ``codebook`` / ``codebook_dir``. InputError if the scene has no field.
    With ``progress(fraction, stage)`` the engine is opened ready to answer: the text encoder loaded, the
    field opened, the reference phrases embedded and (codebook path) the codebook loaded or built, with
    the callback called between these steps and between the codebook's timestep chunks; an exception it
    raises (e.g. :class:`~fourlegs_engine.errors.Cancelled`) stops the opening and propagates.
    """
    from .language.field import LanguageField
    from .query.engine import QueryEngine

    if not has_language_field(scene):
        raise InputError("the scene has no distilled language field: run `fourlegs highlight` on it once (or "
                         "the language stages: extract, train-ae, distill)", file=scene.root, field="language")
    if progress is None:
        encoder = encoder if encoder is not None else text_encoder(scene, encoder_config)
        _check_field_encoder(scene, encoder)
        return QueryEngine(scene, LanguageField.open(scene.root), encoder, options, **engine_kwargs)
    progress(0.0, "loading the text encoder")
    encoder = encoder if encoder is not None else text_encoder(scene, encoder_config)
    _check_field_encoder(scene, encoder)
    progress(0.3, "opening the language field")
    engine = QueryEngine(scene, LanguageField.open(scene.root), encoder, options, **engine_kwargs)
    progress(0.5, "embedding the reference phrases")
    engine.reference_embeddings()
    engine.load_index(progress=lambda f, stage: progress(0.6 + 0.4 * f, stage))
    progress(1.0, "engine ready")
    return engine



def _check_field_encoder(scene: "Scene", encoder: Any) -> None:
    """InputError when ``encoder`` is not the encoder ``scene``'s field was distilled with."""
    recorded = (scene.language or {}).get("encoder")
    if recorded and getattr(encoder, "name", recorded) != recorded:
        raise InputError(f"the field was distilled with the {recorded!r} encoder, the query would encode text with "
                         f"{encoder.name!r}: leave --encoder out (auto) or pass --encoder {recorded}",
                         file=scene.root, field="--encoder")

@dataclass(frozen=True)
class FieldStep:
    """One finished unit of work while building a language field: ``done`` of ``total`` units of ``stage``
    (``"extract features"``: timesteps, ``"train autoencoder"``: epochs, ``"distil (lift)"``: timesteps)."""
    stage: str
    done: int
    total: int


def language_field_steps(scene: "Scene", encoder: Any = None, *, encoder_config: EncoderOptions = EncoderOptions(),
                         mode: str = "lift", plan: Any = "auto") -> Iterator[FieldStep]:
    """Build ``scene``'s language field one unit at a time, yielding a :class:`FieldStep` after each.

    The same stages as :func:`ensure_language_field`, each unit persisted before it is reported, so a
    caller may stop iterating between any two steps (cancel) and a later call resumes where it stopped.
    The first step of each stage reports the units already finished (``done`` may start above 0).
    Reopen the scene (:func:`open_scene`) afterwards to see the field.
    """
    from .language.autoencoder import AETrainOptions, autoencoder_training
    from .language.distill import distill_scene
    from .language.extract import extract_features
    from .runlock import run_lock

    if scene.root is None:
        raise InputError("the scene must be a bundle on disk to hold its language field", field="scene")
    if has_language_field(scene):
        return
    encoder = encoder if encoder is not None else text_encoder(scene, encoder_config)
    config = _plan_config(scene, encoder, plan)
    T = scene.num_timesteps
    with run_lock(scene.root):  # one writer per scene, held between the steps too
        for t in range(T):
            extract_features(scene, encoder, config, timesteps=[t])
            yield FieldStep("extract features", t + 1, T)
        total = AETrainOptions().epochs
        for done, total in autoencoder_training(scene):  # one training sample, a step per epoch
            if done < total:
                yield FieldStep("train autoencoder", done, total)
        yield FieldStep("train autoencoder", total, total)
        for t in range(T):
            distill_scene(scene, mode=mode, timesteps=[t], view_scale=FIELD_VIEW_SCALE)
            yield FieldStep(f"distil ({mode})", t + 1, T)
