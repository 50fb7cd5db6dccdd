"""The 4D grounding method and the accuracy-time bench pieces on small inputs."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch

from fourlegs_bench.accuracy_time import CastField, hold_fill, markdown_table, pareto_plot
from fourlegs_bench.grounding import method_names, score_view
from fourlegs_bench.method4d import FourLegsMethod
from fourlegs_engine.fileio import save_npy_atomic

from _query_helpers import two_cluster_scene

Q = "a ball flying"


def test_4d_method_is_registered_and_predicts_per_view():
    assert "4D (4-LEGS)" in method_names()
    scene, field, enc, _ = two_cluster_scene(T=6, active=(2, 3))
    ctx = SimpleNamespace(scene=scene, queries=[Q, "a person jumping"], text_encoder=enc, video_encoder=None,
                          progress=False)
    method = FourLegsMethod(ctx, field=field, spatial="fast", dilation=0)
    cam = scene.cameras.find("close")
    preds = method.predict_view(ctx, cam)
    p = preds[Q]
    assert p.frames.tolist() == [False, False, True, True, False, False]
    rel = p.relevancy_map(2)
    assert rel.shape == (cam.height, cam.width) and rel.max() > 0.9
    box = p.box(2)
    assert np.all(np.isfinite(box)) and box[2] > box[0]
    # the same answer in time for every view (volumetric), computed once
    assert method.predict_view(ctx, scene.cameras.find("wide"))[Q].frames.tolist() == p.frames.tolist()
    assert method.engine.stats["temporal_many"] == 1
    gt_frames = np.zeros(6, bool)
    gt_frames[2:4] = True
    masks = np.zeros((6, cam.height, cam.width), bool)
    masks[2:4] = rel > 0.5
    boxes = np.full((6, 4), np.nan)
    boxes[2:4] = box
    m = score_view(p, gt_frames, masks, boxes)
    assert m["tIoU"] == 1.0 and m["vAP"] > 0.99 and m["vIoU"] > 0.99


def test_cast_field_decodes_close_to_float32():
    _, field, _, _ = two_cluster_scene(T=2, active=(1,))

    class Wrapped:  # give the linear test field a module decoder, like the real field
        latents, canonical_phrases, encoder_name = field.latents, field.canonical_phrases, "t"
        decoder = torch.nn.Linear(8, 16, bias=False)
        decoder.weight.data = field.weight.T.clone()

    half = CastField(Wrapped, torch.bfloat16)
    z = torch.tensor(np.asarray(field.latents[0], dtype=np.float32))
    out = half.decode(z)
    assert out.dtype == torch.float32
    np.testing.assert_allclose(out.numpy(), (z @ field.weight).numpy(), atol=3e-2)


def test_hold_fill_uses_nearest_distilled_timestep(tmp_path):
    files = {}
    for t in (0, 4):
        files[t] = tmp_path / f"t{t}.npy"
        save_npy_atomic(files[t], np.full((3, 2), t, np.float16))
    held = hold_fill(files, 7, tmp_path / "held.npy")
    assert held.shape == (7, 3, 2)
    assert [int(held[t, 0, 0]) for t in range(7)] == [0, 0, 0, 4, 4, 4, 4]


def test_table_and_pareto_plot(tmp_path):
    metric = {k: {"mean": v, "std": 0.01} for k, v in zip(("vAP", "vIoU", "tIoU", "tRec", "tPrec", "tAP"),
                                                           (0.5, 0.3, 0.6, 0.7, 0.8, 0.9))}
    rows = [{"group": g, "name": n, "note": "", "precompute_s": 0.0, "seconds": s, "temporal_s": 0.1,
             "maps_s": s - 0.1, "metrics": metric, "distill_s_per_timestep": None}
            for g, n, s in (("reference", "exact", 10.0), ("codebook", "codebook K=256", 2.0),
                            ("distill", "lift", 5.0))]
    report = {"scene": {"name": "s", "num_gaussians": 10, "num_timesteps": 4, "views": ["a"], "queries": ["q"]},
              "torch_threads": 1, "metrics": ["vAP", "vIoU", "tIoU", "tRec", "tPrec", "tAP"], "rows": rows}
    table = markdown_table(report)
    assert table.count("\n| ") >= 4 and "50.0 ± 1.0" in table and "hold the nearest" in table
    png = pareto_plot(report, tmp_path / "p.png")
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_query_speed_bench_runs_small(tmp_path):
    from fourlegs_bench.query_speed import markdown, run_query_speed

    rep = run_query_speed(gaussians=300, timesteps=3, codebook_sizes=[16], repeats=2, exact_timesteps=0,
                          spatial_scene="none", workdir=tmp_path, progress=False, refine_margins=(0.0, 0.01),
                          rescore_share=0.1, sample_count=50)
    paths = [r["path"] for r in rep["rows"]]
    assert paths == ["codebook K=16", "codebook K=16 + exact re-scoring ±0.01 (lookup + 50 sampled + 10% of the "
                     "field re-scored, timed)", "exact"]
    cb, refined, exact = rep["rows"]
    assert cb["decoded_latents"] == 0 and cb["query_s"] >= 0 and not exact["extrapolated"]
    # whole codes are re-scored until the share is reached: at least 10% of the 900 (t, g) pairs
    assert 90 <= refined["forced_rescored_latents"] < 900 and refined["query_s"] >= refined["forced_rescore_s"] > 0
    assert refined["forced_sampled_latents"] == 50
    assert refined["rescored_latents_per_query"] == refined["sampled_latents_per_query"] == 0  # timed as lookups
    # the query rows ran in a fresh process: their peak RSS is theirs, not the benchmark's
    assert cb["rss_scope"] == "query process" and exact["rss_scope"] == "whole benchmark process"
    assert "| codebook K=16 |" in markdown(rep)


def test_skipped_groups_are_not_distilled(tmp_path, monkeypatch):
    """--skip knn: the kNN rows are not distilled at all (not distilled and then dropped)."""
    import fourlegs_engine.language.distill as distill_mod
    from fourlegs_bench.accuracy_time import _distill_variants

    calls = []

    def fake_distill(scene, *, timesteps, out_dir, merge, progress, **opts):
        calls.append(opts)
        for t in timesteps:
            save_npy_atomic(out_dir / "steps" / f"t{t:06d}.npy", np.zeros((3, 2), np.float16))
        return SimpleNamespace(timings=[object()] * len(timesteps), seconds_per_timestep=0.5)

    monkeypatch.setattr(distill_mod, "distill_scene", fake_distill)
    scene = SimpleNamespace(num_timesteps=4)
    names = [v.name for v in _distill_variants(scene, None, 2, tmp_path, False, [7], skip=["knn"])]
    assert names == ["lift", "lift + kNN blur", "lift+refine 7 it", "optimize 7 it"]
    assert all("neighbours" not in c for c in calls) and len(calls) == 4
    calls.clear()
    rows = _distill_variants(scene, None, 2, tmp_path / "b", False, [7], skip=["distill"])
    assert [v.group for v in rows] == ["knn", "knn"] and [c["neighbours"] for c in calls] == [5, 10]
