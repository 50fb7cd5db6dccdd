"""The interactive query path (the default): its defaults shared by every front end, the best view scored
at reduced size then confirmed, exact scores where the maps need them, the same answers as the exact
path (synthetic scene through the real pipeline; the real capture when its fitted field is present), and
the action centre inside its own box."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from fourlegs_engine.query import spatial
from fourlegs_engine.query.engine import QueryEngine, QueryOptions
from fourlegs_engine.query.viewpoint import best_view_confirmed

from _query_helpers import two_cluster_scene

Q = "a ball flying"
#: a language field of the real capture (built outside the repository, ~90 s to query both ways): opt-in
REAL_FIELD = Path(os.environ.get("FOURLEGS_REAL_FIELD", "/nonexistent"))


def test_defaults_are_the_interactive_path_in_every_front_end():
    from fourlegs_engine import highlight_job
    from fourlegs_engine.commands.main import build_parser

    o = QueryOptions()
    assert (o.path, o.spatial) == ("sketch", "fast") and o.codebook_refine > 0 and 0 < o.view_scale < 1
    e = QueryOptions.exact(dilation=2)
    assert (e.path, e.spatial, e.view_scale, e.dilation) == ("exact", "exact", 1.0, 2)
    args = build_parser().parse_args(["query", "scene", "text"])
    assert (args.path, args.sketch_rank, args.codebook_size, args.codebook_refine, args.spatial, args.view_scale,
            args.view_confirm) \
        == (o.path, o.sketch_rank, o.codebook_size, o.codebook_refine, o.spatial, o.view_scale, o.view_confirm)
    assert (highlight_job.DEFAULT_QUERY_PATH, highlight_job.DEFAULT_SPATIAL) == (o.path, o.spatial)
    job = highlight_job.HighlightJobOptions(query="x", output="out")
    assert (job.query_path, job.spatial) == (o.path, o.spatial)
    from fourlegs_addon import querying  # the panel: no copies of the engine's defaults

    assert querying.default_options() == o


def test_best_view_confirmed_rescoring_the_reduced_best_at_full_size():
    from fourlegs_engine.scene import Camera

    cams = [Camera.look_at((i, -4, 0), (0, 0, 0), width=8, height=6, fov_y=0.6, name=f"c{i}") for i in range(5)]
    reduced = {"c0": 0.30, "c1": 0.50, "c2": 0.49, "c3": 0.10, "c4": 0.48}
    full = {"c0": 0.31, "c1": 0.40, "c2": 0.45, "c3": 0.90, "c4": 0.44}
    calls = []

    def maps_of(batch, is_reduced):
        calls.extend((cam.name, is_reduced) for cam in batch)
        return [np.full((3, 4) if is_reduced else (6, 8), (reduced if is_reduced else full)[cam.name]) for cam in batch]

    res = best_view_confirmed(cams, maps_of, 7, confirm=3)
    # c3 is best at full size but ranked last at reduced size: only the 3 best reduced ones are confirmed
    assert res.best == "c2" and res.index == 2 and res.t == 7
    assert [c for c, r in calls if not r] == ["c1", "c2", "c4"] and sum(r for _, r in calls) == 5
    assert res.confirmed == ["c1", "c2", "c4"]
    assert res.scores["c2"] == pytest.approx(0.45) and res.scores["c3"] == pytest.approx(0.10)


def test_engine_best_view_renders_every_camera_reduced_and_the_confirmed_at_map_size():
    scene, field, enc, _ = two_cluster_scene(T=4, active=(1, 2), size=(64, 40))
    full = QueryEngine(scene, field, enc, QueryOptions.exact(spatial="fast"))
    coarse = QueryEngine(scene, field, enc, QueryOptions.exact(spatial="fast", view_scale=0.5, view_confirm=1))
    a, b = full.best_view(Q, 1), coarse.best_view(Q, 1)
    assert a.best == b.best == "close"
    assert coarse.stats["view_maps_reduced"] == 2 and coarse.stats["view_maps"] == 1
    assert full.stats["view_maps"] == 2 and full.stats["view_maps_reduced"] == 0
    assert b.scores["close"] == pytest.approx(a.scores["close"], abs=1e-6)  # the confirmed one: full size
    assert b.confirmed == ["close"] and a.confirmed == []


def _ring_of_views(scene, n: int) -> list:
    from fourlegs_engine.scene import Camera

    return [Camera.look_at((3.5 * np.sin(a), -3.5 * np.cos(a), 0.4), (0.3, 0, 0), width=40, height=30, fov_y=0.7,
                           name=f"v{i}") for i, a in enumerate(np.linspace(-1.2, 1.2, n))]


def test_views_rendered_on_several_threads_score_as_rendered_one_at_a_time():
    from fourlegs_engine.threads import kernel_threads

    scene, field, enc, _ = two_cluster_scene(T=4, active=(1, 2), size=(64, 40))
    cams = _ring_of_views(scene, 7)
    results, stats = [], []
    for threads in (1, 2, 3):
        eng = QueryEngine(scene, field, enc, QueryOptions.exact(spatial="fast", view_scale=0.5, view_confirm=2))
        with kernel_threads(threads):
            results.append(eng.best_view(Q, 1, cams))
        stats.append((eng.stats["view_maps_reduced"], eng.stats["view_maps"], eng.stats["render_relevancy"]))
    assert results[0].scores == results[1].scores == results[2].scores  # bit for bit: the same renders
    assert results[0].best == results[1].best == results[2].best and results[0].confirmed == results[2].confirmed
    assert len(set(results[0].scores.values())) > 3  # the views differ: the order of the maps matters
    assert stats[0] == stats[1] == stats[2] == (7, 2, 9)


def test_cancelling_while_views_render_on_threads_stops_the_search_and_leaves_the_engine_usable():
    from fourlegs_engine.errors import Cancelled
    from fourlegs_engine.threads import kernel_threads

    from fourlegs_engine.scene import CameraRig, Scene

    clusters, field, enc, _ = two_cluster_scene(T=4, active=(1, 2), size=(64, 40))
    cams = _ring_of_views(clusters, 12)
    scene = Scene(gaussians=clusters.gaussians, cameras=CameraRig.static(cams, [], 4), name="ring")
    eng = QueryEngine(scene, field, enc, QueryOptions.exact(spatial="fast", view_scale=0.5, view_confirm=2))
    stages = []

    def progress(fraction, stage):
        stages.append(stage)
        if stage.startswith("scoring the views") and len(stages) > 3:
            raise Cancelled("stopped by the test")

    with kernel_threads(2):
        with pytest.raises(Cancelled):
            eng.localize(Q, ("best_view",), t=1, progress=progress)
        rendered = eng.stats["render_relevancy"]
        assert rendered <= len(stages) + 2 < len(cams)  # at most two renders run ahead of the progress reports
        again = eng.best_view(Q, 1, cams)
    with kernel_threads(1):
        assert QueryEngine(scene, field, enc, QueryOptions.exact(spatial="fast", view_scale=0.5, view_confirm=2)
                           ).best_view(Q, 1, cams).scores == again.scores


def test_codebook_maps_score_the_gaussians_near_or_above_relevant_exactly(tmp_path):
    scene, field, enc, _ = two_cluster_scene(T=4, active=(1, 2))
    soft = dict(relevancy_scale=1.0)  # scores spread below saturation
    exact = QueryEngine(scene, field, enc, QueryOptions.exact(**soft))
    lookup = QueryEngine(scene, field, enc, QueryOptions(path="codebook", codebook_size=2, codebook_refine=0.0, **soft),
                         codebook_dir=tmp_path)
    refined = QueryEngine(scene, field, enc, QueryOptions(path="codebook", codebook_size=2, **soft),
                          codebook_dir=tmp_path)
    want = exact.gaussian_relevancy(Q, 1).numpy()
    coded = lookup.gaussian_relevancy(Q, 1).numpy()
    got = refined.gaussian_relevancy(Q, 1).numpy()
    assert np.abs(coded - want).max() > 1e-3  # two codes cannot hold the wiggled ball's scores
    near = coded > 0.4
    assert near.any() and (~near).any()
    np.testing.assert_allclose(got[near], want[near], atol=1e-6)
    np.testing.assert_array_equal(got[~near], coded[~near])
    assert refined.stats["rescored_latents"] == int(near.sum())


def test_action_centre_lies_inside_its_box_when_the_map_has_separate_blobs():
    r = np.zeros((40, 60))
    r[2:8, 40:50] = 0.95        # the best component: highest peak
    r[30:38, 5:25] = 0.7        # a large second blob far away
    focus, box = spatial.action_focus(r)
    centre = spatial.centre_of_mass(focus)
    x0, y0, x1, y1 = box
    assert box == (40, 2, 49, 7)
    assert x0 <= centre[0] <= x1 + 1 and y0 <= centre[1] <= y1 + 1
    np.testing.assert_allclose(centre, [45.0, 5.0])
    whole = spatial.centre_of_mass(r)  # the paper's whole-map centre lies between the blobs, in neither box
    assert not (x0 <= whole[0] <= x1 + 1 and y0 <= whole[1] <= y1 + 1)
    empty, none = spatial.action_focus(np.full((4, 4), 0.3))
    assert none is None and np.allclose(empty, 0.3)


def test_engine_action_centre_pixel_is_inside_its_box_at_reduced_scale():
    scene, field, enc, _ = two_cluster_scene(T=4, active=(1, 2), size=(64, 40))
    eng = QueryEngine(scene, field, enc, QueryOptions.exact(spatial="fast", resolution_scale=0.5))
    cam = scene.cameras.cameras(1, "all")[0]
    res = eng.action_centre(Q, 1, cam)
    x0, y0, x1, y1 = res.bbox
    assert x0 <= res.centre_px[0] <= x1 + 1 and y0 <= res.centre_px[1] <= y1 + 1


@pytest.mark.slow
def test_default_path_answers_as_the_exact_path_on_a_distilled_synthetic_scene(tmp_path):
    """Every scripted query of the tiny synthetic scene through the real pipeline (simulated encoder, lift):
    the default path's segments and peak equal the exact path's."""
    import shutil

    from fourlegs_engine.demo.synthetic import ensure_demo_bundle, read_queries
    from fourlegs_engine.pipeline import ensure_language_field, open_query_engine, text_encoder
    from fourlegs_engine.scene.bundle import load_bundle

    root = tmp_path / "tiny"
    shutil.copytree(ensure_demo_bundle("tiny"), root)
    scene = load_bundle(root)
    encoder = text_encoder(scene)
    scene = ensure_language_field(scene, encoder, progress=False)
    queries = list(read_queries(root))
    exact = open_query_engine(scene, encoder, options=QueryOptions.exact()).temporal_many(queries)
    fast = open_query_engine(scene, encoder)
    assert fast.path == "sketch" and fast.sketch_path.available
    for q, want in zip(queries, exact):
        got = fast.temporal(q)
        assert (got.segments, got.peak) == (want.segments, want.peak), q
    assert (root / "language" / f"sketch_{QueryOptions().sketch_rank}.npz").is_file()  # stored with the field


@pytest.mark.slow
@pytest.mark.skipif(not (REAL_FIELD / "language" / "latents.npy").is_file(),
                    reason="set FOURLEGS_REAL_FIELD to a language field of the real capture")
def test_default_path_answers_as_the_exact_path_on_the_real_capture(tmp_path):
    """The 150-timestep basketball capture: the default path (its index built into a scratch directory, the
    field is read-only) gives the exact path's segments and peak for every annotated phrase, "a person"
    (which matches everyone: its R_avg must be known to about 1e-6) included."""
    from fourlegs_engine.pipeline import open_query_engine, text_encoder
    from fourlegs_engine.scene.bundle import load_bundle

    scene = load_bundle(REAL_FIELD)
    encoder = text_encoder(scene)
    queries = [p for p in ("the ball in the air", "the ball", "a person holding the ball", "a person")
               if p in str(scene.language)]
    assert queries
    exact = open_query_engine(scene, encoder, options=QueryOptions.exact()).temporal_many(queries)
    fast = open_query_engine(scene, encoder, codebook_dir=tmp_path)
    for q, want in zip(queries, exact):
        got = fast.temporal(q)
        assert (got.segments, got.peak) == (want.segments, want.peak), q


def test_query_progress_bar_only_on_a_terminal(monkeypatch):
    import io
    import sys
    import time

    from fourlegs_engine.commands.query import stage_bar

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    for terminal, shown in ((Terminal(), True), (io.StringIO(), False)):
        monkeypatch.setattr(sys, "stderr", terminal)
        with stage_bar("query") as report:
            report(0.0, "scoring timesteps")
            time.sleep(0.6)  # the bar appears once the work has taken half a second
            report(0.5, "scoring timesteps")
            time.sleep(0.2)  # tqdm redraws at most every 0.1 s
            report(0.75, "rendering the views")
        text = terminal.getvalue()
        assert ("75%" in text and "rendering the views" in text) == shown, text
        assert shown or text == ""
