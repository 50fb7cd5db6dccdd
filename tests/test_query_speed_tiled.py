"""The tiled-field speed benchmark: tiling, and its shortcut to the exact answer on the tiled field."""
from __future__ import annotations

import numpy as np
import pytest
from _query_helpers import LinearField, two_cluster_scene

from fourlegs_engine.errors import InputError
from fourlegs_engine.query.engine import QueryEngine
from fourlegs_bench.query_fixtures import flat_scene
from fourlegs_bench.query_speed_tiled import exact_tiled_answers, source_timesteps, write_tiled_latents


def test_source_timesteps_repeat_every_source_timestep_in_order():
    src = source_timesteps(4, 10)
    assert src[0] == 0 and src[-1] == 3 and np.all(np.diff(src) >= 0)
    assert np.bincount(src, minlength=4).min() >= 2
    np.testing.assert_array_equal(source_timesteps(5, 5), np.arange(5))
    np.testing.assert_array_equal(source_timesteps(3, 1), [0])


def test_tiled_latents_copy_gaussians_and_repeat_timesteps(tmp_path):
    rng = np.random.default_rng(0)
    src = rng.normal(size=(3, 5, 4)).astype(np.float16)
    lat = write_tiled_latents(tmp_path / "t.npy", src, 7, 15)
    assert lat.shape == (7, 15, 4) and lat.dtype == np.float16
    for t, s in enumerate(source_timesteps(3, 7)):
        for copy in range(3):
            np.testing.assert_array_equal(lat[t, copy * 5:(copy + 1) * 5], src[s])
    with pytest.raises(InputError, match="whole copies"):
        write_tiled_latents(tmp_path / "u.npy", src, 7, 12)


@pytest.mark.parametrize("query", ["a ball flying", "a person jumping"])
def test_exact_tiled_answers_equal_the_exact_path_on_the_tiled_field(tmp_path, query):
    scene, field, enc, _ = two_cluster_scene(T=5, active=(1, 2, 3))
    rng = np.random.default_rng(1)
    field.latents = (np.asarray(field.latents) + rng.normal(scale=0.3, size=field.latents.shape)).astype(np.float32)
    T, N = 12, 2 * scene.num_gaussians
    tiled = write_tiled_latents(tmp_path / "t.npy", field.latents, T, N)
    brute = QueryEngine(flat_scene(T, N), LinearField(np.asarray(tiled, dtype=np.float32), field.weight.numpy()),
                        enc).temporal(query)
    got = exact_tiled_answers(scene, LinearField(np.asarray(field.latents, dtype=np.float16).astype(np.float32),
                                                 field.weight.numpy()), enc, [query], T, N)[query]
    np.testing.assert_array_equal(got.positive, brute.positive)
    assert got.segment == brute.segment and got.r_avg == pytest.approx(brute.r_avg, abs=1e-6)
    np.testing.assert_allclose(got.scores, brute.scores, atol=1e-12)


def test_markdown_rows_report_the_exact_work_and_what_bounds_decided():
    from fourlegs_bench.query_speed_tiled import markdown_rows

    queries = [{"query": "a", "seconds": 0.1, "sampled": 4096, "rescored": 1000, "bounded": 900},
               {"query": "b", "seconds": 0.3, "sampled": 0, "rescored": 0}]  # a row from before the bounds
    row = {"path": "codebook K=65536", "mean_query_s": 0.2, "mean_found_query_s": 0.1, "max_query_s": 0.3,
           "equal_to_exact": 2, "num_queries": 2, "tIoU": 0.497, "exact_tIoU": 0.5, "anon_rss_mb": 503.4,
           "queries": queries}
    lines = markdown_rows([row])
    assert "median of 3 runs" in lines[1] and "decided by norm bounds" in lines[3]
    assert lines[-1] == "| codebook K=65536 | 0.200 | 0.100 | 0.300 | 2/2 | 49.7 (50.0) | 2048 + 500; 450 | 503 |"
    assert markdown_rows([]) == []
