"""The planner: demand-driven localization, passes, effects, continuity and edge cases."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from _highlights_helpers import HEIGHT, WIDTH, FakeLocalizer, ring_cameras, tiny_scene
from fourlegs_engine.errors import InputError
from fourlegs_engine.highlights.camera_paths import is_proper_rotation, rotation_angle
from fourlegs_engine.highlights.plan import HighlightPlan, frames_in_ranges
from fourlegs_engine.highlights.planner import plan_highlight, plan_needs
from fourlegs_engine.highlights.presets import load_preset, parse_preset
from fourlegs_engine.scene import Camera

QUERY = "a ball flying in the air"


def project(key, point, resolution):
    pose = key.pose
    cam = pose.rotation.T @ (np.asarray(point) - pose.position)
    W, H = resolution
    return np.array([key.focal_px * cam[0] / cam[2] + W / 2, key.focal_px * cam[1] / cam[2] + H / 2]), cam[2]


def assert_continuous(plan: HighlightPlan):
    for a, b in zip(plan.shots, plan.shots[1:]):
        ka, kb = a.camera_keys[-1], b.camera_keys[0]
        np.testing.assert_allclose(kb.c2w, ka.c2w, atol=1e-9, err_msg=f"{a.name} -> {b.name}")
        assert kb.focal_px == pytest.approx(ka.focal_px, rel=1e-12)


def all_keys(plan):
    return [k for s in plan.shots for k in s.camera_keys]


def all_times(plan):
    return np.array([k.timestep for s in plan.shots for k in s.time_keys])


@pytest.fixture(scope="module")
def scene():
    return tiny_scene()


def preset_of(*shots, **top):
    return parse_preset({"name": "test", "fps": top.pop("fps", 24), "resolution": top.pop("resolution", [640, 360]),
                         **top, "shots": list(shots)})


# ----------------------------------------------------------------------------------- the broadcast plan
def test_broadcast_has_all_four_effects_and_only_the_passes_they_need(scene):
    loc = FakeLocalizer(scene, segment=(14, 30))
    plan = plan_highlight(scene, loc, QUERY, load_preset("broadcast"))
    assert plan.effects == ["play", "zoom_in", "bullet_time", "desaturate_background"]
    assert loc.needs == [{"temporal", "best_view", "action_centre"}] and loc.stats["localize"] == 1
    assert plan.passes["rgb"] == [[plan.frame_start, plan.frame_end]]
    assert "depth" not in plan.passes
    replay = plan.shots[-1]
    rel_frames = frames_in_ranges(plan.passes["relevancy"])
    assert rel_frames and rel_frames <= set(range(replay.frame_start, replay.frame_end + 1))
    assert plan.desaturate["ranges"] == plan.passes["relevancy"]
    assert set(map(int, plan.desaturate["weights"])) == rel_frames
    assert plan.localization["computed"] == ["temporal", "best_view", "action_centre"]
    assert plan.localization["segment"] == [14, 30] and plan.localization["peak"] == 22
    json.dumps(plan.to_dict(), allow_nan=False)
    assert_continuous(plan)
    # the context shot runs up to the segment start; the bullet-time holds the peak
    assert plan.shots[0].time_keys[-1].timestep == pytest.approx(14.0)
    assert {k.timestep for k in plan.shots[2].time_keys} == {22.0}


def test_plan_json_round_trip_and_validation(scene, tmp_path):
    plan = plan_highlight(scene, FakeLocalizer(scene), QUERY, load_preset("broadcast"))
    path = tmp_path / "plan.json"
    plan.save(path)
    again = HighlightPlan.load(path)
    assert again.to_dict() == json.loads(path.read_text())
    d = plan.to_dict()
    assert d["format"] == "fourlegs-highlight-plan" and d["version"] == 1
    assert set(d) >= {"scene", "query", "localization", "fps", "resolution", "frame_start", "frame_end", "shots",
                      "passes", "desaturate", "messages"}
    key = d["shots"][0]["camera_keys"][0]
    assert set(key) == {"frame", "c2w", "focal_px", "lens_mm", "sensor_width_mm"}
    assert key["lens_mm"] == pytest.approx(key["focal_px"] * key["sensor_width_mm"] / d["resolution"][0])
    with pytest.raises(Exception):
        plan.save(path)  # existing output is not overwritten unless asked
    bad = json.loads(path.read_text())
    bad["version"] = 2
    with pytest.raises(InputError, match="version"):
        HighlightPlan.from_dict(bad, file=path)
    bad = json.loads(path.read_text())
    bad["shots"][1]["camera_keys"].pop(3)
    with pytest.raises(InputError, match=r"shots\[1\].camera_keys"):
        HighlightPlan.from_dict(bad, file=path)
    bad = json.loads(path.read_text())
    bad["shots"][0]["camera_keys"][0]["c2w"][0][0] = 3.0
    with pytest.raises(InputError, match="rigid"):
        HighlightPlan.from_dict(bad)


# ----------------------------------------------------------------------------------- demand-driven
def test_zoom_only_requests_no_relevancy_pass_and_no_per_frame_maps(scene):
    loc = FakeLocalizer(scene)
    preset = load_preset("broadcast").with_shots(["zoom_in"])
    plan = plan_highlight(scene, loc, QUERY, preset)
    assert plan.effects == ["zoom_in"]
    assert set(plan.passes) == {"rgb"} and plan.desaturate is None
    # maps only for the best-view search (one per camera) and the action centre: none per frame
    assert loc.stats["relevancy_map"] == scene.cameras.num_cameras("train") + 1
    assert plan.frame_end - plan.frame_start + 1 > loc.stats["relevancy_map"]


def test_desaturate_requests_relevancy_only_for_the_segment_plus_fades(scene):
    loc = FakeLocalizer(scene, segment=(18, 25))
    shot = {"effect": "desaturate_background", "camera": "best_view", "from": "start", "to": "end",
            "fade_in_frames": 5, "fade_out_frames": 7}
    plan = plan_highlight(scene, loc, QUERY, preset_of(shot))
    assert loc.needs == [{"temporal", "best_view"}]
    assert loc.stats["action_centre"] == 0
    frames = np.arange(plan.frame_start, plan.frame_end + 1)
    t = all_times(plan)
    inside = frames[(t >= 18) & (t <= 25)]
    expected = set(range(inside[0] - 5, inside[-1] + 7 + 1))
    assert frames_in_ranges(plan.passes["relevancy"]) == expected
    assert len(plan.passes["relevancy"]) == 1
    w = plan.desaturate["weights"]
    assert all(w[str(f)] == 1.0 for f in inside)
    ramp_in = [w[str(f)] for f in range(inside[0] - 5, inside[0])]
    ramp_out = [w[str(f)] for f in range(inside[-1] + 1, inside[-1] + 8)]
    assert all(0 < v < 1 for v in ramp_in + ramp_out)
    assert np.all(np.diff(ramp_in) > 0) and np.all(np.diff(ramp_out) < 0)


def test_needs_follow_the_preset():
    assert plan_needs(load_preset("bullet_time_only")) == {"temporal", "best_view", "action_centre"}
    assert plan_needs(load_preset("subtle_desaturate")) == {"temporal", "best_view"}
    named = preset_of({"effect": "play", "camera": "cam02", "from": "start", "to": "end"})
    assert plan_needs(named) == set()


def test_a_preset_needing_nothing_never_calls_the_localizer(scene):
    preset = preset_of({"effect": "play", "camera": "cam02", "from": "start", "to": "end"})
    plan = plan_highlight(scene, None, QUERY, preset)
    assert plan.localization["found"] is None and plan.localization["computed"] == []
    assert plan.effects == ["play"]
    cam = scene.cameras.find("cam02")
    np.testing.assert_allclose(plan.shots[0].camera_keys[0].c2w, cam.c2w, atol=1e-12)
    assert plan.shots[0].time_keys[0].timestep == 0 and plan.shots[0].time_keys[-1].timestep == 47
    with pytest.raises(InputError, match="needs a localization"):
        plan_highlight(scene, None, QUERY, load_preset("broadcast"))


def test_query_not_found_gives_a_plan_without_localized_effects(scene):
    loc = FakeLocalizer(scene, found=False)
    plan = plan_highlight(scene, loc, "a unicorn", load_preset("broadcast"))
    assert plan.effects == ["play"] and len(plan.shots) == 1
    assert set(plan.passes) == {"rgb"} and plan.desaturate is None
    assert loc.stats["best_view"] == 0 and loc.stats["action_centre"] == 0 and loc.stats["relevancy_map"] == 0
    assert plan.localization["found"] is False
    msg = " ".join(plan.messages)
    assert "'a unicorn' was not found" in msg and "no localized effects" in msg
    assert "zoom" in msg and "bullet_time" in msg and "replay" in msg
    t = all_times(plan)
    assert t[0] == 0 and t[-1] == scene.num_timesteps - 1
    json.dumps(plan.to_dict(), allow_nan=False)


def test_missing_action_centre_drops_only_the_effects_that_need_it(scene):
    loc = FakeLocalizer(scene, centre=None)
    plan = plan_highlight(scene, loc, QUERY, load_preset("broadcast"))
    assert plan.effects == ["play", "desaturate_background"]
    assert any("'zoom' (zoom_in) left out: action_centre" in m for m in plan.messages)
    assert_continuous(plan)


# ----------------------------------------------------------------------------------- effects
@pytest.mark.parametrize("mode", ["dolly", "focal"])
def test_zoom_keeps_the_action_framed_on_every_key(scene, mode):
    centre = np.array([0.6, 0.4, 1.2])
    loc = FakeLocalizer(scene, centre=centre, best_view="cam00")
    preset = preset_of({"effect": "play", "camera": "best_view"},
                       {"effect": "zoom_in", "mode": mode, "factor": 3.0}, recentre=False)
    plan = plan_highlight(scene, loc, QUERY, preset)
    zoom = plan.shots[1]
    for key in zoom.camera_keys:
        uv, z = project(key, centre, plan.resolution)
        assert z > 0 and 0 <= uv[0] <= plan.resolution[0] and 0 <= uv[1] <= plan.resolution[1]
    # it really magnifies: 3x by distance (dolly) or by focal length (focal), eased
    first, last = zoom.camera_keys[0], zoom.camera_keys[-1]
    size = lambda k: k.focal_px / np.linalg.norm(k.pose.position - centre)
    assert size(last) / size(first) == pytest.approx(3.0, rel=1e-6)
    sizes = np.array([size(k) for k in zoom.camera_keys])
    assert np.all(np.diff(sizes) >= -1e-12)
    assert sizes[1] - sizes[0] < sizes[len(sizes) // 2] - sizes[len(sizes) // 2 - 1]  # eased start
    assert_continuous(plan)


def test_recentred_best_view_puts_the_action_mid_frame(scene):
    centre = np.array([0.6, 0.4, 1.2])
    plan = plan_highlight(scene, FakeLocalizer(scene, centre=centre), QUERY, load_preset("broadcast"))
    for shot in plan.shots[:3]:
        for key in shot.camera_keys:
            uv, z = project(key, centre, plan.resolution)
            np.testing.assert_allclose(uv, np.array(plan.resolution) / 2, atol=1e-6)


def test_bullet_time_freezes_time_orbits_the_centre_and_never_flips(scene):
    centre = np.array([0.1, 0.2, 1.0])
    loc = FakeLocalizer(scene, centre=centre, segment=(10, 20))
    plan = plan_highlight(scene, loc, QUERY, preset_of({"effect": "bullet_time", "arc_deg": 270, "duration_s": 2}))
    shot = plan.shots[0]
    assert shot.num_frames == 48 and {k.timestep for k in shot.time_keys} == {15.0}
    rel = np.array([k.pose.position - centre for k in shot.camera_keys])
    np.testing.assert_allclose(np.hypot(rel[:, 0], rel[:, 1]), math.hypot(*rel[0, :2]))
    np.testing.assert_allclose(rel[:, 2], rel[0, 2])
    ang = np.unwrap(np.arctan2(rel[:, 1], rel[:, 0]))
    assert ang[-1] - ang[0] == pytest.approx(math.radians(270))
    steps = [rotation_angle(a.pose.rotation, b.pose.rotation) for a, b in zip(shot.camera_keys, shot.camera_keys[1:])]
    assert max(steps) < math.radians(270) / 47 * 2  # eased: peak speed < 2x the mean
    assert steps[0] < steps[len(steps) // 2] and steps[-1] < steps[len(steps) // 2]  # eased in/out
    assert shot.params["radius"] == pytest.approx(math.hypot(*rel[0, :2]))


def test_bullet_time_from_a_straight_down_best_view(scene):
    centre = np.array([0.0, 0.0, 1.0])
    top = Camera.look_at([0.0, 0.0, 6.0], centre, width=WIDTH, height=HEIGHT, focal=200.0, name="top")
    sc = tiny_scene(cameras=ring_cameras(4) + [top])
    loc = FakeLocalizer(sc, centre=centre, best_view="top")
    plan = plan_highlight(sc, loc, QUERY, load_preset("broadcast"))
    for key in all_keys(plan):
        assert is_proper_rotation(key.pose.rotation) and np.all(np.isfinite(key.c2w))
    orbit = plan.shots[2].camera_keys
    steps = [rotation_angle(a.pose.rotation, b.pose.rotation) for a, b in zip(orbit, orbit[1:])]
    assert max(steps) < math.radians(180) / (len(orbit) - 1) * 2
    for key in orbit:  # radius 0: it spins in place, still looking straight down at the centre
        np.testing.assert_allclose(key.pose.forward, [0, 0, -1], atol=1e-9)
    assert_continuous(plan)


def test_action_centre_behind_the_best_camera(scene):
    cam = scene.cameras.find("cam01")
    behind = cam.center - 2.0 * cam.forward
    loc = FakeLocalizer(scene, centre=behind, best_view="cam01")
    plan = plan_highlight(scene, loc, QUERY, load_preset("broadcast"))
    assert any("behind the best view" in m for m in plan.messages)
    for shot in plan.shots[:3]:
        for key in shot.camera_keys:
            uv, z = project(key, behind, plan.resolution)
            assert z > 0 and np.allclose(uv, np.array(plan.resolution) / 2, atol=1e-6)
    assert_continuous(plan)


def test_action_centre_outside_the_frustum_without_recentring(scene):
    cam = scene.cameras.find("cam01")
    outside = cam.center + 3.0 * cam.forward + 5.0 * cam.c2w[:3, 0]  # far to the right of the frame
    loc = FakeLocalizer(scene, centre=outside, best_view="cam01")
    preset = preset_of({"effect": "play", "camera": "best_view"}, {"effect": "zoom_in"},
                       {"effect": "bullet_time"}, recentre=False)
    plan = plan_highlight(scene, loc, QUERY, preset)
    zoom = plan.shots[1].camera_keys
    uv, z = project(zoom[-1], outside, plan.resolution)
    assert z > 0 and np.allclose(uv, np.array(plan.resolution) / 2, atol=1e-6)  # the zoom turns onto it
    for key in all_keys(plan):
        assert is_proper_rotation(key.pose.rotation)
    assert_continuous(plan)


# ----------------------------------------------------------------------------------- edges
@pytest.mark.parametrize("segment", [(0, 6), (40, 47), (0, 47), (20, 20), (0, 0), (47, 47)])
@pytest.mark.parametrize("preset_name", ["broadcast", "subtle_desaturate", "social_vertical"])
def test_segments_at_the_edges_and_one_frame_segments(scene, segment, preset_name):
    loc = FakeLocalizer(scene, segment=segment)
    plan = plan_highlight(scene, loc, QUERY, load_preset(preset_name))
    json.dumps(plan.to_dict(), allow_nan=False)
    t = all_times(plan)
    assert np.all((t >= 0) & (t <= scene.num_timesteps - 1))
    for s in plan.shots:
        assert s.num_frames >= 1
    assert_continuous(plan)
    if "relevancy" in plan.passes:  # desaturation covers the frames showing the segment
        frames = np.arange(plan.frame_start, plan.frame_end + 1)
        showing = set(frames[(t >= segment[0]) & (t <= segment[1])].tolist())
        desat_shots = [s for s in plan.shots if s.effect == "desaturate_background"]
        desat_frames = {f for s in desat_shots for f in range(s.frame_start, s.frame_end + 1)}
        assert showing & desat_frames <= frames_in_ranges(plan.passes["relevancy"])


def test_one_frame_shots_keep_the_camera_continuous(scene):
    preset = preset_of({"effect": "play", "camera": "best_view", "from": "peak", "from_offset_s": 0, "to": "peak",
                        "min_duration_s": 0},
                       {"effect": "zoom_in", "duration_s": 0.01},
                       {"effect": "bullet_time", "duration_s": 0.01},
                       {"effect": "desaturate_background", "camera": "cam03", "duration_s": 0.01})
    plan = plan_highlight(scene, FakeLocalizer(scene, segment=(20, 20)), QUERY, preset)
    assert [s.num_frames for s in plan.shots] == [1, 1, 1, 1]
    assert_continuous(plan)


@pytest.mark.parametrize("fps", [23.976, 29.97, 60.0, 12.0])
def test_output_fps_override_and_rounding(scene, fps):
    plan = plan_highlight(scene, FakeLocalizer(scene), QUERY, load_preset("broadcast"), fps=fps,
                          resolution=(200, 100))
    assert plan.fps == fps and plan.resolution == (200, 100)
    bullet = plan.shots[2]
    assert bullet.num_frames == int(math.floor(3.0 * fps + 0.5))
    json.dumps(plan.to_dict(), allow_nan=False)


def test_social_vertical_is_9_16_and_keeps_the_vertical_field_of_view(scene):
    plan = plan_highlight(scene, FakeLocalizer(scene, best_view="cam02"), QUERY, load_preset("social_vertical"))
    assert plan.resolution == (1080, 1920)
    cam = scene.cameras.find("cam02")
    assert plan.shots[0].camera_keys[0].focal_px == pytest.approx(cam.fy * 1920 / cam.height)


def test_unknown_camera_name_is_a_clear_error(scene):
    preset = preset_of({"effect": "play", "camera": "nope", "from": "start", "to": "end"})
    with pytest.raises(InputError, match="no camera named 'nope'.*cam00"):
        plan_highlight(scene, None, QUERY, preset)


@settings(max_examples=25)
@given(cx=st.floats(-3, 3), cy=st.floats(-3, 3), cz=st.floats(-1, 4), view=st.integers(0, 5),
       a=st.integers(0, 47), length=st.integers(0, 47), arc=st.floats(-400, 400))
def test_property_random_plans_are_valid_finite_and_continuous(scene, cx, cy, cz, view, a, length, arc):
    segment = (a, min(47, a + length))
    loc = FakeLocalizer(scene, segment=segment, centre=(cx, cy, cz), best_view=f"cam{view:02d}")
    preset = load_preset("broadcast")
    preset.shots[2].params["arc_deg"] = arc
    plan = plan_highlight(scene, loc, QUERY, preset)
    plan.validate()
    json.dumps(plan.to_dict(), allow_nan=False)
    for key in all_keys(plan):
        assert is_proper_rotation(key.pose.rotation) and np.all(np.isfinite(key.c2w)) and key.focal_px > 0
    assert_continuous(plan)
    keys = all_keys(plan)
    steps = [rotation_angle(x.pose.rotation, y.pose.rotation) for x, y in zip(keys, keys[1:])]
    assert max(steps) < math.radians(30)


def test_depth_pass_only_for_shots_with_depth_of_field(scene):
    preset = preset_of({"effect": "play", "camera": "best_view"},
                       {"effect": "zoom_in", "depth_of_field": True}, {"effect": "bullet_time"})
    plan = plan_highlight(scene, FakeLocalizer(scene), QUERY, preset)
    zoom = plan.shots[1]
    assert plan.passes["depth"] == [[zoom.frame_start, zoom.frame_end]]
    assert "relevancy" not in plan.passes
    assert zoom.params["depth_of_field"] is True and plan.shots[2].params["depth_of_field"] is False
