"""2D-features baseline: the exact fast per-pixel relevancy against the literal eq.-2 path."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from fourlegs_engine.errors import InputError
from fourlegs_bench.baseline2d import Features2D, pixel_relevancy, pixel_taps
from fourlegs_engine.demo.synthetic import LABELS
from fourlegs_engine.language.pyramid import crop_layout, pixel_features, pyramid_ratios
from fourlegs_engine.demo.simulated import SimulatedTextEncoder, SimulatedVideoEncoder
from fourlegs_engine.query.lerf import relevancy


def _literal(layout, feats, q, c, stride):
    px = pixel_features(layout, feats, stride)
    h, w, D = px.shape
    return torch.stack([relevancy(px.reshape(-1, D), q[i], c) for i in range(q.shape[0])], 1).reshape(h, w, -1)


@settings(max_examples=12, deadline=None)
@given(st.integers(4, 40), st.integers(6, 30), st.integers(1, 4), st.integers(1, 3), st.integers(0, 10_000),
       st.sampled_from([1.0, 1e-6, 1e3]))
def test_pixel_relevancy_equals_the_literal_path(width, height, stride, steps, seed, magnitude):
    layout = crop_layout(width, height, pyramid_ratios(0.4, 0.9, steps))
    g = torch.Generator().manual_seed(seed)
    D = 16
    q = torch.randn(3, D, generator=g, dtype=torch.float64)
    c = torch.randn(2, D, generator=g, dtype=torch.float64)
    feats = magnitude * (torch.randn(layout.num_crops, D, generator=g, dtype=torch.float64) + q[0])
    fast = pixel_relevancy(layout, feats, q, c, stride, chunk=7)
    torch.testing.assert_close(fast, _literal(layout, feats, q, c, stride), atol=1e-10, rtol=0)


def test_pixel_taps_are_a_partition_of_unity():
    layout = crop_layout(64, 36, pyramid_ratios())
    idx, w = pixel_taps(layout, 1)
    assert idx.shape == (64 * 36, 4 * 5)
    torch.testing.assert_close(w.sum(1), torch.ones(64 * 36, dtype=torch.float64))
    assert (w >= 0).all() and idx.min() >= 0 and idx.max() < layout.num_crops


def test_zero_features_give_the_neutral_relevancy():
    layout = crop_layout(20, 12, pyramid_ratios(0.5, 1.0, 2))
    out = pixel_relevancy(layout, torch.zeros(layout.num_crops, 8), torch.eye(8)[:2], torch.eye(8)[2:4])
    torch.testing.assert_close(out, torch.full_like(out, 0.5))


def test_clean_encoder_maps_light_up_exactly_the_labelled_region():
    """A clean simulated encoder on a frame where a jumping person fills a block: the relevancy of
    "a person jumping" is highest inside the block and < 0.5 far from it."""
    H, W = 54, 96
    frames = torch.zeros(len(LABELS), H, W)
    frames[LABELS.index("floor")] = 1.0
    frames[:, 10:40, 40:60] = 0.0
    frames[LABELS.index("person jumping"), 10:40, 40:60] = 1.0

    class Still:
        def __len__(self):
            return 4

        def __getitem__(self, t):
            return frames

    enc = SimulatedVideoEncoder(LABELS, background_labels=["floor", "wall", "wooden box", "bench"]).clean()
    from fourlegs_engine.scene import Camera
    cam = Camera.look_at((0, -5, 1), (0, 0, 1), width=W, height=H, name="v")
    text = SimulatedTextEncoder()
    base = Features2D(enc, pixel_stride=1)
    from fourlegs_engine.language.encoders import CANONICAL_PHRASES
    maps = base.relevancy_maps(Still(), 2, cam, text.encode_text(["a person jumping", "a ball flying in the air"]),
                               text.encode_text(list(CANONICAL_PHRASES)))
    jump, ball = maps[0].numpy(), maps[1].numpy()
    assert jump[25, 50] > 0.9 and jump[25, 5] < 0.5 and jump[50, 90] < 0.5
    assert ball.max() < 0.5
    preds = base.predict_view(Still(), cam, ["a person jumping"], text)
    box = preds["a person jumping"].box(3)
    assert box[0] <= 40 and box[2] >= 60 and box[1] <= 10 and box[3] >= 40


def test_bad_stride_is_an_input_error():
    with pytest.raises(InputError):
        Features2D(SimulatedVideoEncoder(LABELS), pixel_stride=0)
