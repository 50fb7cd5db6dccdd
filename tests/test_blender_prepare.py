"""Prepare Language Field from the panel: background job, per-step progress, cancel, resume, adoption."""
from __future__ import annotations

import numpy as np
import pytest

from _blender_helpers import bl, bpy_addon, tiny_scene  # noqa: F401

pytestmark = pytest.mark.blender


def test_prepare_field_reports_stages_cancels_between_steps_and_resumes(bl, tmp_path, monkeypatch):
    from fourlegs_engine import api
    from fourlegs_engine.scene import write_bundle
    from fourlegs_addon import importer, jobs, prepare

    bundle = tmp_path / "bundle"
    write_bundle(tiny_scene(T=3, N=64), bundle)
    assert bl.ops.fourlegs.import_scene(filepath=str(bundle / "scene.json")) == {"FINISHED"}
    props = bl.context.scene.fourlegs
    assert not prepare.has_field(props.splat_object)
    units = [("extract features", 3), ("train autoencoder", 2), ("distil (lift)", 3)]
    finished: list[tuple[str, int]] = []
    seen_progress: list[float] = []

    def fake_steps(scene, encoder_config=None):
        for stage, total in units:
            for done in range(1, total + 1):
                if (stage, done) in finished:
                    continue
                finished.append((stage, done))
                yield api.FieldStep(stage, done, total)
                seen_progress.append(jobs.active()[0].progress)
                if len(finished) == 4:
                    jobs.cancel_all()  # Esc / the Cancel button while the 5th unit runs: it ends, then stop

    monkeypatch.setattr(api, "language_field_steps", fake_steps, raising=False)
    monkeypatch.setattr(api, "ensure_language_field", lambda scene, **kw: scene, raising=False)
    assert bl.ops.fourlegs.prepare_field() == {"CANCELLED"}
    assert props.status == "cancelled at train autoencoder 2/2 (run it again to resume)" and not props.running
    assert finished == [("extract features", 1), ("extract features", 2), ("extract features", 3),
                        ("train autoencoder", 1), ("train autoencoder", 2)]
    assert seen_progress == pytest.approx([1 / 9, 2 / 9, 3 / 9, 1 / 3 + 1 / 6])
    assert bl.ops.fourlegs.prepare_field() == {"FINISHED"}  # resumes: no unit twice
    assert len(finished) == len(set(finished)) == 8 and props.status == "language field ready"
    assert seen_progress[-1] == pytest.approx(1.0)
    assert importer.source_key(props.splat_object) == str(bundle.resolve())


def test_prepare_field_error_is_one_line(bl, tmp_path, monkeypatch):
    from fourlegs_engine import api
    from fourlegs_engine.scene import write_bundle

    write_bundle(tiny_scene(T=2, N=16), tmp_path / "b")
    assert bl.ops.fourlegs.import_scene(filepath=str(tmp_path / "b" / "scene.json")) == {"FINISHED"}

    def failing(scene, encoder_config=None):
        raise api.InputError("no weights", field="checkpoint")
        yield

    monkeypatch.setattr(api, "language_field_steps", failing, raising=False)
    monkeypatch.setattr(api, "ensure_language_field", lambda scene, **kw: scene, raising=False)
    with pytest.raises(RuntimeError, match="Prepare Language Field: checkpoint: no weights"):
        bl.ops.fourlegs.prepare_field()
    status = bl.context.scene.fourlegs.status
    assert status.startswith("error: ") and "no weights" in status and "\n" not in status


def test_run_query_uses_the_fast_defaults_of_the_highlight_command():
    from fourlegs_addon import querying

    assert querying.default_options().spatial == "fast"


def test_prepare_extracts_every_timestep_in_one_call_as_the_main_job(bl, tmp_path, monkeypatch):
    """The panel's field costs what the main job's chain costs: extraction in one call over every timestep
    (neighbouring timesteps share rendered frames), then the per-unit autoencoder epochs and distillation,
    and the field is the one the chain makes (same stages, same distillation settings)."""
    from fourlegs_engine import pipeline
    from fourlegs_engine.language import autoencoder, distill, extract
    from fourlegs_engine.scene import write_bundle
    from fourlegs_engine.scene.bundle import update_bundle_meta

    write_bundle(tiny_scene(T=4, N=32), tmp_path / "b")
    assert bl.ops.fourlegs.import_scene(filepath=str(tmp_path / "b" / "scene.json")) == {"FINISHED"}
    calls, done = [], set()

    def fake_extract(scene, encoder, config=None, *, timesteps=None, **kw):
        calls.append(("extract", None if timesteps is None else tuple(timesteps)))
        done.update(range(scene.num_timesteps) if timesteps is None else timesteps)

    def fake_training(scene, *args, **kw):
        for epoch in (1, 2):
            calls.append(("train", epoch))
            yield epoch, 2
        return {"config_hash": "x"}

    def fake_distill(scene, mode="lift", timesteps=None, view_scale=1.0, **kw):
        assert view_scale == pipeline.FIELD_VIEW_SCALE
        calls.append(("distill", tuple(timesteps) if timesteps is not None else None))
        if timesteps is not None and timesteps[-1] == scene.num_timesteps - 1:
            np.save(scene.root / "latents.npy", np.zeros((4, 32, 4), np.float32))
            update_bundle_meta(scene.root, language={"encoder": "simulated", "latents": "latents.npy"})

    monkeypatch.setattr(extract, "extract_features", fake_extract)
    monkeypatch.setattr(autoencoder, "autoencoder_training", fake_training)
    monkeypatch.setattr(distill, "distill_scene", fake_distill)
    monkeypatch.setattr(pipeline, "text_encoder", lambda scene, config=None: object())
    assert bl.ops.fourlegs.prepare_field() == {"FINISHED"}
    extract_calls = [c for c in calls if c[0] == "extract"]
    assert extract_calls[0] == ("extract", None) and done == {0, 1, 2, 3}
    assert calls.index(("extract", None)) < min(i for i, c in enumerate(calls) if c[0] == "train")
    assert [c for c in calls if c[0] == "train"] == [("train", 1), ("train", 2)]  # one training, a step per epoch
    assert [c for c in calls if c[0] == "distill"] == [("distill", (t,)) for t in range(4)]
