"""QueryEngine on a small real scene: exact vs codebook vs float64 oracle, spatial answers, stats."""
from __future__ import annotations

import numpy as np
import pytest

from fourlegs_engine.errors import InputError
from fourlegs_engine.query import maps as maps_module
from fourlegs_engine.query.engine import QueryEngine, QueryOptions
from fourlegs_engine.query.lerf import relevancy_reference
from fourlegs_engine.query.temporal import localize_relevancy

from _query_helpers import CANON, two_cluster_scene

Q = "a ball flying"


@pytest.fixture(scope="module")
def setup():
    return two_cluster_scene()


def oracle_relevancy(field, enc, text):
    lat = np.asarray(field.latents, dtype=np.float64)
    T, N, d = lat.shape
    feats = field.decode64(lat.reshape(-1, d))
    q = enc.encode_text([text])[0].double().numpy()
    canon = enc.encode_text(list(CANON)).double().numpy()
    return relevancy_reference(feats, q, canon).reshape(T, N)


def test_exact_temporal_matches_float64_oracle(setup):
    scene, field, enc, _ = setup
    eng = QueryEngine(scene, field, enc, QueryOptions.exact(dilation=0, chunk=17))
    res = eng.temporal(Q)
    ref = localize_relevancy(oracle_relevancy(field, enc, Q), dilation=0)
    np.testing.assert_allclose(res.scores, ref.scores, atol=1e-12)
    assert res.segment == ref.segment == (1, 2) and res.peak == 1 and res.found and res.undecided == []
    assert eng.stats["decoded_latents"] == scene.num_timesteps * scene.num_gaussians
    np.testing.assert_allclose(eng.gaussian_relevancy(Q, 1).numpy(), oracle_relevancy(field, enc, Q)[1],
                               atol=2e-3)
    # the per-Gaussian scores of the temporal pass are reused, not decoded again, and equal a fresh decode
    assert eng.stats["decoded_latents"] == scene.num_timesteps * scene.num_gaussians
    fresh = QueryEngine(scene, field, enc, QueryOptions.exact(chunk=17))
    for t in range(scene.num_timesteps):
        np.testing.assert_array_equal(eng.gaussian_relevancy(Q, t).numpy(), fresh.gaussian_relevancy(Q, t).numpy())
    assert fresh.stats["decoded_latents"] == scene.num_timesteps * scene.num_gaussians


def test_codebook_path_equals_exact_and_never_decodes_latents(setup, tmp_path):
    scene, field, enc, _ = setup
    exact = QueryEngine(scene, field, enc, QueryOptions.exact()).temporal(Q)
    eng = QueryEngine(scene, field, enc, QueryOptions(path="codebook", codebook_size=256, codebook_refine=0.0), codebook_dir=tmp_path)
    res = eng.temporal(Q)
    np.testing.assert_allclose(res.scores, exact.scores, atol=1e-12)
    assert res.segment == exact.segment == (0, 3)  # dilation 1 reaches both ends
    assert eng.stats["decoded_latents"] == 0 and eng.stats["decoded_codes"] == 256
    assert (tmp_path / "codebook_256.npz").is_file() and (tmp_path / "codes_256.npy").is_file()
    again = QueryEngine(scene, field, enc, QueryOptions(path="codebook", codebook_size=256, codebook_refine=0.0), codebook_dir=tmp_path)
    again.temporal(Q)
    assert np.array_equal(np.asarray(again.codebook.codes), np.asarray(eng.codebook.codes))


def test_forget_query_redoes_the_query_s_own_work_only(setup):
    scene, field, enc, _ = setup
    eng = QueryEngine(scene, field, enc, QueryOptions.exact())
    first = eng.temporal(Q)
    eng.gaussian_relevancy(Q, 1)
    eng.gaussian_relevancy("object", 1)
    decoded, encoded = eng.stats["decoded_latents"], enc.calls
    eng.gaussian_relevancy(Q, 2)  # cached by the temporal pass: nothing decoded
    assert eng.stats["decoded_latents"] == decoded
    eng.forget_query(Q)
    eng.gaussian_relevancy(Q, 2)
    assert eng.stats["decoded_latents"] == decoded + scene.num_gaussians  # decoded again
    eng.gaussian_relevancy("object", 1)  # another query's cache is kept
    assert eng.stats["decoded_latents"] == decoded + scene.num_gaussians
    again = eng.temporal(Q)
    np.testing.assert_array_equal(again.scores, first.scores)
    assert enc.calls == encoded  # the text embedding is kept


