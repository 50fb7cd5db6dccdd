"""Run Query from the panel: background thread + modal operator, results into the scene, cancel, errors."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from _blender_helpers import bl, bpy_addon, tiny_scene  # noqa: F401

pytestmark = pytest.mark.blender


def _engine_for(scene):
    """A real QueryEngine over a small hand-made language field (fixed random decoder, seeded latents)."""
    from fourlegs_engine.language.autoencoder import FeatureDecoder
    from fourlegs_engine.language.field import LanguageField
    from fourlegs_engine.demo.simulated import SimulatedTextEncoder
    from fourlegs_engine.query.engine import QueryEngine, QueryOptions

    torch.manual_seed(0)
    T, N = scene.num_timesteps, scene.num_gaussians
    latents = np.random.default_rng(0).normal(size=(T, N, 8)).astype(np.float16)
    field = LanguageField(latents, FeatureDecoder((8, 16, 768)), encoder_name="simulated")
    return QueryEngine(scene, field, SimulatedTextEncoder(), QueryOptions.exact())


def test_run_query_stores_results_and_colours_by_relevancy(bl, monkeypatch):
    from fourlegs_addon import importer, plots, querying

    scene = tiny_scene()
    engine = _engine_for(scene)
    monkeypatch.setattr(querying, "open_query_engine", lambda s, **kw: engine)
    obj = importer.import_scene(bl.context.scene, scene)
    props = bl.context.scene.fourlegs
    props.query = "the cube"
    assert bl.ops.fourlegs.run_query() == {"FINISHED"}
    expected = engine.temporal("the cube")
    assert not props.running and props.progress == 1.0
    assert props.found == expected.found
    if expected.found:
        assert (props.segment_start, props.segment_end) == tuple(expected.segment)
        assert props.peak == expected.peak
    peak = expected.peak if expected.found else 0
    rel = np.empty(scene.num_gaussians, np.float32)
    obj.data.attributes[importer.RELEVANCY_ATTR].data.foreach_get("value", rel)
    np.testing.assert_allclose(rel, engine.gaussian_relevancy("the cube", peak).numpy(), atol=1e-6)
    assert obj.data.color_attributes.active_color.name == importer.RELEVANCY_RGB_ATTR
    assert plots.IMAGE_NAME in bl.data.images
    # the render engine's relevancy provider is the same engine's per-Gaussian relevancy
    np.testing.assert_allclose(importer.gaussian_relevancy(obj, 1),
                               engine.gaussian_relevancy("the cube", 1).numpy(), atol=1e-6)


def test_run_query_reports_a_missing_language_field(bl):
    from fourlegs_addon import importer

    importer.import_scene(bl.context.scene, tiny_scene())
    bl.context.scene.fourlegs.query = "the cube"
    with pytest.raises(RuntimeError, match="no distilled language field"):
        bl.ops.fourlegs.run_query()
    assert not bl.context.scene.fourlegs.running
    assert bl.context.scene.fourlegs.status.startswith("error:")


def test_cancelled_query_changes_nothing(bl, monkeypatch):
    from fourlegs_addon import query_ops

    scene = tiny_scene()
    job = query_ops.QueryJob(scene, "the cube")
    job.cancelled = True
    monkeypatch.setattr(query_ops.querying, "open_query_engine", lambda s, **kw: _engine_for(s))
    job.run()
    assert job.done and job.localization is None and job.error is None


def test_scores_image_marks_positive_timesteps():
    from fourlegs_addon import plots

    scores = np.array([0.05, 0.1, 0.4, 0.35, 0.1])
    img = plots.scores_pixels(scores, scores > 0.2, (2, 3), 2, width=50, height=20)
    assert img.shape == (20, 50, 4) and np.all(np.isfinite(img))
    bottom = img[-1]
    assert np.allclose(bottom[21, :3], plots.POSITIVE[:3])  # timestep 2 is positive
    assert np.allclose(bottom[5, :3], plots.BAR[:3])
    assert np.allclose(img[0, int(2.5 * 10), :3], plots.PEAK[:3])
    assert np.all(np.isfinite(plots.scores_pixels(np.full(3, np.nan), np.zeros(3, bool), None, None)))


class _Layout:
    """Records what a panel draws (bpy offers no off-screen UI in background mode)."""

    def __init__(self, log):
        self.log = log

    def __getattr__(self, name):
        def call(*args, **kwargs):
            self.log.append((name, args, kwargs))
            return _Layout(self.log) if name in ("row", "column", "box", "split") else _Op()
        return call


class _Op:
    show = None


@pytest.mark.parametrize("imported", [False, True])
def test_panels_draw_every_state(bl, imported):
    from fourlegs_addon import importer, panels

    context = bl.context
    if imported:
        importer.import_scene(context.scene, tiny_scene())
        props = context.scene.fourlegs
        props.segment_start, props.segment_end, props.peak, props.best_view = 1, 2, 1, "cam00"
        subject = props.subjects.add()
        subject.gaussians, subject.height, subject.framed = 40, 1.8, True
    drawn, lists = set(), set()
    for running in (False, True):
        context.scene.fourlegs.running = running
        for cls in panels.classes:
            log = []
            panel = type("P", (), {"layout": _Layout(log)})()
            cls.draw(panel, context)
            ops = [a[0] for name, a, k in log if name == "operator"]
            props_drawn = [a[1] for name, a, k in log if name == "prop"]
            for prop in props_drawn:
                assert prop in context.scene.fourlegs.bl_rna.properties, prop
            for op in ops:
                assert hasattr(bl.ops.fourlegs, op.split(".")[1]), op
            drawn |= set(ops)
            lists |= {a[0] for name, a, k in log if name == "template_list"}
    assert "fourlegs.import_scene" in drawn
    assert ("FOURLEGS_UL_subjects" in lists) == imported
    if imported:
        assert {"fourlegs.run_query", "fourlegs.cancel_query", "fourlegs.generate_highlight",
                "fourlegs.render_video"} <= drawn


def test_panel_workflow_import_query_generate_with_the_real_planner(bl, tmp_path):
    """Import a bundle, Run Query, Generate Highlight (broadcast preset) as a user would, then again
    without bullet-time: the plan changes and only generated data is replaced."""
    from _blender_helpers import language_bundle
    from fourlegs_addon import compositor, keyframes, render_engine

    bundle = language_bundle(tmp_path / "scene")
    assert bl.ops.fourlegs.import_scene(filepath=str(bundle / "scene.json")) == {"FINISHED"}
    props = bl.context.scene.fourlegs
    props.query = "the red cube"
    assert bl.ops.fourlegs.run_query() == {"FINISHED"}
    assert props.found and (props.segment_start, props.segment_end, props.peak) == (1, 4, 2)
    assert props.best_view in ("cam00", "cam01")
    props.preset = "broadcast"
    assert bl.ops.fourlegs.generate_highlight() == {"FINISHED"}
    plan = render_engine.plan_of(bl.context.scene)
    assert [s["effect"] for s in plan["shots"]] == ["play", "zoom_in", "bullet_time", "desaturate_background"]
    assert compositor.has_desaturation(bl.context.scene)
    cam = bl.context.scene.camera
    assert cam.get(keyframes.GENERATED_KEY) and keyframes.keyed_frames(cam, "location", 0)
    props.use_bullet_time = False
    props.use_desaturate = False
    assert bl.ops.fourlegs.generate_highlight() == {"FINISHED"}
    plan = render_engine.plan_of(bl.context.scene)
    assert [s["effect"] for s in plan["shots"]] == ["play", "zoom_in"]
    assert not compositor.has_desaturation(bl.context.scene)
    assert sum(1 for o in bl.data.objects if o.get(keyframes.GENERATED_KEY)) == 1
    props.preset = "broadcast_blur"   # the blurred-background replay, dropped by its own checkbox
    assert bl.ops.fourlegs.generate_highlight() == {"FINISHED"}
    plan = render_engine.plan_of(bl.context.scene)
    assert [s["effect"] for s in plan["shots"]] == ["play", "zoom_in", "blur_background"]
    assert compositor.has_masking(bl.context.scene) and not compositor.has_desaturation(bl.context.scene)
    props.use_blur = False
    assert bl.ops.fourlegs.generate_highlight() == {"FINISHED"}
    assert [s["effect"] for s in render_engine.plan_of(bl.context.scene)["shots"]] == ["play", "zoom_in"]
    assert not compositor.has_masking(bl.context.scene)


def test_missing_dependency_message_names_the_install_command():
    from fourlegs_addon import messages

    exc = ModuleNotFoundError("No module named 'torch'", name="torch")
    msg = messages.error_line(exc)
    assert msg.startswith("torch is missing (querying") and "Preferences > Add-ons" in msg
    assert messages.error_line(ValueError("bad: field")) == "bad: field"


def test_viclip_weights_come_from_the_scene_properties(bl, tmp_path):
    """The add-on's encoder is the commands' EncoderOptions; its ViCLIP paths are the scene's properties."""
    from fourlegs_addon import querying
    from fourlegs_engine.pipeline import EncoderOptions

    props = bl.context.scene.fourlegs
    props.encoder_checkpoint, props.encoder_vocab = "", ""
    assert querying.encoder_config(props) == EncoderOptions()
    props.encoder_checkpoint = str(tmp_path / "ViClip-InternVid-10M-FLT.pth")
    props.encoder_vocab = str(tmp_path / "bpe_simple_vocab_16e6.txt.gz")
    config = querying.encoder_config(props)
    assert config.name == "auto" and config.checkpoint == str(tmp_path / "ViClip-InternVid-10M-FLT.pth")
    assert config.vocab == str(tmp_path / "bpe_simple_vocab_16e6.txt.gz")
    props.encoder_checkpoint, props.encoder_vocab = "", ""


