"""Easing curves, frame rounding and scene-time remapping."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, strategies as st

from fourlegs_engine.errors import InputError
from fourlegs_engine.highlights import timing


@pytest.mark.parametrize("name", sorted(timing.EASINGS))
def test_easing_endpoints_monotone_and_clipped(name):
    s = np.linspace(-0.5, 1.5, 2001)
    e = timing.ease(name, s)
    assert e[0] == 0.0 and e[-1] == 1.0
    assert np.all(np.diff(e) >= -1e-12)
    assert timing.ease(name, 0.0) == 0.0 and timing.ease(name, 1.0) == pytest.approx(1.0, abs=1e-15)
    assert np.all((e >= 0) & (e <= 1))


@pytest.mark.parametrize("name", ["smoothstep", "smootherstep", "ease_in_out_sine", "ease_in_out_cubic"])
def test_in_out_easings_start_and_stop_gently_and_are_symmetric(name):
    h = 1e-4
    assert timing.ease(name, h) / h < 0.01          # zero slope at the start
    assert (1 - timing.ease(name, 1 - h)) / h < 0.01  # and at the end
    s = np.linspace(0, 1, 101)
    np.testing.assert_allclose(timing.ease(name, s) + timing.ease(name, 1 - s), 1.0, atol=1e-12)


def test_unknown_easing_names_the_field():
    with pytest.raises(InputError, match="easing.*unknown easing 'bouncy'"):
        timing.ease("bouncy", 0.5)


@pytest.mark.parametrize("seconds,fps,frames", [
    (2.5, 24, 60), (1.0, 23.976, 24), (0.0, 24, 1), (1 / 3, 30, 10), (0.1, 24, 2), (0.0625, 24, 2),
    (10.0, 29.97, 300), (0.02, 24, 1), (3.0, 24, 72), (0.7, 30, 21)])
def test_frames_for_duration_rounds_to_nearest_frame_ties_up(seconds, fps, frames):
    assert timing.frames_for_duration(seconds, fps) == frames


@pytest.mark.parametrize("seconds,fps", [(-1.0, 24), (float("nan"), 24), (1.0, 0), (1.0, float("inf")), (1.0, -24)])
def test_frames_for_duration_refuses_bad_input(seconds, fps):
    with pytest.raises(InputError):
        timing.frames_for_duration(seconds, fps)


def test_play_frame_count_real_time_and_slow_motion():
    # 30 timesteps at 30 fps = 1 s of scene time: 24 intervals at 24 fps -> 25 frames (ends shown).
    assert timing.play_frame_count(0, 30, scene_fps=30, output_fps=24, speed=1.0) == 25
    assert timing.play_frame_count(0, 30, scene_fps=30, output_fps=24, speed=0.5) == 49
    assert timing.play_frame_count(30, 0, scene_fps=30, output_fps=24, speed=1.0) == 25  # backwards
    assert timing.play_frame_count(5, 5, scene_fps=30, output_fps=24, speed=1.0, minimum=12) == 12
    assert timing.play_frame_count(0, 1e-9, scene_fps=30, output_fps=24, speed=1.0) == 1


def test_remap_time_hold_then_run_and_effective_speed():
    t = timing.remap_time(10, 20, 15, hold_frames=4)
    assert t.shape == (15,)
    np.testing.assert_array_equal(t[:5], 10.0)
    assert t[-1] == 20.0 and np.all(np.diff(t) >= 0)
    run = timing.remap_time(0, 30, 25)
    assert timing.effective_speed(0, 30, 25, scene_fps=30, output_fps=24) == pytest.approx(1.0)
    np.testing.assert_allclose(np.diff(run), 30 / 24)
    assert timing.remap_time(7.5, 9.0, 1).tolist() == [9.0]
    assert timing.effective_speed(3, 3, 10, scene_fps=30, output_fps=24) == 0.0


@given(t0=st.floats(0, 500), t1=st.floats(0, 500), speed=st.floats(0.01, 10),
       scene_fps=st.floats(1, 240), out_fps=st.floats(1, 240))
def test_play_time_properties(t0, t1, speed, scene_fps, out_fps):
    ideal_intervals = abs(t1 - t0) / scene_fps / speed * out_fps
    if math.floor(ideal_intervals + 0.5 + timing._FRAME_EPS) + 1 > timing.MAX_SHOT_FRAMES:  # too many: refused
        with pytest.raises(InputError, match="frames"):
            timing.play_frame_count(t0, t1, scene_fps=scene_fps, output_fps=out_fps, speed=speed)
        return
    n = timing.play_frame_count(t0, t1, scene_fps=scene_fps, output_fps=out_fps, speed=speed)
    assert 1 <= n <= timing.MAX_SHOT_FRAMES
    times = timing.remap_time(t0, t1, n)
    assert np.all(np.isfinite(times)) and times[-1] == pytest.approx(t1)
    if n > 1:
        assert times[0] == pytest.approx(t0)
        achieved = timing.effective_speed(t0, t1, n, scene_fps=scene_fps, output_fps=out_fps)
        # rounding to whole frames changes the speed by at most half a frame interval
        assert abs((n - 1) - ideal_intervals) <= 0.5 + 1e-6
        assert math.isfinite(achieved) and achieved > 0


def test_clamp_timestep_edges():
    assert timing.clamp_timestep(-3.5, 48) == 0.0
    assert timing.clamp_timestep(100, 48) == 47.0
    assert timing.clamp_timestep(0.0, 1) == 0.0
    assert timing.clamp_timestep(5.0, 1) == 0.0
