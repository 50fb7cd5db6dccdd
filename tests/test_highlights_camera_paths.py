"""Camera poses and paths: degenerate geometry stays finite, proper and continuous."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, example, given, strategies as st

from fourlegs_engine.highlights.camera_paths import (Pose, aim, axis_angle_matrix, dolly_path, interpolate_poses,
                                                     is_proper_rotation, look_at_rotation, orbit_path,
                                                     rotation_angle, rotation_between, slerp_rotations)
from fourlegs_engine.scene import Camera

vec = st.tuples(*[st.floats(-20, 20, allow_nan=False)] * 3).map(np.array)
unit_quat = st.tuples(*[st.floats(-1, 1)] * 4).filter(lambda q: np.linalg.norm(q) > 0.1)


def rot_from_quat(q) -> np.ndarray:
    from scipy.spatial.transform import Rotation
    return Rotation.from_quat(np.asarray(q) / np.linalg.norm(q)).as_matrix()


def project(pose: Pose, point, focal=500.0, w=640, h=360):
    cam = pose.rotation.T @ (np.asarray(point) - pose.position)
    return np.array([focal * cam[0] / cam[2] + w / 2, focal * cam[1] / cam[2] + h / 2]), cam[2]


def test_look_at_matches_scene_camera_convention():
    eye, target = np.array([3.0, -2.0, 1.5]), np.array([0.0, 0.0, 1.0])
    R = look_at_rotation(eye, target)
    cam = Camera.look_at(eye, target, width=64, height=36, focal=50.0)
    np.testing.assert_allclose(R, cam.c2w[:3, :3], atol=1e-12)
    assert R[:, 1] @ np.array([0, 0, 1.0]) < 0  # image down is world down-ish


@pytest.mark.parametrize("up_sign", [1.0, -1.0])
def test_look_at_with_up_parallel_to_the_view_is_proper(up_sign):
    eye, target = np.array([0.0, 0.0, 5.0 * up_sign]), np.zeros(3)  # straight down / straight up
    R = look_at_rotation(eye, target)
    assert is_proper_rotation(R)
    np.testing.assert_allclose(R[:, 2], -np.sign(up_sign) * np.array([0, 0, 1.0]), atol=1e-12)
    # with a previous rotation the roll is kept: minimal change from the previous camera
    prev = look_at_rotation(np.array([0.01, 0.0, 5.0]), target)
    R2 = look_at_rotation(np.array([0.0, 0.0, 5.0]), target, previous=prev)
    assert is_proper_rotation(R2) and rotation_angle(prev, R2) < 0.01
    # eye == target keeps the previous orientation instead of dividing by zero
    np.testing.assert_allclose(look_at_rotation(target, target, previous=prev), prev, atol=1e-12)


def test_aim_turns_minimally_and_handles_a_target_behind():
    pose = Pose.from_camera(Camera.look_at([4, 0, 1.5], [0, 0, 1.0], width=64, height=36, focal=50.0))
    off = np.array([0.0, 0.8, 1.3])
    aimed = aim(pose, off)
    uv, z = project(aimed, off)
    np.testing.assert_allclose(uv, [320, 180], atol=1e-9)
    assert z > 0 and is_proper_rotation(aimed.rotation)
    behind = pose.position - 3 * pose.forward
    turned = aim(pose, behind)
    assert is_proper_rotation(turned.rotation)
    uv, z = project(turned, behind)
    assert z > 0 and np.allclose(uv, [320, 180], atol=1e-6)
    # a half turn about the camera's own vertical axis keeps the horizon level
    assert abs(turned.rotation[:, 0] @ np.array([0, 0, 1.0])) < 1e-9
    assert aim(pose, pose.position) is pose


def test_rotation_between_opposite_vectors_is_a_half_turn():
    a = np.array([0.0, 0.0, 1.0])
    R = rotation_between(a, -a, fallback_axis=np.array([1.0, 0, 0]))
    assert is_proper_rotation(R)
    np.testing.assert_allclose(R @ a, -a, atol=1e-12)
    np.testing.assert_allclose(R @ np.array([1.0, 0, 0]), [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(rotation_between(a, a), np.eye(3), atol=1e-15)
    np.testing.assert_allclose(rotation_between(np.zeros(3), a), np.eye(3))


def test_orbit_keeps_the_centre_framed_radius_and_height():
    centre = np.array([0.3, -0.2, 1.0])
    start = aim(Pose.from_camera(Camera.look_at([4, 1, 2.5], [0, 0, 1], width=64, height=36, focal=50)), centre)
    angles = np.radians(np.linspace(0, 270, 91))
    poses = orbit_path(start, centre, angles)
    rel0 = start.position - centre
    for p, a in zip(poses, angles):
        assert is_proper_rotation(p.rotation)
        uv, z = project(p, centre)
        np.testing.assert_allclose(uv, [320, 180], atol=1e-6)
        rel = p.position - centre
        assert math.hypot(*rel[:2]) == pytest.approx(math.hypot(*rel0[:2]))
        assert rel[2] == pytest.approx(rel0[2])
    # counter-clockwise seen from above, by exactly the requested angle
    a_end = math.atan2((poses[-1].position - centre)[1], (poses[-1].position - centre)[0])
    a_start = math.atan2(rel0[1], rel0[0])
    assert (a_end - a_start) % (2 * math.pi) == pytest.approx(math.radians(270))
    steps = [rotation_angle(a.rotation, b.rotation) for a, b in zip(poses, poses[1:])]
    assert max(steps) < math.radians(3.0 + 1e-6)


def test_orbit_from_straight_above_and_with_zero_radius_never_flips():
    centre = np.array([0.0, 0.0, 1.0])
    R = look_at_rotation(np.array([0.0, 0.0, 6.0]), centre)  # straight down
    start = Pose(np.array([0.0, 0.0, 6.0]), R)
    poses = orbit_path(start, centre, np.radians(np.linspace(0, 360, 73)))
    for p in poses:
        assert is_proper_rotation(p.rotation)
        np.testing.assert_allclose(p.position, start.position, atol=1e-12)  # radius 0: spins in place
        np.testing.assert_allclose(p.forward, [0, 0, -1], atol=1e-12)
    steps = [rotation_angle(a.rotation, b.rotation) for a, b in zip(poses, poses[1:])]
    assert max(steps) == pytest.approx(math.radians(5.0), abs=1e-9)
    # camera sitting on the centre: still finite and proper
    on = orbit_path(Pose(centre, np.eye(3)), centre, np.linspace(0, 3, 5), radius_factors=np.linspace(1, 2, 5))
    assert all(is_proper_rotation(p.rotation) and np.all(np.isfinite(p.position)) for p in on)


def test_orbit_radius_and_height_scaling_keep_the_centre_framed():
    centre = np.array([0.0, 0.0, 1.0])
    start = aim(Pose(np.array([3.0, 0.0, 2.0]), np.eye(3)), centre)
    k = np.linspace(0, 1, 30)
    poses = orbit_path(start, centre, k * math.pi, radius_factors=1 + k, height_factors=1 + 2 * k)
    assert math.hypot(*(poses[-1].position - centre)[:2]) == pytest.approx(6.0)
    assert (poses[-1].position - centre)[2] == pytest.approx(3.0)
    for p in poses:
        uv, z = project(p, centre)
        assert z > 0 and np.allclose(uv, [320, 180], atol=1e-6)


def test_dolly_keeps_an_aimed_target_at_the_centre_and_respects_min_distance():
    centre = np.array([0.5, 0.5, 1.0])
    start = aim(Pose(np.array([5.0, -3.0, 2.0]), np.eye(3)), centre)
    d0 = np.linalg.norm(start.position - centre)
    poses = dolly_path(start, centre, np.array([1.0, 0.5, 0.25, 0.01]), min_distance=0.5)
    dists = [np.linalg.norm(p.position - centre) for p in poses]
    np.testing.assert_allclose(dists[:3], [d0, d0 / 2, d0 / 4])
    assert dists[3] == pytest.approx(0.5)
    for p in poses:
        np.testing.assert_allclose(project(p, centre)[0], [320, 180], atol=1e-6)
        np.testing.assert_allclose(p.rotation, start.rotation, atol=1e-12)
    on_target = Pose(centre, np.eye(3))
    assert all(p is on_target for p in dolly_path(on_target, centre, np.array([1.0, 0.5, 0.1])))


def test_interpolation_around_a_pivot_swings_instead_of_cutting_through():
    centre = np.zeros(3)
    a = aim(Pose(np.array([3.0, 0, 1.0]), np.eye(3)), centre)
    b = aim(Pose(np.array([-3.0, 0.01, 1.0]), np.eye(3)), centre)
    w = np.linspace(0, 1, 21)
    swing = interpolate_poses(a, b, w, pivot=centre)
    assert min(np.linalg.norm(p.position[:2]) for p in swing) == pytest.approx(3.0, rel=1e-3)
    straight = interpolate_poses(a, b, w)
    assert min(np.linalg.norm(p.position[:2]) for p in straight) < 0.1
    np.testing.assert_allclose(swing[0].position, a.position, atol=1e-12)
    np.testing.assert_allclose(swing[-1].position, b.position, atol=1e-12)
    np.testing.assert_allclose(swing[-1].rotation, b.rotation, atol=1e-9)


@given(eye=vec, target=vec, q=unit_quat)
def test_property_aim_and_look_at_are_proper_and_finite(eye, target, q):
    R = look_at_rotation(eye, target)
    assert is_proper_rotation(R)
    pose = aim(Pose(eye, rot_from_quat(q)), target)
    assert is_proper_rotation(pose.rotation) and np.all(np.isfinite(pose.position))
    if np.linalg.norm(target - eye) > 1e-6:
        d = (target - eye) / np.linalg.norm(target - eye)
        assert pose.forward @ d == pytest.approx(1.0, abs=1e-7)


def _orbit(start, centre, arc, rs, hs, n):
    k = np.linspace(0, 1, n)
    return orbit_path(start, centre, np.radians(arc) * k, radius_factors=1 + (rs - 1) * k,
                      height_factors=1 + (hs - 1) * k)


@given(centre=vec, eye=vec, q=unit_quat, arc=st.floats(-720, 720), rs=st.floats(0.05, 5), hs=st.floats(0, 5))
@example(centre=np.array([0.0, 18.5, 0.0]), eye=np.array([0.0, 18.4375, 5.0]), q=(0.0, 0.0, 0.0, 1.0), arc=0.0,
         rs=0.5, hs=0.0)                    # descends from above to 0.03 beside the centre: aim turns fast at the end
def test_property_orbit_is_proper_finite_and_continuous(centre, eye, q, arc, rs, hs):
    start = Pose(eye, rot_from_quat(q))
    poses = _orbit(start, centre, arc, rs, hs, 61)
    np.testing.assert_allclose(poses[0].position, start.position, atol=1e-9)
    np.testing.assert_allclose(poses[0].rotation, start.rotation, atol=1e-7)
    for p in poses:
        assert is_proper_rotation(p.rotation) and np.all(np.isfinite(p.position))
    # Continuity: sampling 4x as densely shrinks the largest orientation step about 4x; a flip would keep it
    # at the flip's size. Aiming at the centre turns by about step / distance, so this holds where the path
    # stays several fine steps away from the centre; a path through (or grazing) the centre turns its aim
    # discontinuously by construction (the degenerate cases have their own tests above).
    rel = eye - centre
    assume(np.linalg.norm(rel) > 1e-2)
    coarse = max(rotation_angle(a.rotation, b.rotation) for a, b in zip(poses, poses[1:]))
    fine_poses = _orbit(start, centre, arc, rs, hs, 241)
    fine = max(rotation_angle(a.rotation, b.rotation) for a, b in zip(fine_poses, fine_poses[1:]))
    fine_step = max(np.linalg.norm(a.position - b.position) for a, b in zip(fine_poses, fine_poses[1:]))
    closest = min(np.linalg.norm(p.position - centre) for p in fine_poses)
    if closest > 4 * fine_step:
        assert fine <= 0.6 * coarse + 1e-7
    # and steps stay small unless the path runs close to the centre, where aiming turns quickly
    assert coarse < 0.5 or closest < 0.3 * np.linalg.norm(rel)


@given(a=unit_quat, b=unit_quat)
def test_property_slerp_is_proper_and_geodesic(a, b):
    Ra, Rb = rot_from_quat(a), rot_from_quat(b)
    Rs = slerp_rotations(Ra, Rb, np.linspace(0, 1, 11))
    total = rotation_angle(Ra, Rb)
    for R in Rs:
        assert is_proper_rotation(R)
    steps = [rotation_angle(x, y) for x, y in zip(Rs, Rs[1:])]
    np.testing.assert_allclose(steps, total / 10, atol=1e-6)


def test_axis_angle_with_zero_axis_is_identity():
    np.testing.assert_array_equal(axis_angle_matrix(np.zeros(3), 1.0), np.eye(3))


class _StubFraming:
    """A framing whose line-of-sight test answers from a rule over the path's camera positions."""

    def __init__(self, clear, enters=lambda eyes: True):
        self.centre = np.zeros(3)
        self.rig = None
        self.clear, self.enters = clear, enters

    def path_is_clear(self, eyes):
        return bool(self.clear(np.atleast_2d(eyes)))

    def path_enters_gaussians(self, eyes):
        return bool(self.enters(np.atleast_2d(eyes)))

    def fitting_focal(self, distance, resolution):
        return 1e9  # the subject always fits: the lens stays the anchor's


