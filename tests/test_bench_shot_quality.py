"""The shot-quality numbers against geometry worked out by hand: a ball of Gaussians seen by a pinhole
camera, a wall hiding part of it, a faint floater in front of the lens."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fourlegs_bench.shot_quality import frame_quality, markdown_table, summarize
from fourlegs_engine.scene import Camera
from fourlegs_engine.scene.gaussians import GaussianFrame

W, H, FOCAL, DIST, RADIUS, SIGMA = 320, 180, 200.0, 3.0, 0.3, 0.02


def frame(points, opacities, sigma=SIGMA):
    n = len(points)
    rot = torch.zeros(n, 4)
    rot[:, 0] = 1
    logit = torch.logit(torch.as_tensor(opacities, dtype=torch.float32).clamp(1e-4, 1 - 1e-4))
    return GaussianFrame(means=torch.as_tensor(np.asarray(points), dtype=torch.float32), rotations=rot,
                         log_scales=torch.full((n, 3), math.log(sigma)), opacity_logits=logit,
                         colors=torch.full((n, 3), 0.5))


def ball(centre, count=3000):
    rng = np.random.default_rng(0)
    v = rng.normal(size=(count, 3))
    return np.asarray(centre) + RADIUS * v / np.linalg.norm(v, axis=1, keepdims=True) * rng.uniform(0, 1, (count, 1)) ** (1 / 3)


CAMERA = Camera.look_at((0.0, -DIST, 0.0), (0.0, 0.0, 0.0), width=W, height=H, focal=FOCAL)


def test_height_and_offset_follow_the_pinhole_projection():
    pts = ball((0.0, 0.0, 0.0))
    q = frame_quality(frame(pts, np.full(len(pts), 0.99)), np.ones(len(pts), bool), CAMERA)
    # the sphere's silhouette (40.2 px of 180) plus the splats' soft edge (alpha > 0.5 about 1.5 sigma out)
    expected = 2 * FOCAL * (math.tan(math.asin(RADIUS / DIST)) + 1.5 * SIGMA / DIST) / H
    assert q["height"] == pytest.approx(expected, abs=3 / H)
    assert q["offset"] < 0.02 and q["in_frame"] and q["occluded"] < 0.02 and q["floaters"] == 0.0
    # moved 0.5 m to the right: 33 px off-centre of a 183.6 px half-diagonal
    moved = ball((0.5, 0.0, 0.0))
    q = frame_quality(frame(moved, np.full(len(moved), 0.99)), np.ones(len(moved), bool), CAMERA)
    assert q["offset"] == pytest.approx(FOCAL * 0.5 / DIST / math.hypot(W / 2, H / 2), abs=0.01)
    # half out of the frame on the left: not wholly in frame
    out = ball((-(W / 2) * DIST / FOCAL, 0.0, 0.0))
    assert not frame_quality(frame(out, np.full(len(out), 0.99)), np.ones(len(out), bool), CAMERA)["in_frame"]


def test_a_wall_over_the_left_half_occludes_half_and_a_faint_floater_counts():
    pts = ball((0.0, 0.0, 0.0))
    # the wall's splats reach about 1.5 sigma past their last centre: the edge sits on the ball's middle
    xs, zs = np.meshgrid(np.arange(-0.6, -1.5 * SIGMA * 2 / DIST, 0.01), np.arange(-0.6, 0.6, 0.01))
    wall = np.stack([xs.ravel(), np.full(xs.size, -1.0), zs.ravel()], axis=1)
    subject = np.r_[np.ones(len(pts), bool), np.zeros(len(wall), bool)]
    q = frame_quality(frame(np.r_[pts, wall], np.r_[np.full(len(pts), 0.99), np.full(len(wall), 0.99)]), subject, CAMERA)
    assert q["occluded"] == pytest.approx(0.5, abs=0.07)
    # a faint, wide splat half a metre in front of the lens is a floater; an opaque one is not
    for opacity, counted in ((0.2, True), (0.9, False)):
        g = frame(np.r_[pts, [[0.0, -DIST + 0.5, 0.0]]], np.r_[np.full(len(pts), 0.99), [opacity]], sigma=SIGMA)
        g.log_scales[-1] = math.log(0.1)
        q = frame_quality(g, np.r_[np.ones(len(pts), bool), [False]], CAMERA)
        assert (q["floaters"] > 0.01) is counted


def test_summary_rows_per_shot():
    rows = summarize([{"shot": "a", "effect": "play", "height": h, "offset": 0.1, "in_frame": f, "occluded": 0.0,
                       "floaters": 0.0} for h, f in ((0.1, True), (0.3, False))])
    assert rows[0]["height_last"] == 0.3 and rows[0]["in_frame_share"] == 0.5 and rows[0]["frames"] == 2
    assert "| a | play | 2 |" in markdown_table(rows)
