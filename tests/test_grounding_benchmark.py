"""Ground truth (visible masks, boxes, segments) and the grounding benchmark runner on the tiny scene."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from fourlegs_bench import grounding
from fourlegs_bench.baseline2d import ViewPrediction, inclusive_to_exclusive
from fourlegs_bench.ground_truth import (VISIBILITY_THRESHOLD, CoverageVideo, ensure_ground_truth,
                                               label_ids, scene_queries, segments_of, visible_masks)
from fourlegs_bench.metrics import METRIC_NAMES, mask_to_box
from fourlegs_engine.demo.synthetic import LABELS, SCRIPT, _frames_of, write_synthetic_bundle
from fourlegs_engine.render import rasterize
from fourlegs_engine.scene import load_bundle


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    return write_synthetic_bundle(tmp_path_factory.mktemp("gt") / "tiny", "tiny", 0)


@pytest.fixture(scope="module")
def scene_gt(bundle):
    scene = load_bundle(bundle)
    return scene, ensure_ground_truth(scene, scene.cameras.cameras(0, "test")[:1])  # one view: fast


def test_temporal_ground_truth_is_the_script(scene_gt):
    scene, gt = scene_gt
    T = scene.num_timesteps
    for query, labels in gt.labels.items():
        expected = np.zeros(T, bool)
        for action in SCRIPT:
            frames = _frames_of(action.start, action.end, T)
            if action.label in labels and frames:
                expected[frames[0]:frames[1] + 1] = True
        if labels == ["ball flying in the air"]:
            expected = np.array([LABELS.index(labels[0]) in scene.gaussians.labels[t] for t in range(T)])
        np.testing.assert_array_equal(gt.frames[query], expected, err_msg=query)
        assert gt.segments(query) == segments_of(expected)


def test_masks_are_visible_parts_of_the_labelled_gaussians(scene_gt):
    """A mask pixel is one where the labelled Gaussians, rendered alone, cover > 0.5 (occlusion can only
    remove pixels), masks are empty outside the temporal ground truth, and boxes are the masks' boxes."""
    scene, gt = scene_gt
    g = scene.gaussians
    for cam in scene.cameras.cameras(0, "test")[:1]:
        masks, boxes = gt.masks[cam.name], gt.boxes[cam.name]
        assert masks.shape == (scene.num_timesteps, len(gt.queries), cam.height, cam.width)
        occluded_somewhere = False
        for qi, query in enumerate(gt.queries):
            ids = label_ids(scene, gt.labels[query])
            for t in range(scene.num_timesteps):
                mask = np.asarray(masks[t, qi])
                if not gt.frames[query][t]:
                    assert not mask.any()
                    assert np.isnan(boxes[t, qi]).all()
                    continue
                box = mask_to_box(mask)
                if box is None:
                    assert np.isnan(boxes[t, qi]).all()
                else:
                    np.testing.assert_array_equal(boxes[t, qi], box)
                frame = g.at(t)
                sel = torch.from_numpy(np.isin(np.asarray(g.labels[t]), ids))
                alone = rasterize(frame.means[sel], frame.rotations[sel], frame.log_scales[sel],
                                  frame.opacity_logits[sel], cam, outputs=("alpha",))["alpha"][..., 0].numpy()
                assert not (mask & ~(alone > VISIBILITY_THRESHOLD - 1e-4)).any(), (query, t)
                occluded_somewhere |= bool(((alone > 0.9) & ~mask).any())
        assert occluded_somewhere  # people and the ball do hide each other


def test_visible_masks_threshold_is_strict():
    cov = torch.zeros(3, 2, 2)
    cov[0, 0, 0] = 0.5
    cov[0, 0, 1] = 0.3
    cov[1, 0, 1] = 0.3
    cov[2, 1, 1] = 0.51
    m = visible_masks(cov, [[0], [0, 1], [2], []])
    assert m[0].tolist() == [[False, False], [False, False]]
    assert m[1].tolist() == [[False, True], [False, False]]
    assert m[2].tolist() == [[False, False], [False, True]]
    assert not m[3].any()


