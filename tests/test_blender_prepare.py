"""Prepare Language Field from the panel: background job, per-step progress, cancel, resume, adoption."""
from __future__ import annotations

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
    with pytest.raises(RuntimeError, match="Prepare Language Field: checkpoint: no weights"):
        bl.ops.fourlegs.prepare_field()
    status = bl.context.scene.fourlegs.status
    assert status.startswith("error: ") and "no weights" in status and "\n" not in status


def test_run_query_uses_the_fast_defaults_of_the_highlight_command():
    from fourlegs_addon import querying

    assert querying.default_options().spatial == "fast"
