"""Subject-aware framing: instances, the target subject size, the rig volume, segments and blur.

The scene: two people 2.8 m apart (a larger one on -x, a smaller one on +x) on a floor, filmed by a
ring of eight cameras. The checks measure the result independently of the planner: the subject's
height is read from the engine's render of its Gaussians alone (:mod:`fourlegs_bench.shot_quality`),
the rig from the ring's own radius and heights.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from _highlights_helpers import HEIGHT, WIDTH, FakeLocalizer
from fourlegs_bench.shot_quality import frame_quality
from fourlegs_engine.highlights.instances import split_instances
from fourlegs_engine.highlights.plan import frames_in_ranges
from fourlegs_engine.highlights.planner import plan_highlight
from fourlegs_engine.highlights.presets import load_preset, parse_preset
from fourlegs_engine.highlights.preview import blur_background, frame_at, key_camera, render_tiles
from fourlegs_engine.highlights.rig_volume import MIN_HEIGHT_M, RigVolume
from fourlegs_engine.query.results import TemporalResult
from fourlegs_engine.scene import Camera, CameraRig, GaussianSequence, Scene

QUERY = "a person"
RING_RADIUS, RING_HEIGHT = 4.5, 2.2
SIGMA = 0.05


def _box(rng, centre, half, count):
    return np.asarray(centre) + rng.uniform(-1, 1, (count, 3)) * np.asarray(half)


def two_people(T: int = 40):
    """(scene, relevant (N,) bool, big (N,) bool, small (N,) bool): people at x = -1.4 (400 Gaussians) and
    x = +1.4 (200 Gaussians), 1.7 m tall, world up +z, a floor at z = 0."""
    rng = np.random.default_rng(7)
    big = _box(rng, (-1.4, 0.0, 0.85), (0.2, 0.15, 0.8), 400)
    small = _box(rng, (1.4, 0.0, 0.85), (0.2, 0.15, 0.8), 200)
    floor = np.concatenate([rng.uniform(-4, 4, (400, 2)), np.zeros((400, 1))], axis=1)
    means = np.concatenate([big, small, floor]).astype(np.float32)
    N = len(means)
    relevant = np.zeros(N, bool)
    relevant[:600] = True
    rot = np.zeros((T, N, 4), np.float32)
    rot[..., 0] = 1
    g = GaussianSequence(means=np.broadcast_to(means, (T, N, 3)).copy(), rotations=rot,
                         log_scales=np.full((N, 3), math.log(SIGMA), np.float32),
                         opacity_logits=np.full(N, 3.0, np.float32),
                         colors=np.where(relevant[:, None], [0.8, 0.3, 0.2], [0.4, 0.4, 0.4]).astype(np.float32))
    cams = []
    for i in range(8):
        a = 2 * math.pi * (i + 0.5) / 8
        eye = (RING_RADIUS * math.cos(a), RING_RADIUS * math.sin(a), RING_HEIGHT)
        cams.append(Camera.look_at(eye, (0.0, 0.0, 0.9), width=WIDTH, height=HEIGHT, focal=200.0, name=f"cam{i:02d}"))
    scene = Scene(gaussians=g, cameras=CameraRig.static(cams, [], T), name="two-people", fps=30.0)
    return scene, relevant, np.arange(N) < 400, (np.arange(N) >= 400) & (np.arange(N) < 600)


class PeopleLocalizer(FakeLocalizer):
    """The fake localizer with per-Gaussian relevancy (1 on both people) and optional extra segments."""

    def __init__(self, scene, relevant, *, segments=None, **kw):
        super().__init__(scene, **kw)
        self.relevant = relevant
        self.segments = segments

    def gaussian_relevancy(self, query, t):
        self.stats["gaussian_relevancy"] += 1
        return torch.as_tensor(self.relevant.astype(np.float32))

    def temporal(self, query):
        result = super().temporal(query)
        if self.segments is None:
            return result
        positive = np.zeros(self.scene.num_timesteps, bool)
        for a, b in self.segments:
            positive[a:b + 1] = True
        return TemporalResult(positive / positive.sum(), positive, list(self.segments), self.segment, self.peak,
                              True, "")


@pytest.fixture(scope="module")
def people():
    return two_people()


def _localizer(people, **kw):
    scene, relevant, _, _ = people
    return PeopleLocalizer(scene, relevant, segment=(10, 20), centre=(0.0, 0.0, 0.9), best_view="cam00", **kw)


def _preset(**top):
    shots = [{"name": "context", "effect": "play", "camera": "best_view", "from": "segment_start",
              "from_offset_s": -0.3, "to": "segment_start"},
             {"name": "zoom", "effect": "zoom_in", "target_height": top.pop("zoom_target", 0.5)},
             {"name": "orbit", "effect": "bullet_time", "arc_deg": 120.0, "duration_s": 1.5,
              "target_height": top.pop("orbit_target", 0.5)},
             {"name": "replay", "effect": top.pop("replay_effect", "desaturate_background"), "camera": "best_view",
              "transition_s": 0.5}]
    return parse_preset({"name": "subjects", "fps": 24, "resolution": [640, 360], **top, "shots": shots})


def _subject_height(scene, plan, key, frame, members):
    t = plan.shots[0].time_keys[0].timestep if frame is None else plan.timestep_at(key.frame)
    cam = key_camera(key, plan, 320, near=0.1)
    return frame_quality(frame_at(scene.gaussians, t), members, cam)


def test_instances_are_the_separate_people_ranked_by_relevancy_mass(people):
    scene, relevant, big, small = people
    means = scene.gaussians.means[0]
    found = split_instances(means, relevant.astype(float), np.full((len(means), 3), SIGMA), relevant,
                            np.array([0.0, 0.0, 1.0]))
    assert len(found) == 2
    np.testing.assert_array_equal(found[0].members, big)
    np.testing.assert_array_equal(found[1].members, small)
    assert found[0].mass == pytest.approx(400.0) and found[1].mass == pytest.approx(200.0)
    assert found[0].centre[0] == pytest.approx(-1.4, abs=0.05)
    assert 1.5 < found[0].height < 2.0
    # a larger blob of background Gaussians ranks after the foreground person
    foreground = np.zeros(len(means), bool)
    foreground[400:600] = True
    ranked = split_instances(means, relevant.astype(float), np.full((len(means), 3), SIGMA), relevant,
                             np.array([0.0, 0.0, 1.0]), foreground=foreground)
    np.testing.assert_array_equal(ranked[0].members, small)


def test_the_plan_frames_the_largest_instance_not_the_gap_between_people(people):
    scene, relevant, big, small = people
    plan = plan_highlight(scene, _localizer(people), QUERY, _preset())
    assert len(plan.localization["instances"]) == 2 and plan.localization["framed_instances"] == 1
    orbit = next(s for s in plan.shots if s.name == "orbit")
    assert np.linalg.norm(np.array(orbit.params["centre"])[:2] - [-1.4, 0.0]) < 0.1
    for key in orbit.camera_keys[::6]:
        q = _subject_height(scene, plan, key, key.frame, big)
        assert q["in_frame"] and q["offset"] < 0.1


def test_zoom_and_orbit_reach_the_target_subject_height(people):
    scene, relevant, big, small = people
    plan = plan_highlight(scene, _localizer(people), QUERY, _preset(zoom_target=0.5, orbit_target=0.5))
    zoom = next(s for s in plan.shots if s.name == "zoom")
    start = _subject_height(scene, plan, zoom.camera_keys[0], 0, big)["height"]
    end = _subject_height(scene, plan, zoom.camera_keys[-1], 0, big)["height"]
    assert start < 0.4 and end == pytest.approx(0.5, abs=0.07)
    orbit = next(s for s in plan.shots if s.name == "orbit")
    heights = [_subject_height(scene, plan, k, 0, big)["height"] for k in orbit.camera_keys[::4]]
    assert min(heights) > 0.4 and max(heights) < 0.6, heights


def test_a_best_view_tighter_than_the_zoom_target_starts_wide_and_the_zoom_grows_the_subject(people):
    """A long lens on every camera (the person spans ~0.7 of the frame height at the best view, above the
    zoom's target 0.5): the context shot's lens is widened so the zoom starts at about 0.6 x 0.5 and grows
    the person to 0.5, instead of holding a frame-filling view."""
    scene, relevant, big, small = people
    cams = [Camera.look_at(c.center, (0.0, 0.0, 0.9), width=WIDTH, height=HEIGHT, focal=420.0, name=c.name)
            for c in scene.cameras.cameras(0, "train")]
    tight = Scene(gaussians=scene.gaussians, cameras=CameraRig.static(cams, [], scene.num_timesteps),
                  name="two-people-tele", fps=30.0)
    best = cams[0]
    at_best_view = frame_quality(frame_at(tight.gaussians, 15), big, best)["height"]
    assert at_best_view > 0.65
    localizer = PeopleLocalizer(tight, relevant, segment=(10, 20), centre=(0.0, 0.0, 0.9), best_view="cam00")
    plan = plan_highlight(tight, localizer, QUERY, _preset(zoom_target=0.5, orbit_target=0.5))
    context = next(s for s in plan.shots if s.name == "context")
    zoom = next(s for s in plan.shots if s.name == "zoom")
    wide = _subject_height(tight, plan, context.camera_keys[0], 0, big)["height"]
    start = _subject_height(tight, plan, zoom.camera_keys[0], 0, big)["height"]
    end = _subject_height(tight, plan, zoom.camera_keys[-1], 0, big)["height"]
    assert wide == pytest.approx(0.6 * 0.5, abs=0.05) and start == pytest.approx(wide, abs=0.02), (wide, start)
    assert end == pytest.approx(0.5, abs=0.07), end
    assert any("so the zoom starts wide" in m for m in plan.messages)
    # the widening is bounded: at most half the best view's focal length (output pixels, vertical fit)
    best_view_focal = best.fy * plan.resolution[1] / best.height
    assert context.camera_keys[0].focal_px >= 0.5 * best_view_focal - 1e-6


def test_every_camera_stays_inside_the_ring_and_above_the_floor(people):
    scene, relevant, big, small = people
    for preset in (_preset(), load_preset("broadcast")):
        plan = plan_highlight(scene, _localizer(people), QUERY, preset, resolution=(640, 360))
        eyes = np.array([k.pose.position for s in plan.shots for k in s.camera_keys])
        inner = RING_RADIUS * math.cos(math.pi / 8)      # the octagon's inner radius
        assert (np.linalg.norm(eyes[:, :2], axis=1) <= RING_RADIUS + 0.02).all()
        # inside the octagon of cameras (vertices at 22.5 + k 45 degrees): within the nearest face's half-plane
        angles = np.arctan2(eyes[:, 1], eyes[:, 0])
        face = np.round(angles / (math.pi / 4)) * (math.pi / 4)
        assert (eyes[:, 0] * np.cos(face) + eyes[:, 1] * np.sin(face) <= inner + 0.02).all()
        assert (eyes[:, 2] <= RING_HEIGHT + 0.02).all() and (eyes[:, 2] >= MIN_HEIGHT_M - 0.02).all()


def test_rig_volume_distances_outside_a_box_of_cameras():
    corners = np.array([[x, y, 2.0] for x in (-1, 1) for y in (-1, 1)], dtype=float)
    rig = RigVolume.build(corners, np.array([0, 0, 1.0]), floor=0.0, min_height=0.5)
    assert rig.contains(np.array([[0, 0, 1.0], [0.9, -0.9, 0.6]])).all()
    np.testing.assert_allclose(rig.outside(np.array([[2.0, 0, 1.0], [0, 0, 3.5], [0, 0, 0.2]])), [1.0, 1.5, 0.3])
    assert RigVolume.build(corners[:1], np.array([0, 0, 1.0])) is None


def test_subjects_two_gives_each_person_its_own_zoom_and_orbit(people):
    scene, relevant, big, small = people
    plan = plan_highlight(scene, _localizer(people), QUERY, _preset(subjects=2))
    assert [s.name for s in plan.shots] == ["context", "zoom", "orbit", "zoom 2", "orbit 2", "replay"]
    assert plan.localization["framed_instances"] == 2
    second = next(s for s in plan.shots if s.name == "orbit 2")
    assert second.params["subject"] == 1
    assert np.linalg.norm(np.array(second.params["centre"])[:2] - [1.4, 0.0]) < 0.1
    q = _subject_height(scene, plan, second.camera_keys[-1], 0, small)
    assert q["in_frame"] and q["offset"] < 0.1
    for a, b in zip(plan.shots, plan.shots[1:]):   # the camera never jumps between shots
        np.testing.assert_allclose(b.camera_keys[0].c2w, a.camera_keys[-1].c2w, atol=1e-9)


@pytest.mark.parametrize("mode", ["picked", "all"])
def test_segments_all_gives_a_replay_per_segment(people, mode):
    segments = [(3, 6), (10, 20), (28, 33)]
    plan = plan_highlight(people[0], _localizer(people, segments=segments), QUERY, _preset(segments=mode))
    loc = plan.localization
    assert loc["segment_mode"] == mode and loc["segment"] == [10, 20]
    replays = [s for s in plan.shots if s.effect == "desaturate_background"]
    expected = segments if mode == "all" else [(10, 20)]
    assert loc["highlighted_segments"] == [list(s) for s in expected]
    assert len(replays) == len(expected)
    for shot, (a, b) in zip(replays, expected):
        full = [k.timestep for k in shot.time_keys if plan.desaturation_weight(k.frame) == 1.0]
        assert full and a - 1e-9 <= min(full) and max(full) <= b + 1e-9


def test_a_replay_of_a_subject_standing_near_the_view_widens_its_lens_to_show_it(people):
    """The real capture's "a person": a replay of another segment frames the person found there, who may
    stand much nearer the best view than the person the shots were planned for. Its lens is widened (at
    most to half) so the person fits; the picked segment's replay keeps the anchor's lens."""
    scene, relevant, big, small = people
    means = scene.gaussians.means.copy()
    near = means[:, big].copy()
    near[..., 0] += 3.3 + 1.4          # the larger person at (3.3, 1.37): 1.6 m from cam00, for t < 8
    near[..., 1] += 1.37
    means[:8, big] = near[:8]
    g = scene.gaussians
    moving = Scene(gaussians=GaussianSequence(means=means, rotations=g.rotations, log_scales=g.log_scales,
                                              opacity_logits=g.opacity_logits, colors=g.colors),
                   cameras=scene.cameras, name="two-people-moving", fps=30.0)
    localizer = PeopleLocalizer(moving, relevant, segment=(10, 20), centre=(0.0, 0.0, 0.9), best_view="cam00",
                                segments=[(3, 6), (10, 20)])
    plan = plan_highlight(moving, localizer, QUERY, _preset(segments="all"))
    context = next(s for s in plan.shots if s.name == "context")
    replays = [s for s in plan.shots if s.effect == "desaturate_background"]
    assert len(replays) == 2
    early, picked = replays
    anchor_focal = context.camera_keys[0].focal_px
    assert picked.camera_keys[-1].focal_px == pytest.approx(anchor_focal)
    widened = early.camera_keys[-1].focal_px
    assert 0.5 * anchor_focal - 1e-6 <= widened < anchor_focal
    assert any("its lens is widened" in m and "stands" in m for m in plan.messages)
    key = next(k for k in early.camera_keys if plan.desaturation_weight(k.frame) == 1.0)
    q = _subject_height(moving, plan, key, key.frame, big)
    assert q["in_frame"] and q["height"] <= 0.9, q


def test_blur_background_needs_relevancy_only_where_it_blurs(people):
    scene, relevant, big, small = people
    plan = plan_highlight(scene, _localizer(people), QUERY, _preset(replay_effect="blur_background"))
    assert plan.desaturate is None and plan.blur is not None and plan.blur["radius"] == pytest.approx(0.02)
    blurred = {int(f) for f, w in plan.blur["weights"].items() if w > 0}
    assert blurred and frames_in_ranges(plan.passes["relevancy"]) == blurred
    replay = plan.shots[-1]
    assert blurred <= set(range(replay.frame_start, replay.frame_end + 1))
    # the contact sheet computes relevancy maps only for the blurred frames it shows
    loc = _localizer(people)
    tiles = render_tiles(scene, plan, localizer=loc, per_shot=6, width=96)
    assert loc.stats["relevancy_map"] == sum(t["blur"] > 0 for t in tiles) > 0
    # a plan without masked effects: no relevancy pass and no relevancy map at all
    plain = plan_highlight(scene, _localizer(people), QUERY, _preset().with_shots(["play", "zoom_in", "bullet_time"]))
    assert "relevancy" not in plain.passes and plain.blur is None and plain.desaturate is None
    loc = _localizer(people)
    render_tiles(scene, plain, localizer=loc, per_shot=3, width=64)
    assert loc.stats["relevancy_map"] == 0


def test_blur_keeps_the_relevant_pixels_and_blurs_the_rest():
    rng = np.random.default_rng(0)
    rgb = rng.uniform(0, 1, (40, 60, 3))
    rel = np.zeros((40, 60))
    rel[:, :30] = 1.0
    out = blur_background(rgb, rel, 1.0, 0.05)
    np.testing.assert_array_equal(out[:, :30], rgb[:, :30])
    assert out[:, 35:].std() < 0.5 * rgb[:, 35:].std()
    np.testing.assert_array_equal(blur_background(rgb, rel, 0.0, 0.05), rgb)


def test_the_highlight_job_opens_the_query_engine_for_blur_presets_too():
    from fourlegs_engine.highlight_job import preset_needs_relevancy

    assert preset_needs_relevancy(load_preset("broadcast_blur"))
    assert preset_needs_relevancy(load_preset("broadcast"))
    assert not preset_needs_relevancy(load_preset("broadcast").with_shots(["play", "zoom_in", "bullet_time"]))