def _move(clear, enters=lambda eyes: True):
    """Swing from a camera on +x to one on +y round the origin (a 'best_view' move of 24 frames)."""
    from types import SimpleNamespace

    from fourlegs_engine.highlights.effects import _camera_move

    previous = Pose(np.array([3.0, 0.0, 1.0]), look_at_rotation(np.array([3.0, 0.0, 1.0]), np.zeros(3)))
    anchor = Pose(np.array([0.0, 3.0, 1.0]), look_at_rotation(np.array([0.0, 3.0, 1.0]), np.zeros(3)))
    ctx = SimpleNamespace(anchor=anchor, anchor_focal=400.0, framing=_StubFraming(clear, enters), resolution=(640, 360),
                          messages=[], previous=previous, previous_focal=300.0, output_fps=24.0,
                          action_centre=np.zeros(3), up=np.array([0.0, 0.0, 1.0]))
    poses, focals = _camera_move({"camera": "best_view", "transition_s": 1.0}, ctx, 24)
    return previous, anchor, poses, focals, ctx.messages


def test_a_move_whose_every_path_passes_through_gaussians_cuts_to_the_camera():
    previous, anchor, poses, focals, messages = _move(lambda eyes: False)
    assert all(np.allclose(q.position, anchor.position) and np.allclose(q.rotation, anchor.rotation) for q in poses)
    np.testing.assert_allclose(focals, 400.0)
    assert any("the shot cuts to it" in m for m in messages)