def test_temporal_stride_and_many_queries(setup):
    scene, field, enc, _ = setup
    eng = QueryEngine(scene, field, enc, QueryOptions.exact(dilation=0))
    many = eng.temporal_many([Q, "a person jumping", "object"])
    assert eng.stats["decoded_latents"] == scene.num_timesteps * scene.num_gaussians
    np.testing.assert_allclose(many[0].scores, eng.temporal(Q).scores)
    assert not many[2].found and "not found" in many[2].message  # the query is a canonical phrase
    strided = eng.temporal(Q, stride=2)
    assert list(strided.timesteps) == [0, 2] and len(strided.scores) == 4


def test_not_found_is_finite(setup):
    scene, field, enc, _ = setup
    res = QueryEngine(scene, field, enc, QueryOptions.exact()).temporal("texture")
    assert not res.found and res.segment is None and np.all(res.scores == 0)
    assert res.to_dict()["peak"] is None


def test_spatial_maps_centre_view_and_stats(setup):
    scene, field, enc, _ = setup
    for spatial in ("exact", "fast"):
        eng = QueryEngine(scene, field, enc, QueryOptions.exact(spatial=spatial))
        wide = scene.cameras.find("wide")
        maps = eng.relevancy_map(Q, wide, 1)
        rel = maps["relevancy"]
        assert rel.shape == (32, 48) and np.all(np.isfinite(rel)) and rel.min() >= 0 and rel.max() <= 1
        # cluster A (x=+0.6) projects to the right half of the wide view
        uv, _ = wide.project(np.array([[0.6, 0, 0]]))
        centre = eng.action_centre(Q, 1, wide)
        assert abs(centre.centre_px[0] - uv[0, 0]) < 4 and abs(centre.centre_px[1] - uv[0, 1]) < 4
        assert np.linalg.norm(centre.centre_3d - [0.6, 0, 0]) < 0.3
        x0, y0, x1, y1 = centre.bbox
        assert x0 <= uv[0, 0] <= x1 + 1 and x0 > 17  # cluster B (u ~ 16) is not in the box
        view = eng.best_view(Q, 1)
        assert view.best == "close" and view.scores["close"] > view.scores["wide"]
        assert eng.stats["render_features" if spatial == "exact" else "render_relevancy"] == 4  # map, centre, 2 views
        assert eng.stats["render_relevancy" if spatial == "exact" else "render_features"] == 0
    # at a timestep where nothing is relevant the fast and exact maps both stay low
    low = QueryEngine(scene, field, enc, QueryOptions.exact(spatial="exact")).relevancy_map(Q, wide, 0)["relevancy"]
    assert low.max() <= 0.5  # background decodes to the zero vector: exactly 0.5, not relevant


def test_exact_map_decodes_the_empty_pixels_once_and_equals_decoding_every_pixel(setup):
    import torch

    scene, field, enc, _ = setup
    eng = QueryEngine(scene, field, enc, QueryOptions.exact(spatial="exact"))
    wide = scene.cameras.find("wide")
    got = eng.relevancy_map(Q, wide, 1, outputs=("relevancy", "alpha"))
    H, W = got["alpha"].shape
    empty = int((got["alpha"] == 0).sum())
    assert 0 < empty < H * W and eng.stats["decoded_pixels"] == H * W - empty + 1
    lat = torch.from_numpy(np.asarray(field.latents[1], dtype=np.float32))
    pix = eng.maps.rasterize(1, wide, lat, ("features", "alpha"))["features"].reshape(H * W, -1)
    want = eng.scorer.score_latents_many(pix, eng.embed_query(Q)[None])[:, 0].reshape(H, W).clamp(0, 1).numpy()
    np.testing.assert_array_equal(got["relevancy"], want)


def test_fast_and_exact_maps_agree_on_the_relevant_region(setup):
    scene, field, enc, _ = setup
    cam = scene.cameras.find("close")
    ex = QueryEngine(scene, field, enc, QueryOptions.exact()).relevancy_map(Q, cam, 2)
    fa = QueryEngine(scene, field, enc, QueryOptions.exact(spatial="fast")).relevancy_map(Q, cam, 2)
    np.testing.assert_allclose(ex["alpha"], fa["alpha"], atol=1e-6)
    solid = ex["alpha"] > 0.95
    assert solid.any()
    assert np.mean(np.abs(ex["relevancy"] - fa["relevancy"])[solid]) < 0.1
    half = QueryEngine(scene, field, enc, QueryOptions.exact(resolution_scale=0.5)).relevancy_map(Q, cam, 2)
    assert half["relevancy"].shape == (16, 24)


