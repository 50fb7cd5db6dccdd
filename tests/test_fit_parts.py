"""Rigid parts of the foreground (fit/clusters.py): what joins a part, where parts are cut, and the
rigid motion of parts against a float64 reference."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings, strategies as st
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from fourlegs_engine.fit.clusters import MIN_PART, axis_angle_quaternion, motion_parts, rigid_part_motion


def _knn(points: np.ndarray, k: int = 12) -> tuple[np.ndarray, np.ndarray]:
    d, nb = cKDTree(points).query(points, k=k + 1)
    return nb[:, 1:], d[:, 1:]


def _ball_and_person(seed: int = 0) -> tuple[np.ndarray, slice, slice]:
    """A ball's surface (radius 12 cm, 600 points) 1 m from a person-sized slab (1.7 m tall, 2400 points)."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(600, 3))
    ball = 0.12 * d / np.linalg.norm(d, axis=1, keepdims=True) + [0.0, -1.5, 0.0]
    body = np.c_[rng.uniform(-0.2, 0.2, 2400), rng.uniform(-1.7, 0.0, 2400), rng.uniform(-0.1, 0.1, 2400)] + [1.0, 0, 0]
    return np.concatenate([ball, body]), slice(0, 600), slice(600, 3000)


def test_a_ball_apart_from_a_person_is_one_part_and_the_person_is_cut_to_the_extent():
    points, ball, body = _ball_and_person()
    labels, free = motion_parts(points, *_knn(points), max_extent=0.4)
    assert np.unique(labels[ball]).size == 1
    assert not np.isin(labels[ball], labels[body]).any()
    assert free[labels[ball][0]] and not free[np.unique(labels[body])].any()  # the ball is whole, the person cut
    body_parts = np.unique(labels[body])
    assert body_parts.size >= 4  # 1.7 m cut to parts of at most 40 cm along their principal axis
    for p in body_parts:
        pts = points[labels == p]
        centred = pts - pts.mean(0)
        axis = np.linalg.svd(centred, full_matrices=False)[2][0]
        assert np.ptp(centred @ axis) <= 0.4 + 1e-9
    assert set(np.unique(labels)) == set(range(labels.max() + 1))


def test_an_isolated_point_inside_the_ball_joins_the_ball():
    points, ball, _ = _ball_and_person()
    points = np.concatenate([points, [[0.0, -1.5, 0.0], [0.01, -1.52, 0.0]]])  # the ball's empty inside
    labels, _ = motion_parts(points, *_knn(points), max_extent=0.4)
    assert labels[-1] == labels[-2] == labels[0]
    assert np.bincount(labels).min() >= 2


def test_parts_without_neighbours_or_points():
    labels, free = motion_parts(np.zeros((0, 3)), np.zeros((0, 0), np.int64), np.zeros((0, 0)), 0.4)
    assert labels.shape == (0,) and free.shape == (0,)
    pts = np.random.default_rng(1).normal(size=(50, 3))
    labels, free = motion_parts(pts, np.zeros((50, 0), np.int64), np.zeros((50, 0)), 100.0)
    assert np.array_equal(labels, np.zeros(50, np.int64)) and free.tolist() == [True]  # no links: one part
    tiny, free = motion_parts(pts, np.zeros((50, 0), np.int64), np.zeros((50, 0)), 1e-6)
    assert np.unique(tiny).size == 50 and not free.any()  # cut down to single points


def test_missing_neighbours_as_cKDTree_gives_them_are_no_links():
    pts = np.array([[0.0, 0, 0], [0.001, 0, 0], [5.0, 0, 0]])
    d, nb = cKDTree(pts).query(pts, k=5, distance_upper_bound=0.01)  # index 3 and inf where none is near
    labels, free = motion_parts(pts, nb[:, 1:], d[:, 1:], max_extent=1.0)
    assert labels[0] == labels[1] != labels[2] and free.all()


def test_coincident_points_are_cut_by_order_not_lost():
    pts = np.zeros((2 * MIN_PART, 3))
    pts[MIN_PART:, 0] = 1.0  # two clusters of identical points, 1 m apart, linked by kNN across
    labels, _ = motion_parts(pts, *_knn(pts, 4), max_extent=0.5)
    assert labels.shape == (2 * MIN_PART,) and labels.min() == 0
    assert np.unique(labels[:MIN_PART]).size == 1 and np.unique(labels[MIN_PART:]).size == 1
    assert labels[0] != labels[-1]


