"""Framing the action: region extent, scene up, line of sight past an occluder, the near plane.

The scene: two "players" (the relevant Gaussians) on a floor, and a dense non-relevant "bystander"
standing right between the best camera and the players. The checks are independent of the framing
code: occlusion is measured by sampling the Gaussians' densities along each camera→centre segment in
float64, the region's extent from the players' own Gaussians.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from _highlights_helpers import HEIGHT, WIDTH, FakeLocalizer
from fourlegs_engine.highlights.camera_paths import look_at_rotation
from fourlegs_engine.highlights.framing import NEAR_CLIP_M, Framing, action_region, scene_up
from fourlegs_engine.highlights.planner import plan_highlight
from fourlegs_engine.highlights.presets import load_preset
from fourlegs_engine.render import render_frame
from fourlegs_engine.scene import Camera, CameraRig, GaussianSequence, Scene
from fourlegs_engine.scene.gaussians import GaussianFrame

QUERY = "a person"
SIGMA = 0.06
OPACITY = 0.95


def _blob(rng, centre, size, count):
    return np.asarray(centre) + rng.uniform(-1, 1, (count, 3)) * np.asarray(size)


def occluded_scene(T: int = 12):
    """(scene, relevant mask, best camera name): players around (0, 0, 0.9), a bystander between
    camera 'cam00' (on +x) and them, a floor; world up +z."""
    rng = np.random.default_rng(3)
    # two players close enough to be one instance (a gap narrower than the instance link distance)
    players = np.concatenate([_blob(rng, (0.0, -0.2, 0.9), (0.15, 0.12, 0.8), 150),
                              _blob(rng, (0.0, 0.2, 0.9), (0.15, 0.12, 0.8), 150)])
    bystander = _blob(rng, (1.6, 0.0, 0.9), (0.15, 0.25, 0.8), 200)
    floor = np.concatenate([rng.uniform(-2.5, 2.5, (150, 2)), np.zeros((150, 1))], axis=1)
    means = np.concatenate([players, bystander, floor]).astype(np.float32)
    N = len(means)
    relevant = np.zeros(N, bool)
    relevant[:len(players)] = True
    rot = np.zeros((T, N, 4), np.float32)
    rot[..., 0] = 1
    colors = np.where(relevant[:, None], [0.9, 0.2, 0.1], [0.3, 0.3, 0.8]).astype(np.float32)
    g = GaussianSequence(means=np.broadcast_to(means, (T, N, 3)).copy(), rotations=rot,
                         log_scales=np.full((N, 3), math.log(SIGMA), np.float32),
                         opacity_logits=np.full(N, math.log(OPACITY / (1 - OPACITY)), np.float32), colors=colors)
    cams = []
    for i in range(8):
        a = 2 * math.pi * i / 8
        eye = (3.2 * math.cos(a), 3.2 * math.sin(a), 1.8)
        cams.append(Camera.look_at(eye, (0.0, 0.0, 0.9), width=WIDTH, height=HEIGHT, focal=220.0, name=f"cam{i:02d}"))
    return Scene(gaussians=g, cameras=CameraRig.static(cams, [], T), name="occluded", fps=30.0), relevant


class RegionLocalizer(FakeLocalizer):
    """The fake localizer plus per-Gaussian relevancy (1 on the players, 0 elsewhere)."""

    def __init__(self, scene, relevant, **kw):
        super().__init__(scene, **kw)
        self.relevant = relevant

    def gaussian_relevancy(self, query, t):
        self.stats["gaussian_relevancy"] += 1
        return torch.as_tensor(self.relevant.astype(np.float32))


def sampled_occlusion(eye, target, means, exclude, samples=400):
    """1 - prod(1 - max alpha along the segment) over the non-excluded isotropic Gaussians (float64)."""
    s = np.linspace(0.0, 1.0, samples)[:, None]
    pts = eye[None] + s * (target - eye)[None]                                   # (S,3)
    m = means[~exclude].astype(np.float64)
    d2 = ((pts[:, None, :] - m[None]) ** 2).sum(-1) / SIGMA ** 2                 # (S,M)
    alpha = OPACITY * np.exp(-0.5 * d2.min(axis=0))
    alpha[d2.min(axis=0) > 9.0] = 0.0
    return 1.0 - float(np.prod(1.0 - alpha))


@pytest.fixture(scope="module")
def planned():
    scene, relevant = occluded_scene()
    loc = RegionLocalizer(scene, relevant, segment=(3, 8), centre=(0.3, 0.0, 1.0), best_view="cam00")
    plan = plan_highlight(scene, loc, QUERY, load_preset("broadcast"), resolution=(640, 360))
    return scene, relevant, plan


def test_scene_up_comes_from_the_cameras_right_vectors():
    ring = occluded_scene(T=2)[0].cameras.cameras(0)
    np.testing.assert_array_equal(scene_up(ring), [0.0, 0.0, 1.0])
    # the same rig turned so that -y is up (the Panoptic convention), plus one camera looking straight down
    turn = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])                    # +z -> -y
    turned = [Camera(K=c.K, w2c=np.block([[c.w2c[:3, :3] @ turn.T, c.w2c[:3, 3:]], [np.zeros((1, 3)), np.ones((1, 1))]]),
                     width=c.width, height=c.height) for c in ring]
    top = Camera.look_at((0, -5.0, 0), (0, 0, 0), up=(1.0, 0, 0), width=WIDTH, height=HEIGHT, focal=200.0)
    np.testing.assert_array_equal(scene_up(turned + [top]), [0.0, -1.0, 0.0])
    assert scene_up([]) @ np.array([0, 0, 1.0]) == 1.0


def test_action_region_is_robust_to_stray_relevant_gaussians():
    rng = np.random.default_rng(0)
    pts = rng.normal(0, 0.2, (400, 3))
    stray = np.array([[5.0, 5.0, 5.0], [-6.0, 0.0, 0.0], [-6.05, 0.0, 0.0], [0.0, -4.0, 1.0]])
    means = np.concatenate([pts, stray])
    region = action_region(means, np.ones(len(means)), np.full((len(means), 3), 0.1), np.ones(len(means)))
    assert not region.members[400:].any()          # lone relevant Gaussians are not the action
    assert np.linalg.norm(region.centre) < 0.1
    reach = np.linalg.norm(pts[region.members[:400]] - region.centre, axis=1)
    assert region.members[:400].mean() > 0.9
    assert np.percentile(reach, 95) < region.radius < 1.2
    assert action_region(means, np.zeros(len(means)), np.ones((len(means), 3)), np.ones(len(means))) is None


def test_the_bystander_really_blocks_the_best_views_straight_dolly(planned):
    scene, relevant, plan = planned
    centre = np.array(plan.localization["action_region"]["centre"])
    means = scene.gaussians.means[0]
    best = scene.cameras.find("cam00").center
    assert sampled_occlusion(best + 0.5 * (centre - best), centre, means, relevant) > 0.9


@pytest.mark.parametrize("shot_name", ["zoom", "bullet_time"])
def test_zoom_and_orbit_keep_a_clear_line_of_sight_and_frame_the_whole_region(planned, shot_name):
    scene, relevant, plan = planned
    shot = next(s for s in plan.shots if s.name == shot_name)
    assert shot.params["clear"] is True, plan.messages
    centre = np.array(plan.localization["action_region"]["centre"])
    means = scene.gaussians.means[0].astype(np.float64)
    players = means[relevant]
    assert len(plan.localization["instances"]) == 1
    W, H = plan.resolution
    for key in shot.camera_keys[1:]:   # the first key is where the previous shot ended
        eye = key.pose.position
        assert sampled_occlusion(eye, centre, means, relevant | (np.linalg.norm(means - centre, axis=1) < 0.0)) <= 0.25
        # nothing within the near plane: every Gaussian's 3-sigma sphere stays beyond it
        assert (np.linalg.norm(means - eye, axis=1) - 3 * SIGMA).min() >= NEAR_CLIP_M
        # every player Gaussian (3 sigma) is in front of the camera and inside the image
        cam = key.pose.rotation.T @ (players - eye).T
        assert (cam[2] > 3 * SIGMA).all()
        u = key.focal_px * cam[0] / cam[2] + W / 2
        v = key.focal_px * cam[1] / cam[2] + H / 2
        pad = key.focal_px * 3 * SIGMA / cam[2]
        assert (u - pad >= 0).all() and (u + pad <= W).all() and (v - pad >= 0).all() and (v + pad <= H).all()
        # upright: the image's up is the scene's (+z) side of the horizon, no roll
        assert abs(key.pose.rotation[:, 0] @ np.array([0, 0, 1.0])) < 1e-8
        assert key.pose.up @ np.array([0, 0, 1.0]) > 0


def test_orbit_encloses_the_region_and_turns_about_the_scene_up(planned):
    scene, relevant, plan = planned
    orbit = next(s for s in plan.shots if s.effect == "bullet_time")
    centre = np.array(orbit.params["centre"])
    players = scene.gaussians.means[0][relevant].astype(np.float64)
    enclosing = np.linalg.norm(players - centre, axis=1).max() + 3 * SIGMA
    eyes = np.array([k.pose.position for k in orbit.camera_keys])
    rel = eyes - centre
    assert (np.linalg.norm(rel, axis=1) > enclosing + NEAR_CLIP_M).all()
    turned = np.degrees(np.unwrap(np.arctan2(rel[:, 1], rel[:, 0])))
    assert abs(turned[-1] - turned[0]) == pytest.approx(180.0, abs=1e-6)
    # scene time frozen at the peak
    assert {k.timestep for k in orbit.time_keys} == {float(plan.localization["peak"])}
    # not a rigid turn of the start pose: the add-on must play its keys, not rebuild it as a pivot rig
    assert orbit.params["rigid"] is False


def test_a_rig_with_minus_y_up_orbits_about_y(planned):
    """The same scene expressed with -y up (the Panoptic convention): same framing, rotated."""
    scene, relevant, _ = planned
    turn = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])                    # +z -> -y
    g = scene.gaussians
    means = (g.means.astype(np.float64) @ turn.T).astype(np.float32)
    cams = [Camera(K=c.K, w2c=np.block([[c.w2c[:3, :3] @ turn.T, c.w2c[:3, 3:]], [np.zeros((1, 3)), np.ones((1, 1))]]),
                   width=c.width, height=c.height, name=c.name) for c in scene.cameras.cameras(0)]
    turned = Scene(gaussians=GaussianSequence(means=means, rotations=g.rotations, log_scales=g.log_scales,
                                              opacity_logits=g.opacity_logits, colors=g.colors),
                   cameras=CameraRig.static(cams, [], g.num_timesteps), name="turned", fps=30.0)
    loc = RegionLocalizer(turned, relevant, segment=(3, 8), centre=turn @ np.array([0.3, 0.0, 1.0]), best_view="cam00")
    plan = plan_highlight(turned, loc, QUERY, load_preset("broadcast"), resolution=(640, 360))
    assert plan.localization["up"] == [0.0, -1.0, 0.0]
    orbit = next(s for s in plan.shots if s.effect == "bullet_time")
    eyes = np.array([k.pose.position for k in orbit.camera_keys])
    centre = np.array(orbit.params["centre"])
    heights = -(eyes - centre)[:, 1]
    assert heights.min() > 0                       # above the action, never under the floor
    for key in orbit.camera_keys[1:] + next(s for s in plan.shots if s.name == "replay").camera_keys:
        assert abs(key.pose.rotation[:, 0] @ np.array([0, -1.0, 0])) < 1e-9   # level about -y


def _one_gaussian(z: float, sigma: float) -> GaussianFrame:
    t = lambda a: torch.tensor(a, dtype=torch.float32)
    return GaussianFrame(means=t([[0.0, 0.0, z]]), rotations=t([[1.0, 0, 0, 0]]),
                         log_scales=t([[math.log(sigma)] * 3]), opacity_logits=t([4.0]), colors=t([[1.0, 1.0, 1.0]]))


def test_near_plane_culls_whole_gaussians_by_their_centre():
    """The renderer draws a Gaussian whose centre is beyond the near plane whole (its nearer part
    included) and drops one whose centre is nearer, whatever its extent: a framed camera must keep
    every Gaussian's 3-sigma extent beyond the near plane, which the planner does (test above)."""
    cam = Camera(K=np.array([[100.0, 0, 32], [0, 100.0, 32], [0, 0, 1]]), w2c=np.eye(4), width=64, height=64,
                 near=NEAR_CLIP_M, far=100.0)
    crossing = render_frame(_one_gaussian(NEAR_CLIP_M + 0.01, 0.05), cam, outputs=("alpha",))["alpha"]
    behind = render_frame(_one_gaussian(NEAR_CLIP_M - 0.01, 0.05), cam, outputs=("alpha",))["alpha"]
    assert float(crossing.max()) > 0.9         # drawn, although 3 sigma reach 0.14 m in front of the near plane
    assert float(behind.max()) == 0.0          # centre nearer than the near plane: the whole splat is cut