def test_generate_without_a_query_result_starts_the_query_instead_of_blocking(bl, tmp_path, monkeypatch):
    """With a UI, Generate Highlight never localizes on the main thread: it starts Run Query (background)
    and asks to press Generate again; the second press plans from the query's cached result."""
    from _blender_helpers import language_bundle
    from fourlegs_addon import jobs, query_ops, render_engine

    bundle = language_bundle(tmp_path / "scene")
    assert bl.ops.fourlegs.import_scene(filepath=str(bundle / "scene.json")) == {"FINISHED"}
    props = bl.context.scene.fourlegs
    props.query = "the red cube"
    props.preset = "broadcast"
    monkeypatch.setattr(jobs, "interactive", lambda: True)
    opened = []
    real_open = query_ops.querying.open_query_engine
    monkeypatch.setattr(query_ops.querying, "open_query_engine",
                        lambda *a, **k: opened.append(1) or real_open(*a, **k))
    assert bl.ops.fourlegs.generate_highlight() == {"CANCELLED"}
    assert render_engine.plan_of(bl.context.scene) is None
    assert props.found and (props.segment_start, props.segment_end) == (1, 4)  # the query ran (as a job)
    assert len(opened) == 1
    assert bl.ops.fourlegs.generate_highlight() == {"FINISHED"}
    assert render_engine.plan_of(bl.context.scene) is not None and len(opened) == 1  # no second localization


