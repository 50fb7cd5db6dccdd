"""The one setup chain: open a scene (any format) -> encoder -> language field -> query engine."""
from __future__ import annotations

import numpy as np
import pytest

from fourlegs_engine import pipeline
from fourlegs_engine.errors import InputError
from fourlegs_engine.pipeline import EncoderOptions
from fourlegs_engine.scene import Scene, is_bundle, load_bundle
from fourlegs_engine.scene.ply import write_ply_scene

from _language_helpers import micro_bundle, micro_scene
from _scene_helpers import random_scene


def test_auto_encoder_is_the_fields_then_simulated_for_synthetic_scenes_then_viclip():
    scene = micro_scene(T=2)
    assert EncoderOptions().resolved_name(scene) == "simulated"  # synthetic: labels in the metadata
    scene.language = {"encoder": "viclip-b16"}
    assert EncoderOptions().resolved_name(scene) == "viclip-b16"  # the encoder the field was distilled with
    assert EncoderOptions(name="simulated").resolved_name(scene) == "simulated"  # an explicit name wins
    plain = Scene(gaussians=scene.gaussians, cameras=scene.cameras, name="plain")
    assert EncoderOptions().resolved_name(plain) == "viclip" and EncoderOptions().resolved_name(None) == "viclip"
    with pytest.raises(InputError, match="--checkpoint"):  # ViCLIP weights are never guessed
        pipeline.text_encoder(plain)


def test_open_scene_refuses_both_or_neither_source():
    with pytest.raises(InputError, match="not both"):
        pipeline.open_scene("x", demo="tiny")
    with pytest.raises(InputError, match="no scene given"):
        pipeline.open_scene()


def test_open_scene_converts_a_ply_sequence_once_into_a_cached_bundle(tmp_path, monkeypatch):
    monkeypatch.setenv("FOURLEGS_CACHE", str(tmp_path / "cache"))
    source = random_scene(T=2, N=30, sh_degree=0)
    write_ply_scene(source, tmp_path / "frames")
    scene = pipeline.open_scene(tmp_path / "frames")
    assert scene.root is not None and is_bundle(scene.root)
    assert str(scene.root).startswith(str(tmp_path / "cache" / "bundles"))
    np.testing.assert_allclose(np.asarray(scene.gaussians.means), np.asarray(source.gaussians.means), atol=1e-6)
    again = pipeline.open_scene(tmp_path / "frames")
    assert again.root == scene.root  # converted once, reused


def test_language_field_stages_run_once_in_order_with_the_chosen_encoder(tmp_path, monkeypatch):
    """The wiring of the chain (the stages themselves are tested in test_language_distill.py)."""
    from fourlegs_engine.language import autoencoder, distill, extract
    from fourlegs_engine.scene.bundle import update_bundle_meta

    scene = load_bundle(micro_bundle(tmp_path / "micro", T=2))
    assert not pipeline.has_language_field(scene)
    with pytest.raises(InputError, match="no distilled language field"):
        pipeline.open_query_engine(scene)
    calls: list[tuple] = []
    # the simulated encoder's features cost next to nothing: the "auto" plan is the paper's full extraction
    monkeypatch.setattr(extract, "extract_features", lambda sc, enc, config, progress=False: calls.append(
        ("extract", enc.name, config.knobs_dict())))
    monkeypatch.setattr(autoencoder, "train_autoencoder", lambda sc, progress=False: calls.append(("train",)))

    def fake_distill(sc, mode="lift", progress=False, view_scale=1.0):
        calls.append(("distill", mode, view_scale))
        np.save(sc.root / "latents.npy", np.zeros((2, sc.num_gaussians, 4), np.float32))
        update_bundle_meta(sc.root, language={"encoder": "simulated", "latents": "latents.npy"})

    monkeypatch.setattr(distill, "distill_scene", fake_distill)
    stages: list[str] = []

    def stage(name):
        from contextlib import nullcontext
        stages.append(name)
        return nullcontext()

    built = pipeline.ensure_language_field(scene, stage=stage)
    assert calls == [("extract", "simulated", {}), ("train",), ("distill", "lift", pipeline.FIELD_VIEW_SCALE)]
    assert stages == ["extract features", "train autoencoder", "distil (lift)"]
    assert built is not scene and pipeline.has_language_field(built)  # the bundle re-read with its field
    assert pipeline.ensure_language_field(built, stage=stage) is built and len(calls) == 3  # nothing rerun