def test_a_blocked_swing_with_a_clear_straight_path_moves_straight():
    straight = lambda eyes: np.allclose(eyes[:, 2], 1.0) and np.all(np.abs(eyes[:, 0] + eyes[:, 1] - 3.0) < 1e-6)
    previous, anchor, poses, focals, messages = _move(straight)
    eyes = np.array([q.position for q in poses])
    assert np.allclose(eyes[0], previous.position) and np.allclose(eyes[-1], anchor.position)
    assert np.all(np.abs(eyes[:, 0] + eyes[:, 1] - 3.0) < 1e-6)   # on the chord, not round the pivot
    assert focals[0] == pytest.approx(300.0) and focals[-1] == pytest.approx(400.0)
    assert any("moves straight" in m for m in messages)


def test_a_clear_swing_goes_round_the_action():
    previous, anchor, poses, focals, messages = _move(lambda eyes: True)
    eyes = np.array([q.position for q in poses])
    radii = np.linalg.norm(eyes[:, :2], axis=1)
    assert np.allclose(eyes[0], previous.position) and np.allclose(eyes[-1], anchor.position)
    assert radii.min() > 2.9 and messages == []   # round the pivot at the same distance, not across the chord


def test_a_swing_that_only_hides_the_action_for_a_moment_is_kept():
    previous, anchor, poses, focals, messages = _move(lambda eyes: False, enters=lambda eyes: False)
    eyes = np.array([q.position for q in poses])
    assert np.linalg.norm(eyes[:, :2], axis=1).min() > 2.9 and any("no clear path found" in m for m in messages)