def test_ground_truth_is_cached_in_the_bundle(scene_gt):
    scene, gt = scene_gt
    assert (scene.root / "ground_truth" / "meta.json").is_file()
    cams = scene.cameras.cameras(0, "test")[:1]
    videos = {c.name: CoverageVideo(scene, c) for c in cams}
    again = ensure_ground_truth(scene, cams, videos=videos)
    assert all(v.renders == 0 for v in videos.values())
    for name in gt.masks:
        np.testing.assert_array_equal(np.asarray(again.masks[name]), np.asarray(gt.masks[name]))
        np.testing.assert_array_equal(again.boxes[name], gt.boxes[name])
    segments = json.loads((scene.root / "ground_truth" / "temporal.json").read_text())
    assert set(segments["queries"]) == set(gt.queries)


# ---------------------------------------------------------------------------------------- runner
class _Oracle:
    """Predicts from the rendered label coverage itself: must score 100% on every metric."""

    name = "oracle"

    def __init__(self, ctx):
        self.ctx = ctx

    def predict_view(self, ctx, camera):
        scene = ctx.scene
        queries = scene_queries(scene)
        video = ctx.videos[camera.name]
        out = {}
        for q in ctx.queries:
            ids = label_ids(scene, queries[q])
            present = np.array([np.isin(np.asarray(scene.gaussians.labels[t]), ids).any()
                                for t in range(scene.num_timesteps)])

            def rmap(t, ids=ids):
                return video[t][ids].sum(0).numpy().astype(np.float64)

            def box(t, rmap=rmap):
                b = mask_to_box(rmap(t) > VISIBILITY_THRESHOLD)
                return np.full(4, np.nan) if b is None else b
            out[q] = ViewPrediction(frames=present, scores=present.astype(float), relevancy_map=rmap, box=box)
        return out


class _Nothing:
    name = "nothing"

    def __init__(self, ctx):
        pass

    def predict_view(self, ctx, camera):
        T = ctx.scene.num_timesteps
        return {q: ViewPrediction(np.zeros(T, bool), np.zeros(T), lambda t: None, lambda t: None)
                for q in ctx.queries}


@pytest.fixture(scope="module")
def registered():
    grounding.register_method("oracle (test)", _Oracle, replace=True)
    grounding.register_method("nothing (test)", _Nothing, replace=True)
    yield
    grounding._METHODS.pop("oracle (test)", None)
    grounding._METHODS.pop("nothing (test)", None)


def test_oracle_scores_perfectly_and_an_empty_prediction_scores_zero(scene_gt, registered):
    scene, gt = scene_gt
    res = grounding.run_grounding_benchmark(scene, ["oracle (test)", "nothing (test)"], views=["test00"])
    oracle, nothing = res["methods"]["oracle (test)"], res["methods"]["nothing (test)"]
    for q in gt.queries:
        for view in res["scene"]["views"]:
            masks_present = np.asarray(gt.masks[view][:, gt.queries.index(q)]).any(axis=(1, 2))
            expect_spatial = 1.0 if masks_present[gt.frames[q]].all() else None
            m = oracle["per_view"][view][q]
            assert m["tIoU"] == m["tRec"] == m["tPrec"] == m["tAP"] == 1.0
            if expect_spatial:
                assert m["vAP"] == pytest.approx(1.0) and m["vIoU"] == pytest.approx(1.0)
    for k in ("vAP", "vIoU", "tIoU", "tRec", "tPrec"):
        assert nothing[k]["mean"] == 0.0 and nothing[k]["std"] == 0.0
    # constant scores rank nothing: tAP is the share of ground-truth frames
    base_rate = np.mean([gt.frames[q].mean() for q in gt.queries])
    assert nothing["tAP"]["mean"] == pytest.approx(base_rate)
    assert oracle["tIoU"]["mean"] == 1.0


