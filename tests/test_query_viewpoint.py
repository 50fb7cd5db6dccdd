"""The best-view score: the paper's mean relevancy against the relevant pixels' mass (small subjects)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fourlegs_engine.errors import InputError
from fourlegs_engine.query.options import QueryOptions
from fourlegs_engine.query.viewpoint import best_view, best_view_confirmed, view_score
from fourlegs_engine.scene import Camera


def _cameras(count: int) -> list[Camera]:
    return [Camera.look_at((3.0, float(i), 1.0), (0.0, 0.0, 0.0), width=64, height=36, focal=50.0, name=f"c{i}")
            for i in range(count)]


def _maps(background: list[float], subject: list[float], size=(36, 64)) -> list[np.ndarray]:
    """One map per camera: a flat background relevancy and a 3x3 subject patch (0.3 % of the frame)."""
    maps = []
    for b, s in zip(background, subject):
        m = np.full(size, b)
        m[10:13, 20:23] = s
        maps.append(m)
    return maps


def test_a_small_subject_is_ranked_by_its_relevant_mass_not_by_the_background():
    """Camera 0 has the brighter background, camera 1 shows the ball: the paper's mean picks camera 0, the
    relevant mass camera 1 (the real capture's case: the ball covers ~0.2 % of a frame)."""
    cams = _cameras(2)
    maps = _maps([0.13, 0.11], [0.13, 0.95])
    by_id = {id(c): m for c, m in zip(cams, maps)}
    assert best_view(cams, lambda c: by_id[id(c)], 0, "mean").best == "c0"
    result = best_view(cams, lambda c: by_id[id(c)], 0, "relevant")
    assert result.best == "c1"
    assert result.scores["c1"] == pytest.approx(9 * 0.45 / (36 * 64)) and result.scores["c0"] == 0.0


def test_relevant_falls_back_to_the_mean_when_no_pixel_is_relevant():
    cams = _cameras(3)
    maps = _maps([0.1, 0.3, 0.2], [0.4, 0.45, 0.2])
    by_id = {id(c): m for c, m in zip(cams, maps)}
    relevant = best_view(cams, lambda c: by_id[id(c)], 0, "relevant")
    mean = best_view(cams, lambda c: by_id[id(c)], 0, "mean")
    assert relevant.best == mean.best == "c1" and relevant.scores == mean.scores


@settings(max_examples=15, deadline=None)
@given(st.lists(st.tuples(st.floats(0.0, 0.49), st.floats(0.0, 1.0)), min_size=2, max_size=6),
       st.sampled_from(["relevant", "mean"]))
def test_confirmed_search_agrees_with_the_full_search_when_every_camera_is_confirmed(cases, score):
    cams = _cameras(len(cases))
    maps = _maps([b for b, _ in cases], [s for _, s in cases])
    by_id = {id(c): m for c, m in zip(cams, maps)}
    full = best_view(cams, lambda c: by_id[id(c)], 0, score)
    confirmed = best_view_confirmed(
        cams, lambda batch, reduced: [by_id[id(c)][::2, ::2] if reduced else by_id[id(c)] for c in batch],
        0, len(cams), score)
    assert confirmed.best == full.best
    assert all(np.isfinite(v) and v >= 0 for v in confirmed.scores.values())


def test_view_score_of_an_empty_or_non_finite_map_is_finite():
    assert view_score(np.zeros((0, 0)), "relevant") == 0.0 and view_score(np.zeros((0, 0)), "mean") == 0.0
    assert view_score(np.full((2, 2), 1.0), "relevant") == pytest.approx(0.5)


def test_an_unknown_view_score_is_one_input_error():
    from fourlegs_engine.query.engine import _check_options
    with pytest.raises(InputError, match="view_score"):
        _check_options(QueryOptions(view_score="median"))