def test_localize_computes_only_what_is_needed(setup):
    scene, field, enc, _ = setup
    eng = QueryEngine(scene, field, enc, QueryOptions.exact(spatial="fast"))
    loc = eng.localize(Q, {"temporal"})
    assert loc.temporal.found and loc.best_view is None and loc.action_centre is None
    assert eng.stats["relevancy_map"] == 0 and eng.stats["best_view"] == 0
    eng.stats.clear()
    loc = eng.localize(Q, {"best_view"}, t=2)
    assert loc.temporal is None and loc.best_view == "close" and loc.action_centre is None
    assert eng.stats["temporal"] == 0 and eng.stats["action_centre"] == 0 and eng.stats["best_view"] == 1
    eng.stats.clear()
    loc = eng.localize(Q, {"temporal", "best_view", "action_centre"})
    assert loc.t == loc.temporal.peak and loc.best_view == "close" and loc.action_centre is not None
    d = loc.to_dict()
    import json
    json.dumps(d, allow_nan=False)
    with pytest.raises(InputError):
        eng.localize(Q, {"everything"})


def test_empty_scene_and_single_timestep():
    scene, field, enc, _ = two_cluster_scene(T=1, active=(0,))
    res = QueryEngine(scene, field, enc, QueryOptions.exact()).temporal(Q)
    assert res.found and res.segment == (0, 0) and res.scores.tolist() == [1.0]
    empty, efield, enc, _ = two_cluster_scene(T=3, n_per=0)
    eng = QueryEngine(empty, efield, enc, QueryOptions.exact(spatial="fast"))
    res = eng.temporal(Q)
    assert not res.found and "no Gaussians" in res.message and np.all(res.scores == 0)
    m = eng.relevancy_map(Q, empty.cameras.find("wide"), 0)
    assert np.all(np.isfinite(m["relevancy"])) and np.all(m["alpha"] == 0)
    loc = eng.localize(Q, {"temporal", "best_view", "action_centre"})
    assert loc.best_view is None and loc.messages
    cb = QueryEngine(empty, efield, enc, QueryOptions(path="codebook", codebook_size=16, codebook_refine=0.0), codebook_dir=None)
    assert not cb.temporal(Q).found


def test_negative_phrases_suppress_an_absent_query(setup):
    scene, field, enc, dirs = setup
    enc.table["a dog"] = 0.6 * dirs[4] + 0.8 * dirs[7]  # close to the ball, but not it
    plain = QueryEngine(scene, field, enc, QueryOptions.exact()).gaussian_relevancy("a dog", 1)
    enc.table["a ball"] = dirs[4]
    neg = QueryEngine(scene, field, enc, QueryOptions.exact(negatives=["a ball"])).gaussian_relevancy("a dog", 1)
    assert plain.max() > 0.5 and neg.max() < 0.5


@pytest.mark.parametrize("stride", [1, 2])
def test_codebook_refine_full_margin_decides_as_the_exact_path(setup, tmp_path, stride):
    scene, field, enc, _ = setup
    exact = QueryEngine(scene, field, enc, QueryOptions.exact(temporal_stride=stride)).temporal(Q)
    coarse = QueryEngine(scene, field, enc, QueryOptions(path="codebook", codebook_size=2, temporal_stride=stride, codebook_refine=1.0, codebook_samples=10 ** 9), codebook_dir=tmp_path)
    res = coarse.temporal(Q)
    np.testing.assert_array_equal(res.positive, exact.positive)
    assert res.segment == exact.segment and res.r_avg == pytest.approx(exact.r_avg, abs=1e-6)
    assert res.num_relevant == exact.num_relevant
    T, N = scene.num_timesteps, scene.num_gaussians
    scored = len(range(0, T, stride))
    assert coarse.stats["sampled_latents"] == scored * N  # every pair, at the scored timesteps only
    assert coarse.stats["rescored_latents"] <= scored * N
    again = QueryEngine(scene, field, enc, QueryOptions(path="codebook", codebook_size=2, temporal_stride=stride, codebook_refine=1.0, codebook_samples=10 ** 9), codebook_dir=tmp_path).temporal(Q)
    np.testing.assert_array_equal(again.scores, res.scores)  # the same answer every time