def test_cancel_stops_the_query_inside_the_temporal_pass(bl, monkeypatch):
    """Cancel pressed while the engine scores timesteps: it stops at the next timestep, no error shown."""
    from fourlegs_addon import query_ops

    scene = tiny_scene()
    engine = _engine_for(scene)
    monkeypatch.setattr(query_ops.querying, "open_query_engine", lambda s, **kw: engine)
    job = query_ops.QueryJob(scene, "the cube")
    seen = []
    real = job.on_progress

    def press_cancel_after_first_timestep(fraction, stage):
        seen.append((round(job.progress, 3), stage))
        if len([s for _, s in seen if s == "scoring timesteps"]) == 2:
            job.cancelled = True  # what the Cancel button / Esc does
        real(fraction, stage)

    job.on_progress = press_cancel_after_first_timestep
    job.run()
    assert job.done and job.localization is None and job.error is None and job.peak_relevancy is None
    assert engine.stats["decoded_latents"] == scene.num_gaussians  # one timestep of four scored
    assert 0.2 <= job.progress < 0.9 and job.stage == "localizing: scoring timesteps"


def test_cancel_stops_the_query_while_the_engine_opens(bl, tmp_path, monkeypatch):
    """Cancel pressed while Run Query opens the engine (text encoder loaded, field not yet opened): the
    opening stops there, nothing is cached or stored, and the operator ends cancelled without an error."""
    from _blender_helpers import language_bundle

    from fourlegs_addon import importer, jobs, query_ops, querying
    from fourlegs_engine.language.field import LanguageField

    path = language_bundle(tmp_path / "bundle")
    bl.ops.fourlegs.import_scene(filepath=str(path / "scene.json"))
    obj = bl.context.scene.fourlegs.splat_object
    props = bl.context.scene.fourlegs
    props.query = "red cube"
    opened, stages = [], []
    real_open = LanguageField.open.__func__
    monkeypatch.setattr(LanguageField, "open",
                        classmethod(lambda cls, *a, **k: opened.append(1) or real_open(cls, *a, **k)))
    real_progress = query_ops.QueryJob.on_open_progress

    def cancel_when_the_field_opens(job, fraction, stage):
        stages.append(stage)
        if stage == "opening the language field":
            jobs.cancel_all()  # what the Cancel button does
        real_progress(job, fraction, stage)

    monkeypatch.setattr(query_ops.QueryJob, "on_open_progress", cancel_when_the_field_opens)
    querying._ENGINES.clear()
    assert bl.ops.fourlegs.run_query() == {"CANCELLED"}
    assert stages == ["loading the text encoder", "opening the language field"] and opened == []
    assert querying._ENGINES == {} and importer.source_key(obj) not in query_ops._LOCALIZERS
    assert not props.running and props.status == "cancelled" and not props.found and len(props.segments) == 0

    monkeypatch.setattr(query_ops.QueryJob, "on_open_progress", real_progress)
    assert bl.ops.fourlegs.run_query() == {"FINISHED"}  # nothing left half-open: the next run works
    assert opened == [1] and props.found and (props.segment_start, props.segment_end) == (1, 4)