def test_replay_keeps_every_relevant_gaussian_in_colour_in_every_desaturated_frame(planned):
    """The renderer's relevancy pass (per-Gaussian relevancy rendered like a colour and divided by the
    coverage, as the add-on's engine does) stays above the compositor's grey ramp (0.6) on every pixel
    the players cover, at the replay's camera and scene time, on every frame the plan desaturates."""
    from fourlegs_engine.highlights.preview import frame_at, key_camera

    scene, relevant, plan = planned
    replay = next(s for s in plan.shots if s.effect == "desaturate_background")
    rel = torch.as_tensor(relevant.astype(np.float32))[:, None]
    frames = [f for f in range(replay.frame_start, replay.frame_end + 1) if plan.desaturation_weight(f) > 0]
    assert len(frames) >= 10
    covered_total = 0
    for f in frames:
        key = replay.camera_keys[f - replay.frame_start]
        cam = key_camera(key, plan, 160, near=NEAR_CLIP_M)
        g = frame_at(scene.gaussians, replay.time_keys[f - replay.frame_start].timestep)
        hw = (cam.height, cam.width)
        out = render_frame(g, cam, outputs=("alpha", "depth", "features"), features=rel)
        alpha = out["alpha"].reshape(hw).numpy()
        relevancy = out["features"].reshape(hw).numpy() / np.maximum(alpha, 1e-3)
        players_only = GaussianFrame(means=g.means[relevant], rotations=g.rotations[relevant],
                                     log_scales=g.log_scales[relevant], opacity_logits=g.opacity_logits[relevant],
                                     colors=g.colors[relevant])
        mine = render_frame(players_only, cam, outputs=("alpha", "depth"))
        # pixels where the players are the surface seen (nothing else in front of them)
        visible = ((mine["alpha"].reshape(hw).numpy() > 0.9)
                   & (np.abs(out["depth"].reshape(hw).numpy() - mine["depth"].reshape(hw).numpy()) < 0.05))
        covered_total += int(visible.sum())
        # (a frame of the swing to the replay camera may see the players only behind the bystander)
        assert not visible.any() or (relevancy[visible] >= 0.6).mean() > 0.97, f"frame {f}"
        # upright replay camera: the image's x axis is horizontal
        assert abs(key.pose.rotation[:, 0] @ np.array([0, 0, 1.0])) < 1e-6
    assert covered_total > 100 * len(frames)


def test_orbit_never_frames_the_action_closer_than_the_zoom_it_continues():
    """Bullet-time continues the zoom: its magnification (focal / distance to the action) stays at or
    below the zoom's end, so a small action (a ball) is not blown up to fill the frame."""
    scene, players = occluded_scene()
    means = scene.gaussians.means[0]
    ball = players & (np.linalg.norm(means - np.array([0.0, -0.35, 1.5]), axis=1) < 0.15)
    assert 3 <= ball.sum() < 30
    loc = RegionLocalizer(scene, ball, segment=(3, 8), centre=(0.0, -0.35, 1.5), best_view="cam02")
    plan = plan_highlight(scene, loc, QUERY, load_preset("broadcast"), resolution=(640, 360))
    zoom = next(s for s in plan.shots if s.effect == "zoom_in")
    orbit = next(s for s in plan.shots if s.effect == "bullet_time")
    centre = np.array(orbit.params["centre"])
    end = zoom.camera_keys[-1]
    zoom_magnification = end.focal_px / np.linalg.norm(end.pose.position - centre)
    for key in orbit.camera_keys:
        assert key.focal_px / np.linalg.norm(key.pose.position - centre) <= zoom_magnification * (1 + 1e-9)