def test_codebook_refine_samples_at_the_scored_timesteps_only(setup, tmp_path):
    scene, field, enc, _ = setup
    eng = QueryEngine(scene, field, enc, QueryOptions(path="codebook", codebook_size=2, temporal_stride=2, codebook_refine=0.05), codebook_dir=tmp_path)
    T, N = scene.num_timesteps, scene.num_gaussians
    ts = np.arange(0, T, 2)
    seen = []
    score_any_rows = eng.scorer.score_any_rows
    eng.scorer.score_any_rows = lambda q, flat, window=None: seen.append(flat) or score_any_rows(q, flat, window)
    (codes_a, scores_a, controls_a), (codes_b, scores_b, _) = eng.codebook_path.sample_members(
        Q, [np.array([0]), np.array([1])], [7, 5], ts, np.random.default_rng(0))
    assert controls_a is None  # strided: a code is its members' mean over every timestep, not the scored ones
    assert len(seen) == 1  # both groups decoded in one batch
    flat = np.sort(seen[0])
    assert len(scores_a) == len(codes_a) == 7 and len(scores_b) == len(codes_b) == 5 and len(np.unique(flat)) == 12
    assert np.isin(flat // N, ts).all() and (codes_a == 0).all() and (codes_b == 1).all()
    codes = np.asarray(eng.codebook.codes).reshape(-1)
    np.testing.assert_array_equal(np.sort(codes[flat]), np.sort(np.concatenate([codes_a, codes_b])))
    exact = QueryEngine(scene, field, enc, QueryOptions.exact())
    full = {(int(t), int(g)): exact.gaussian_relevancy(Q, int(t)).double().numpy()[g]
            for t, g in zip(*np.divmod(flat, N))}
    assert sorted(np.round(np.concatenate([scores_a, scores_b]), 6)) == sorted(np.round(list(full.values()), 6))
    flat, _ = eng.codebook.sample_members(np.arange(2), 10 ** 9, np.random.default_rng(1))
    np.testing.assert_array_equal(np.sort(flat), np.arange(T * N))  # every member when they fit
    seen.clear()
    [(codes_all, _, _)] = eng.codebook_path.sample_members(Q, [np.arange(2)], [len(ts) * N], ts, np.random.default_rng(2))
    np.testing.assert_array_equal(np.sort(seen[0]), np.flatnonzero(np.isin(np.arange(T * N) // N, ts)))
    with pytest.raises(InputError, match="samples"):
        QueryEngine(scene, field, enc, QueryOptions(path="codebook", codebook_refine=0.1, codebook_samples=1))


def test_codebook_refine_margin_zero_decodes_nothing_and_bad_margin_is_refused(setup, tmp_path):
    scene, field, enc, _ = setup
    eng = QueryEngine(scene, field, enc, QueryOptions(path="codebook", codebook_size=2, codebook_refine=0.0), codebook_dir=tmp_path)
    eng.temporal(Q)
    assert eng.stats["rescored_latents"] == 0 and eng.stats["decoded_latents"] == 0
    for bad in (-0.1, 2.0, float("nan")):
        with pytest.raises(InputError, match="refine"):
            QueryEngine(scene, field, enc, QueryOptions(path="codebook", codebook_refine=bad))


def test_codebook_refine_on_a_memmapped_field_reads_the_same_rows(setup, tmp_path):
    from _query_helpers import LinearField

    scene, field, enc, _ = setup
    np.save(tmp_path / "latents.npy", np.asarray(field.latents, dtype=np.float16))
    mm = np.load(tmp_path / "latents.npy", mmap_mode="r")
    mapped = LinearField(mm, field.weight.numpy())
    eng = QueryEngine(scene, mapped, enc, QueryOptions(path="codebook", codebook_size=3, codebook_refine=1.0, codebook_samples=10 ** 9), codebook_dir=tmp_path)
    assert eng.scorer.rows().path == str(tmp_path / "latents.npy")  # read from the file, not the mapping
    exact = QueryEngine(scene, mapped, enc, QueryOptions.exact()).temporal(Q)
    res = eng.temporal(Q)
    np.testing.assert_array_equal(res.positive, exact.positive)
    assert res.r_avg == pytest.approx(exact.r_avg, abs=1e-6)
    assert res.segment == exact.segment


def _mapped_rss_kb(path) -> int:
    """Resident kB of this process's mappings of ``path`` (/proc/self/smaps)."""
    total, current = 0, None
    with open("/proc/self/smaps") as f:
        for line in f:
            head = line.split()
            if "-" in head[0] and len(head) >= 5 and ":" in head[3]:  # a mapping's header line
                current = head[5] if len(head) > 5 else None
            elif head[0] == "Rss:" and current == str(path):
                total += int(head[1])
    return total


@pytest.mark.skipif(not __import__("os").path.exists("/proc/self/smaps"), reason="needs Linux /proc")
def test_scattered_exact_reads_do_not_stay_resident(tmp_path):
    # the kernel maps cached pages around every faulting row; a re-scoring query reading thousands of
    # scattered rows through the mapping would keep ~64 kB resident per row (here the whole 20 MB file)
    from _query_helpers import LinearField
    from fourlegs_bench.query_fixtures import flat_scene, warm_page_cache

    T, N, d = 4, 40_000, 64
    rng = np.random.default_rng(0)
    path = tmp_path / "latents.npy"
    np.save(path, rng.normal(size=(T, N, d)).astype(np.float16))  # 20 MB
    warm_page_cache(path)
    mm = np.load(path, mmap_mode="r")
    field = LinearField(mm, rng.normal(size=(d, 16)).astype(np.float32))
    _, _, enc, _ = two_cluster_scene(D=16)
    eng = QueryEngine(flat_scene(T, N), field, enc, QueryOptions(path="codebook", codebook_size=4, codebook_refine=0.01))
    flat = np.sort(rng.choice(T * N, size=4000, replace=False))
    got = eng.scorer.score_pairs(Q, flat)
    assert _mapped_rss_kb(path) < 1024
    t_of, g_of = np.divmod(flat, N)
    want = eng.scorer.score_latents(np.asarray(mm[t_of, g_of], dtype=np.float32), eng.embed_query(Q)).double().numpy()
    np.testing.assert_array_equal(got, want)


def test_localize_reports_progress_per_timestep_and_stops_when_the_callback_raises(setup):
    from fourlegs_engine.errors import Cancelled

    scene, field, enc, _ = setup
    eng = QueryEngine(scene, field, enc, QueryOptions.exact(spatial="fast"))
    seen = []
    loc = eng.localize(Q, {"temporal", "best_view", "action_centre"}, progress=lambda f, s: seen.append((f, s)))
    plain = QueryEngine(scene, field, enc, QueryOptions.exact(spatial="fast")).localize(Q, {"temporal", "best_view",
                                                                                     "action_centre"})
    assert loc.temporal.segment == plain.temporal.segment and loc.best_view == plain.best_view
    fractions = [f for f, _ in seen]
    assert fractions == sorted(fractions) and 0.0 <= fractions[0] and fractions[-1] <= 1.0
    per_timestep = [f for f, s in seen if s == "scoring timesteps"]
    assert len(per_timestep) == scene.num_timesteps  # one call before each scored timestep
    assert sum(s == "rendering the views" for _, s in seen) == len(eng.cameras_at(loc.t))

    calls = []

    def cancel_at_third(fraction, stage):
        calls.append(stage)
        if calls.count("scoring timesteps") == 3:
            raise Cancelled("stop")

    eng.stats.clear()
    with pytest.raises(Cancelled):
        eng.localize(Q, {"temporal", "best_view"}, progress=cancel_at_third)
    assert eng.stats["decoded_latents"] == 2 * scene.num_gaussians  # stopped inside the temporal pass
    assert eng.stats["best_view"] == 0
    assert eng._progress is None  # a later call without a callback is not stopped
    assert eng.localize(Q, {"temporal"}).temporal.segment == plain.temporal.segment


def test_codebook_refined_temporal_pass_can_be_cancelled(setup, tmp_path):
    from fourlegs_engine.errors import Cancelled

    scene, field, enc, _ = setup
    eng = QueryEngine(scene, field, enc, QueryOptions(path="codebook", codebook_size=2, codebook_refine=1.0,
                                                      codebook_samples=10 ** 9), codebook_dir=tmp_path)

    def cancel(fraction, stage):
        if stage == "re-scoring the uncertain Gaussians":
            raise Cancelled("stop")

    with pytest.raises(Cancelled):
        eng.localize(Q, {"temporal"}, progress=cancel)
    assert eng.stats["rescored_latents"] == 0


@pytest.mark.parametrize("chunk", [17, 4096])
def test_temporal_on_concurrent_streams_equals_one_stream(setup, chunk):
    """Two torch threads score the timesteps on two streams; one thread scores them one by one: the
    per-Gaussian scores, the answer and the counted work (decodes, text encodings) are the same."""
    import torch

    from fourlegs_engine.threads import torch_threads
    scene, field, enc, _ = setup
    queries = [Q, "object"]
    answers, engines, encodings = {}, {}, {}
    for threads in (1, 2):
        eng = QueryEngine(scene, field, enc, QueryOptions.exact(chunk=chunk))
        calls = enc.calls
        with torch_threads(threads):
            answers[threads] = eng.temporal_many(queries)
            assert torch.get_num_threads() == threads  # the streams restore the thread count
        encodings[threads] = (enc.calls - calls, eng.stats["encode_text"])
        assert eng.stats["decoded_latents"] == scene.num_timesteps * scene.num_gaussians
        engines[threads] = eng
    assert encodings[1] == encodings[2] == (3, 3)  # each query, then the canonical phrases, once
    for one, two in zip(answers[1], answers[2]):
        np.testing.assert_array_equal(one.scores, two.scores)
        assert one.segment == two.segment and one.peak == two.peak
    for q in queries:
        for t in range(scene.num_timesteps):
            np.testing.assert_array_equal(engines[1].temporal_pass.scores_at(q, t), engines[2].temporal_pass.scores_at(q, t))


@pytest.mark.parametrize("t", [0, 1])
def test_relevant_only_maps_give_the_full_maps_relevant_part_and_the_same_best_view(setup, t, monkeypatch):
    """Only the Gaussians touching the relevant ones' box are rendered: above 0.5 the map is the full
    map's (the same Gaussians, blended in the same order), elsewhere both stay at most 0.5; so the best
    view and its relevant-mass scores equal the full maps'. At t = 0 nothing is relevant: the views'
    scores are all 0 and the search falls back to the whole maps' mean. (Half of this scene's Gaussians
    are the subject: the share above which the whole frame is rendered is lifted for the test.)"""
    scene, field, enc, _ = setup
    if t == 1:
        whole = QueryEngine(scene, field, enc, QueryOptions.exact(spatial="fast"))
        whole.maps.relevancy_maps([Q], scene.cameras.cameras(t, "all")[0], t, outputs=("relevancy",),
                                  relevant_only=True)
        assert whole.stats["relevant_only_maps"] == 0   # a subject of half the Gaussians: the whole frame
    monkeypatch.setattr(maps_module, "REGION_MAX_SHARE", 1.0)
    eng = QueryEngine(scene, field, enc, QueryOptions.exact(spatial="fast"))
    for cam in scene.cameras.cameras(t, "all"):
        full = eng.maps.relevancy_maps([Q], cam, t, outputs=("relevancy",))["relevancy"][0]
        part = eng.maps.relevancy_maps([Q], cam, t, outputs=("relevancy",), relevant_only=True)["relevancy"][0]
        np.testing.assert_allclose(np.clip(part - 0.5, 0, None), np.clip(full - 0.5, 0, None), atol=1e-6)
        assert part.max() <= 1.0 and (part[full <= 0.5] <= 0.5 + 1e-6).all()
    assert eng.stats["relevant_only_maps"] == len(scene.cameras.cameras(t, "all"))
    view = eng.best_view(Q, t)
    full_maps = {c.name: eng.maps.relevancy_maps([Q], c, t, outputs=("relevancy",))["relevancy"][0]
                 for c in scene.cameras.cameras(t, "all")}
    score = "relevant" if t == 1 else "mean"
    want = {n: float(np.clip(m.astype(np.float64) - 0.5, 0, None).mean()) if score == "relevant"
            else float(m.astype(np.float64).mean()) for n, m in full_maps.items()}
    assert view.best == max(want, key=want.get)
    assert view.scores == pytest.approx(want, abs=1e-7)


def test_relevant_only_maps_skip_the_gaussians_away_from_the_relevant_region(setup):
    scene, field, enc, _ = setup
    eng = QueryEngine(scene, field, enc, QueryOptions.exact(spatial="fast"))
    wide = scene.cameras.cameras(1, "all")[0]
    relevant = eng.gaussian_relevancy(Q, 1) > 0.5
    touching = eng.maps.touching_relevant(1, wide, relevant)
    n = scene.num_gaussians // 2
    assert bool(relevant[:n].all()) and not bool(relevant[n:].any())   # blob A is the ball at t = 1
    assert bool(touching[:n].all()) and int(touching[n:].sum()) < n // 4  # blob B, 1.2 m away, left out