def test_tiny_benchmark_reports_the_2d_baseline(scene_gt, tmp_path, monkeypatch, capsys):
    """`fourlegs bench grounding --scene tiny` end to end on one view (kept short for the suite)."""
    from fourlegs_engine.commands.main import main
    monkeypatch.setenv("FOURLEGS_CACHE", str(tmp_path / "cache"))
    scene, _ = scene_gt
    out = tmp_path / "res.json"
    assert main(["bench", "grounding", "--bundle", str(scene.root), "--methods", "2D features",
                 "--views", "test00", "--pixel-stride", "3", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "| 2D features |" in text and "a ball flying in the air" in text
    res = json.loads(out.read_text())
    base = res["methods"]["2D features"]
    for k in METRIC_NAMES:
        assert 0.0 <= base[k]["mean"] <= 1.0 and base[k]["std"] == 0.0   # one view
    assert set(base["per_query"]) == set(res["queries"])
    # the baseline finds something real: the walking person is localized in time and space
    walk = base["per_query"]["a person walking"]
    assert walk["tIoU"]["mean"] > 0.3 and walk["vAP"]["mean"] > 0.2
    assert main(["bench", "grounding", "--bundle", str(scene.root), "--methods", "2D features",
                 "--json", str(out)]) == 2                                 # refuses to overwrite


def test_unknown_method_or_view_is_an_input_error(scene_gt):
    from fourlegs_engine.errors import InputError
    scene, _ = scene_gt
    with pytest.raises(InputError, match="unknown method"):
        grounding.run_grounding_benchmark(scene, ["no such method"])
    with pytest.raises(InputError, match="no camera"):
        grounding.run_grounding_benchmark(scene, ["2D features"], views=["cam99"])


def test_inclusive_boxes_convert_to_exclusive():
    np.testing.assert_array_equal(inclusive_to_exclusive((2, 3, 4, 5)), [2, 3, 5, 6])
    assert np.isnan(inclusive_to_exclusive(None)).all()


def test_stride_list_parsing_and_the_speed_accuracy_plot(tmp_path):
    from fourlegs_engine.errors import InputError
    assert grounding.parse_strides("1, 2,4") == [1, 2, 4]
    for bad in ("0", "a,b", ""):
        with pytest.raises(InputError):
            grounding.parse_strides(bad)
    metric = {"mean": 0.5, "std": 0.1}
    results = {"scene": {"name": "s", "views": ["v"], "num_timesteps": 3},
               "methods": {f"2D features (pixel stride {k})": {**{m: metric for m in METRIC_NAMES},
                                                              "seconds": float(k), "per_query": {}}
                           for k in (1, 2)}}
    grounding.plot_speed_accuracy(results, tmp_path / "p.png")
    assert (tmp_path / "p.png").stat().st_size > 1000
    table = grounding.markdown_tables(results)
    assert "| 2D features (pixel stride 2) | 50.0 ± 10.0 |" in table


def test_tiled_ground_truth_stretches_each_segment_over_the_repeated_timesteps(bundle):
    from fourlegs_bench.ground_truth import temporal_ground_truth
    from fourlegs_bench.query_speed_tiled import tiled_ground_truth

    scene = load_bundle(bundle)
    T0 = scene.num_timesteps
    T = 2 * T0 + 3
    queries = list(scene_queries(scene))
    frames = temporal_ground_truth(scene)
    tiled = tiled_ground_truth(scene, queries, T)
    for q in queries:
        assert tiled[q].shape == (T,) and tiled[q].dtype == bool
        source, stretched = segments_of(np.asarray(frames[q])), segments_of(tiled[q])
        assert len(stretched) == len(source)  # no segment lost or split
        for (a, b), (a0, b0) in zip(stretched, source):
            # the nearest source timestep of each end is the source segment's end
            assert round(a * (T0 - 1) / (T - 1)) == a0 and round(b * (T0 - 1) / (T - 1)) == b0
            assert (b - a + 1) >= 2 * (b0 - a0 + 1) - 2