def test_a_swing_through_gaussians_takes_the_straight_path_when_that_only_hides_the_action():
    on_chord = lambda eyes: np.all(np.abs(eyes[:, 0] + eyes[:, 1] - 3.0) < 1e-6)
    previous, anchor, poses, focals, messages = _move(lambda eyes: False, enters=lambda eyes: not on_chord(eyes))
    eyes = np.array([q.position for q in poses])
    assert on_chord(eyes) and np.allclose(eyes[-1], anchor.position)
    assert any("would pass through scene Gaussians" in m for m in messages)


def _follow(first_is_previous: bool):
    from types import SimpleNamespace

    from fourlegs_engine.highlights.camera_paths import hold_path
    from fourlegs_engine.highlights.framed_moves import follow_subject

    subject = np.array([0.5, 0.5, 1.0])
    eye = np.array([3.0, 0.0, 1.5])
    aimed_away = Pose(eye, look_at_rotation(eye, np.array([0.0, -2.0, 1.0])))
    previous = aimed_away if first_is_previous else Pose(np.array([0.0, 3.0, 1.0]),
                                                         look_at_rotation(np.array([0.0, 3.0, 1.0]), np.zeros(3)))
    framing = SimpleNamespace(track=True, track_at=lambda times: np.repeat(subject[None], len(times), 0))
    ctx = SimpleNamespace(framing=framing, previous=previous, output_fps=24.0, up=np.array([0.0, 0.0, 1.0]))
    poses = follow_subject(hold_path(aimed_away, 24), np.linspace(0, 5, 24), ctx, 1.0)
    forward = np.array([q.rotation[:, 2] for q in poses])
    towards = (subject - eye) / np.linalg.norm(subject - eye)
    return forward @ towards


def test_a_replay_that_cut_to_its_camera_follows_the_subject_from_its_first_frame():
    np.testing.assert_allclose(_follow(first_is_previous=False), 1.0, atol=1e-9)


def test_a_replay_that_continues_the_previous_shot_turns_onto_the_subject_over_its_transition():
    cos = _follow(first_is_previous=True)
    assert cos[0] < 0.9 and np.allclose(cos[-1], 1.0, atol=1e-9) and np.all(np.diff(cos) >= -1e-12)
