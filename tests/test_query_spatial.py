"""Spatial helpers on arrays: centre of mass, 3D lift, best connected component."""
from __future__ import annotations

import numpy as np

from fourlegs_engine.query.spatial import best_component_bbox, centre_of_mass, lift_centre, mask_bbox
from fourlegs_engine.query.viewpoint import best_view
from fourlegs_engine.scene import Camera


def test_centre_of_mass_weighs_only_relevant_pixels():
    r = np.full((10, 20), 0.4)
    r[2:4, 15:17] = 0.9  # relevant blob, centre (16, 3)
    np.testing.assert_allclose(centre_of_mass(r), [16.0, 3.0])
    r = np.full((10, 20), 0.3)  # nothing relevant: plain centre of mass of R
    np.testing.assert_allclose(centre_of_mass(r), [10.0, 5.0])
    assert centre_of_mass(np.zeros((4, 4))) is None
    assert centre_of_mass(np.full((3, 3), np.nan)) is None


def test_best_component_is_the_one_with_the_highest_score():
    r = np.zeros((12, 12))
    r[1:3, 1:6] = 0.7   # large, weaker
    r[8:10, 8:10] = 0.95  # small, stronger
    assert best_component_bbox(r) == (8, 8, 9, 9)
    assert best_component_bbox(np.full((5, 5), 0.5)) is None  # 0.5 is not relevant
    assert best_component_bbox(np.ones((5, 5))) == (0, 0, 4, 4)  # every pixel relevant
    assert mask_bbox(r > 0.9) == (8, 8, 9, 9) and mask_bbox(np.zeros((3, 3))) is None


def test_lift_centre_unprojects_with_the_rendered_depth():
    cam = Camera.look_at((0, -5, 0), (0, 0, 0), width=40, height=30, fov_y=0.8)
    point = np.array([0.3, 0.0, 0.2])
    uv, z = cam.project(point[None])
    depth = np.full((30, 40), z[0])
    alpha = np.ones((30, 40))
    got, d = lift_centre(cam, uv[0], depth, alpha, np.ones((30, 40)))
    np.testing.assert_allclose(got, point, atol=1e-9)
    # centre on an empty pixel: the depth comes from the relevant solid pixels instead
    alpha[:, :] = 0
    alpha[0:3, 0:3] = 1
    rel = np.zeros((30, 40))
    rel[0:3, 0:3] = 0.9
    got, d = lift_centre(cam, uv[0], depth, alpha, rel)
    assert abs(d - z[0]) < 1e-9 and got is not None
    assert lift_centre(cam, uv[0], depth, np.zeros((30, 40)), rel) == (None, 0.0)
    assert lift_centre(cam, None, depth, alpha, rel) == (None, 0.0)


def test_best_view_highest_mean_and_ties():
    cams = [Camera.look_at((i + 1, -5, 0), (0, 0, 0), width=8, height=6, name=f"c{i}") for i in range(3)]
    means = {"c0": 0.2, "c1": 0.7, "c2": 0.7}
    res = best_view(cams, lambda c: np.full((6, 8), means[c.name]), t=3)
    assert res.best == "c1" and res.index == 1 and res.t == 3
    assert best_view([], lambda c: None, t=0).best is None