def _reference_motion(means, rotations, labels, centres, translation, omega):
    """float64 scipy reference: x' = R_p (x − c_p) + c_p + t_p, q' = q_p ⊗ q."""
    out_m = np.empty_like(means)
    out_q = np.empty_like(rotations)
    for i, p in enumerate(labels):
        r = Rotation.from_rotvec(omega[p])
        out_m[i] = r.apply(means[i] - centres[p]) + centres[p] + translation[p]
        q = rotations[i]
        composed = r * Rotation.from_quat([q[1], q[2], q[3], q[0]])  # scipy: x, y, z, w
        x, y, z, w = composed.as_quat()
        out_q[i] = [w, x, y, z]
    return out_m, out_q


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2 ** 31 - 1), st.floats(0.0, 3.1))
def test_rigid_part_motion_matches_scipy_and_keeps_distances_within_a_part(seed, angle):
    rng = np.random.default_rng(seed)
    n, p = 40, 3
    means = rng.normal(size=(n, 3))
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    labels = rng.integers(0, p, n)
    centres = rng.normal(size=(p, 3))
    translation = rng.normal(size=(p, 3))
    axis = rng.normal(size=(p, 3))
    omega = angle * axis / np.linalg.norm(axis, axis=1, keepdims=True)
    got_m, got_q = rigid_part_motion(*(torch.from_numpy(a) for a in (means, q, labels, centres, translation, omega)))
    ref_m, ref_q = _reference_motion(means, q, labels, centres, translation, omega)
    np.testing.assert_allclose(got_m.numpy(), ref_m, atol=1e-10)
    same_sign = np.sign((got_q.numpy() * ref_q).sum(1))[:, None]  # q and −q are one rotation
    np.testing.assert_allclose(got_q.numpy() * same_sign, ref_q, atol=1e-10)
    for part in range(p):
        idx = np.flatnonzero(labels == part)
        d0 = np.linalg.norm(means[idx, None] - means[None, idx], axis=-1)
        d1 = np.linalg.norm(got_m.numpy()[idx, None] - got_m.numpy()[None, idx], axis=-1)
        np.testing.assert_allclose(d1, d0, atol=1e-10)


def test_axis_angle_at_zero_is_the_identity_with_finite_gradients():
    omega = torch.zeros(2, 3, dtype=torch.float64, requires_grad=True)
    q = axis_angle_quaternion(omega)
    assert torch.equal(q.detach(), torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=torch.float64))
    q.sum().backward()
    assert torch.isfinite(omega.grad).all()
    # the derivative of the vector part at 0 is ½·I
    jac = torch.autograd.functional.jacobian(lambda w: axis_angle_quaternion(w[None])[0, 1:], torch.zeros(3, dtype=torch.float64))
    np.testing.assert_allclose(jac.numpy(), 0.5 * np.eye(3), atol=1e-12)


def test_rigid_part_motion_gradients_match_finite_differences():
    rng = np.random.default_rng(3)
    means = torch.tensor(rng.normal(size=(12, 3)))
    q = torch.nn.functional.normalize(torch.tensor(rng.normal(size=(12, 4))), dim=-1)
    labels = torch.tensor(rng.integers(0, 2, 12))
    centres = torch.tensor(rng.normal(size=(2, 3)))
    translation = torch.tensor(rng.normal(size=(2, 3)), requires_grad=True)
    for omega0 in (np.zeros((2, 3)), rng.normal(size=(2, 3)), np.array([[1e-9, 0, 0], [math.pi - 1e-3, 0, 0]])):
        omega = torch.tensor(omega0, requires_grad=True)
        assert torch.autograd.gradcheck(
            lambda t, w: tuple(rigid_part_motion(means, q, labels, centres, t, w)), (translation, omega), eps=1e-6, atol=1e-6)


# ------------------------------------------------------------------ the part steps on a thrown ball
def _ball_scene() -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """The synthetic capture's dome, floor and box person plus a ball (radius 12 cm, 300 Gaussians)
    that flies 30 cm (more than its diameter) between t = 0 and t = 1. Returns the arrays, the (N,)
    ball flags and the ball's displacement."""
    import _fit_helpers as fh

    g = fh.scene_gaussians(0)
    rng = np.random.default_rng(5)
    d = rng.normal(size=(300, 3))
    ball = 0.12 * d / np.linalg.norm(d, axis=1, keepdims=True) + [0.7, -1.3, 0.0]
    g["means"] = np.concatenate([g["means"], ball])
    g["colors"] = np.concatenate([g["colors"], np.tile([0.95, 0.45, 0.1], (300, 1))])
    g["log_scales"] = np.concatenate([g["log_scales"], np.full((300, 3), math.log(0.04))])
    g["fg"] = np.concatenate([g["fg"], np.ones(300, bool)])
    is_ball = np.zeros(len(g["means"]), bool)
    is_ball[-300:] = True
    return g, is_ball, np.array([0.0, 0.0, 0.3])