def test_language_field_steps_report_each_unit_and_resume_after_a_stop(tmp_path, monkeypatch):
    """One step per timestep / epoch, each after its unit is done; stopping between steps and calling
    again redoes nothing finished (the stages' own resumption is tested in test_language_distill.py)."""
    from fourlegs_engine.language import autoencoder, distill, extract
    from fourlegs_engine.scene.bundle import update_bundle_meta

    scene = load_bundle(micro_bundle(tmp_path / "micro", T=3))
    done = {"extract": set(), "epochs": 0, "distill": set()}
    calls: list[tuple] = []

    def fake_extract(sc, enc, config, timesteps=None):
        calls.append(("extract", tuple(timesteps)))
        done["extract"].update(timesteps)

    def fake_training(sc):  # resumes from its last finished epoch, as the checkpoint does
        while done["epochs"] < 4:
            done["epochs"] += 1
            calls.append(("train", done["epochs"]))
            yield done["epochs"], 4
        return {"config_hash": "x"}

    def fake_distill(sc, mode="lift", timesteps=None, view_scale=1.0):
        assert view_scale == pipeline.FIELD_VIEW_SCALE  # the same field as ensure_language_field's
        calls.append(("distill", tuple(timesteps)))
        done["distill"].update(timesteps)
        if done["distill"] == {0, 1, 2}:
            np.save(sc.root / "latents.npy", np.zeros((3, sc.num_gaussians, 4), np.float32))
            update_bundle_meta(sc.root, language={"encoder": "simulated", "latents": "latents.npy"})

    monkeypatch.setattr(extract, "extract_features", fake_extract)
    monkeypatch.setattr(autoencoder, "autoencoder_training", fake_training)
    monkeypatch.setattr(distill, "distill_scene", fake_distill)
    steps = pipeline.language_field_steps(scene)
    first = [next(steps) for _ in range(5)]  # 3 extract + 2 epochs, then stop (cancel)
    steps.close()
    assert [(s.stage, s.done, s.total) for s in first] == [
        ("extract features", 1, 3), ("extract features", 2, 3), ("extract features", 3, 3),
        ("train autoencoder", 1, 4), ("train autoencoder", 2, 4)]
    rest = list(pipeline.language_field_steps(scene))
    assert [(s.stage, s.done) for s in rest][-5:] == [("train autoencoder", 3), ("train autoencoder", 4),
                                                       ("distil (lift)", 1), ("distil (lift)", 2), ("distil (lift)", 3)]
    assert [c for c in calls if c[0] == "train"] == [("train", e) for e in (1, 2, 3, 4)]  # no epoch twice
    assert pipeline.has_language_field(load_bundle(scene.root))
    assert list(pipeline.language_field_steps(load_bundle(scene.root))) == []  # a built field: nothing to do


def test_language_field_steps_draw_the_autoencoder_sample_once(tmp_path, monkeypatch):
    """A step per epoch, yet the training sample is drawn once: the panel's per-unit field costs what the
    main job's one training costs (drawing it per epoch had cost the panel 19 % more CPU)."""
    from fourlegs_engine.language import ae_sample
    from fourlegs_engine.language.autoencoder import AETrainOptions

    scene = load_bundle(micro_bundle(tmp_path / "micro", T=2))
    draws = []
    real = ae_sample.training_data
    monkeypatch.setattr(ae_sample, "training_data", lambda *a, **k: draws.append(1) or real(*a, **k))
    steps = [(s.stage, s.done) for s in pipeline.language_field_steps(scene)]
    epochs = AETrainOptions().epochs
    assert [done for stage, done in steps if stage == "train autoencoder"] == list(range(1, epochs + 1))
    assert len(draws) == 1
    assert pipeline.has_language_field(load_bundle(scene.root))


def test_language_field_steps_hold_the_scene_lock_between_steps(tmp_path):
    """The panel's field is one writer of its scene while it runs, between its steps too: another process
    is refused with the holder named, and may write once the steps are closed (cancel)."""
    import os
    import subprocess
    import sys

    scene = load_bundle(micro_bundle(tmp_path / "micro", T=2))
    probe = [sys.executable, "-c", "import sys; from fourlegs_engine.runlock import RunLock; "
             f"RunLock({str(scene.root)!r}).acquire(); print('acquired')"]
    steps = pipeline.language_field_steps(scene)
    assert next(steps).stage == "extract features"
    refused = subprocess.run(probe, capture_output=True, text=True, timeout=120)
    assert refused.returncode != 0 and "acquired" not in refused.stdout
    assert str(os.getpid()) in refused.stderr  # the holder is named
    steps.close()
    assert subprocess.run(probe, capture_output=True, text=True, timeout=120).stdout.strip() == "acquired"
