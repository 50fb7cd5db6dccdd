"""The planner on the real query engine (``fourlegs_engine.query.engine.QueryEngine``).

The language field is built by hand so the answer is known: 16-d latents, an identity decoder and a
word-basis text encoder. The ball's Gaussians carry the "ball" direction only while it flies
(timesteps 14..30); everything else carries "floor". The engine's own ``stats`` counters prove that the
planner asks for nothing the plan's effects do not need.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from _highlights_helpers import tiny_scene
from fourlegs_engine.highlights.planner import plan_highlight
from fourlegs_engine.highlights.presets import load_preset
from fourlegs_engine.query.engine import QueryEngine, QueryOptions
from fourlegs_engine.scene import Camera

D = 16
WORDS = {"ball": 0, "floor": 1, "object": 2, "things": 3, "stuff": 4, "texture": 5, "unicorn": 6}
SEGMENT = (14, 30)


class WordEncoder:
    """Text -> normalized sum of one basis vector per known word."""

    name, dim, input_kind = "words", D, "labels"

    def encode_text(self, texts):
        out = torch.zeros(len(texts), D)
        for i, text in enumerate(texts):
            for w in text.lower().split():
                if w in WORDS:
                    out[i, WORDS[w]] += 1.0
        return out / out.norm(dim=1, keepdim=True).clamp_min(1e-12)


class HandField:
    """A language field: (T,N,D) latents decoded by the identity."""

    canonical_phrases = ("object", "things", "stuff", "texture")

    def __init__(self, latents):
        self.latents = latents

    def decode(self, x):
        return x / x.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def small_ring(n=4, w=64, h=36):
    cams = []
    for i in range(n):
        a = 2 * math.pi * i / n + 0.3
        cams.append(Camera.look_at((4 * math.cos(a), 4 * math.sin(a), 1.6), (0, 0, 0.8), width=w, height=h,
                                   focal=55.0, name=f"cam{i:02d}"))
    return cams


@pytest.fixture(scope="module")
def engine():
    scene = tiny_scene(cameras=small_ring())
    T, N = scene.num_timesteps, scene.num_gaussians
    lat = np.zeros((T, N, D), np.float32)
    lat[:, :, WORDS["floor"]] = 1.0
    ball = np.arange(60, N)
    for t in range(*SEGMENT):
        lat[t, ball] = 0.0
        lat[t, ball, WORDS["ball"]] = 1.0
    lat[SEGMENT[1], ball] = 0.0
    lat[SEGMENT[1], ball, WORDS["ball"]] = 1.0
    return QueryEngine(scene, HandField(lat), WordEncoder(), QueryOptions.exact(spatial="fast"))


def test_real_engine_broadcast_plan(engine):
    engine.stats.clear()
    plan = plan_highlight(engine.scene, engine, "ball", load_preset("broadcast"))
    loc = plan.localization
    assert loc["found"] is True
    a, b = loc["segment"]
    assert abs(a - SEGMENT[0]) <= 1 and abs(b - SEGMENT[1]) <= 1  # dilation may widen by one step
    assert plan.effects == ["play", "zoom_in", "bullet_time", "desaturate_background"]
    # the action centre is near the ball at the peak
    ball = engine.scene.gaussians.means[loc["peak"], 60:].mean(axis=0)
    assert np.linalg.norm(np.array(loc["action_centre"]) - ball) < 0.35
    n_cams = len(engine.scene.cameras.cameras(0, "all"))
    assert engine.stats["localize"] == 1 and engine.stats["temporal"] == 1
    assert engine.stats["best_view"] == 1 and engine.stats["action_centre"] == 1
    assert engine.stats["relevancy_map"] == n_cams + 1  # view search + centre; none per frame


def test_real_engine_zoom_only_requests_no_per_frame_maps(engine):
    engine.stats.clear()
    plan = plan_highlight(engine.scene, engine, "ball", load_preset("broadcast").with_shots(["zoom_in"]))
    assert set(plan.passes) == {"rgb"}
    assert engine.stats["relevancy_map"] == len(engine.scene.cameras.cameras(0, "all")) + 1
    assert plan.frame_end - plan.frame_start + 1 > engine.stats["relevancy_map"]


def test_real_engine_desaturate_only_skips_the_action_centre(engine):
    engine.stats.clear()
    plan = plan_highlight(engine.scene, engine, "ball", load_preset("subtle_desaturate"))
    assert engine.stats["action_centre"] == 0 and engine.stats["best_view"] == 1
    assert "relevancy" in plan.passes and plan.localization["action_centre"] is None


def test_real_engine_query_not_found(engine):
    engine.stats.clear()
    plan = plan_highlight(engine.scene, engine, "unicorn", load_preset("broadcast"))
    assert plan.localization["found"] is False
    assert plan.effects == ["play"] and set(plan.passes) == {"rgb"}
    assert engine.stats["best_view"] == 0 and engine.stats["relevancy_map"] == 0
    assert any("'unicorn' was not found" in m for m in plan.messages)