def _ball_problem(part_extent: float):
    """The model at the true t = 0, its true t = 1 frames, the training cameras, options and tracker."""
    import _fit_helpers as fh
    from fourlegs_engine.fit.model import GaussianModel, correct_colours
    from fourlegs_engine.fit.optimize import Tracker
    from fourlegs_engine.fit.options import FitOptions

    g, is_ball, shift = _ball_scene()
    train = [cam.scaled(2.0) for cam in fh.cameras()[0]]
    n = len(g["means"])
    dt = torch.float64
    means0 = torch.tensor(g["means"], dtype=dt)
    rots = torch.zeros(n, 4, dtype=dt)
    rots[:, 0] = 1.0
    model = GaussianModel(means0, rots, torch.tensor(g["log_scales"], dtype=dt), torch.full((n,), 3.0, dtype=dt),
                          torch.tensor(g["colors"], dtype=dt), torch.tensor(g["fg"]), torch.zeros(len(train), 3, dtype=dt),
                          torch.zeros(len(train), 3, dtype=dt))
    means1 = means0.clone()
    means1[torch.from_numpy(is_ball)] += torch.tensor(shift, dtype=dt)

    class Frames:  # the true renders at t = 1
        def __init__(self):
            from fourlegs_engine.fit.model import render_views

            with torch.no_grad():
                outs = [render_views(model, cam, means=means1, rotations=rots, subset=torch.arange(n)) for cam in train]
            self.images = [correct_colours(o["rgb"], model, c) for c, o in enumerate(outs)]
            self.masks = [o["features"] for o in outs]

    opts = FitOptions(part_extent=part_extent, part_fraction=1.0, motion_step_range=1.0, lr_means_later=0.0016,
                      knn=8)
    return model, Frames(), train, opts, Tracker(model, train, opts, floor_y=0.0), is_ball


def _fit_ball_step(part_extent: float) -> tuple[np.ndarray, np.ndarray]:
    """Fit t = 1 from the true t = 0 (box still, ball thrown) with 40 steps; the ball's (B,3) centres
    at t = 0 and as fitted at t = 1."""
    from fourlegs_engine.fit.optimize import fit_later_timestep

    model, frames, train, opts, tracker, is_ball = _ball_problem(part_extent)
    prev = (model.means, model.rotations)
    m, _, _, _ = fit_later_timestep(model, tracker, frames, train, opts, 4.0, prev, prev,
                                 torch.Generator().manual_seed(0), lambda ev: None, 1, 40)
    ball = torch.from_numpy(is_ball)
    return model.means[ball].numpy(), m[ball].numpy()


def test_a_ball_thrown_farther_than_its_size_is_carried_over_whole_by_the_part_steps():
    _, _, shift = _ball_scene()
    start, with_parts = _fit_ball_step(part_extent=0.4)
    _, without = _fit_ball_step(part_extent=0.0)
    err_parts = np.linalg.norm(with_parts.mean(0) - (start.mean(0) + shift))
    err_plain = np.linalg.norm(without.mean(0) - (start.mean(0) + shift))
    assert err_parts < 0.05, err_parts  # of the 30 cm thrown
    assert err_parts < 0.5 * err_plain, (err_parts, err_plain)
    # the ball stays a ball: its Gaussians keep their distances to the centre (12 cm)
    radii = np.linalg.norm(with_parts - with_parts.mean(0), axis=1)
    assert np.median(np.abs(radii - 0.12)) < 0.02


def test_later_part_steps_move_the_free_ball_and_leave_the_cut_person_where_the_forecast_put_it():
    from fourlegs_engine.fit.optimize import move_parts

    model, frames, _, opts, tracker, is_ball = _ball_problem(0.4)
    fi = tracker.fg_idx
    start_m, start_r = model.means[fi], model.rotations[fi]
    labels = tracker.parts.numpy()
    ball_fg = is_ball[fi.numpy()]
    assert np.unique(labels[ball_fg]).size == 1 and bool(tracker.free_parts[labels[ball_fg][0]])
    assert not tracker.free_parts[np.unique(labels[~ball_fg])].any()  # the box (50 × 100 cm) is cut
    m, r = move_parts(model, tracker, frames, opts, 4.0, start_m, start_r, torch.Generator().manual_seed(0), 40,
                      only_free=True)
    assert torch.equal(m[~torch.from_numpy(ball_fg)], start_m[~torch.from_numpy(ball_fg)])
    assert torch.equal(r[~torch.from_numpy(ball_fg)], start_r[~torch.from_numpy(ball_fg)])
    moved = (m[torch.from_numpy(ball_fg)] - start_m[torch.from_numpy(ball_fg)]).mean(0).numpy()
    assert abs(moved[2] - 0.3) < 0.05 and abs(moved[0]) < 0.05 and abs(moved[1]) < 0.05, moved



def test_a_later_timestep_without_free_parts_takes_no_part_steps():
    from fourlegs_engine.fit.optimize import fit_later_timestep

    def fit(no_parts: bool):
        model, frames, train, opts, tracker, _ = _ball_problem(0.4)
        if no_parts:
            tracker.parts = tracker.free_parts = None
        else:
            tracker.free_parts = torch.zeros_like(tracker.free_parts)  # the ball cut too: nothing is free
        prev = (model.means, model.rotations)
        prev2 = (model.means.clone(), model.rotations.clone())  # a later timestep: not the first one
        return fit_later_timestep(model, tracker, frames, train, opts, 4.0, prev, prev2,
                                  torch.Generator().manual_seed(0), lambda ev: None, 2, 12)[:2]

    skipped, plain = fit(False), fit(True)
    assert torch.equal(skipped[0], plain[0]) and torch.equal(skipped[1], plain[1])