def _ranked_bundle(path, label, active):
    from _blender_helpers import language_bundle

    language_bundle(path, T=6, N=200, query_label=label)
    lat = np.load(path / "language" / "latents.npy")
    lat[:, :, :] = [0.0, 1.0]
    lat[list(active), :100] = [1.0, 0.0]  # the label's Gaussians at these timesteps only
    np.save(path / "language" / "latents.npy", lat)
    return path


def test_find_best_scene_ranks_the_imported_scenes_and_selects_the_best(bl, tmp_path):
    from fourlegs_addon import importer, query_ops, querying
    from fourlegs_engine.query.multiscene import scene_relevance

    cube = _ranked_bundle(tmp_path / "cube", "red cube", active=(0, 1))
    ball = _ranked_bundle(tmp_path / "ball", "blue ball", active=(0, 1))
    objs = {}
    for path in (cube, ball):
        scene = importer.load_engine_scene(path)
        objs[path.name] = importer.import_scene(bl.context.scene, scene, source=str(path))
    props = bl.context.scene.fourlegs
    props.splat_object = objs["ball"]
    props.query = ""
    assert not bl.ops.fourlegs.find_best_scene.poll()  # needs a query
    props.query = "red cube"
    assert bl.ops.fourlegs.find_best_scene.poll()
    assert bl.ops.fourlegs.find_best_scene() == {"FINISHED"}
    want = {name: scene_relevance(querying.open_query_engine(importer.engine_scene_for(obj)), "red cube", 10)
            for name, obj in objs.items()}
    assert want["cube"] > want["ball"] and want["cube"] > 0  # the paper's stride 10 samples t=0 here
    for name, obj in objs.items():
        assert obj[query_ops.RELEVANCE_KEY] == pytest.approx(want[name])
    assert props.splat_object == objs["cube"] and objs["cube"].select_get() and not objs["ball"].select_get()
    assert bl.context.view_layer.objects.active == objs["cube"]
    assert props.status == f"best scene: {objs['cube'].name}" and not props.running
    from fourlegs_addon import panels

    log = []
    panels.FOURLEGS_PT_query.draw(type("P", (), {"layout": _Layout(log)})(), bl.context)
    assert "fourlegs.find_best_scene" in [a[0] for name, a, k in log if name == "operator"]
    # one scene only: nothing to rank
    bl.data.objects.remove(objs["ball"])
    assert not bl.ops.fourlegs.find_best_scene.poll()
