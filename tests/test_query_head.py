"""RelevancyHead: relevancy straight from latents equals decode-then-score (float64 reference)."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from fourlegs_engine.language.autoencoder import FeatureDecoder
from fourlegs_engine.query.engine import QueryEngine
from fourlegs_engine.query.head import RelevancyHead
from fourlegs_engine.query.relevancy import l2_normalize, relevancy_reference

from _query_helpers import CANON, two_cluster_scene


def trained_like_decoder(dims=(16, 24, 32, 48), seed=0) -> FeatureDecoder:
    """A decoder in eval mode with non-trivial BatchNorm statistics (as after training)."""
    torch.manual_seed(seed)
    dec = FeatureDecoder(dims).eval()
    for m in dec.net:
        if isinstance(m, torch.nn.BatchNorm1d):
            m.running_mean.normal_()
            m.running_var.uniform_(0.2, 3.0)
            m.weight.data.normal_()
            m.bias.data.normal_()
    return dec


def reference(dec: FeatureDecoder, z: np.ndarray, queries: np.ndarray, refs: np.ndarray) -> np.ndarray:
    """(M,Q) float64 relevancy of the decoded features (decoder run in float64)."""
    d64 = FeatureDecoder(dec.dims).double().eval()
    d64.load_state_dict(dec.state_dict())
    with torch.no_grad():
        feats = d64(torch.from_numpy(z).double()).numpy()
    return np.stack([relevancy_reference(feats, q, refs) for q in queries], 1)


def unit(rng, n, d):
    x = rng.normal(size=(n, d))
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def test_head_equals_float64_decode_then_score():
    dec = trained_like_decoder()
    head = RelevancyHead.from_decoder(dec)
    assert head is not None
    rng = np.random.default_rng(1)
    z = rng.normal(size=(700, 16)) * rng.uniform(0.01, 3.0, size=(700, 1))
    z[:5] = 0.0  # empty pixels: their rendered latent is 0
    queries, refs = unit(rng, 3, 48), unit(rng, 5, 48)
    got = head.relevancy_many(torch.from_numpy(z).float(), torch.from_numpy(queries).float(),
                              torch.from_numpy(refs).float(), scale=10.0).numpy()
    np.testing.assert_allclose(got, reference(dec, z.astype(np.float32).astype(np.float64), queries, refs), atol=2e-6)


def test_query_equal_to_a_reference_scores_at_most_one_half_exactly():
    dec = trained_like_decoder(seed=3)
    head = RelevancyHead.from_decoder(dec)
    rng = np.random.default_rng(4)
    refs = torch.from_numpy(unit(rng, 4, 48)).float()
    z = torch.randn(200, 16)
    r = head.relevancy_many(z, refs[2:3], refs, scale=10.0)[:, 0]
    assert torch.all(r <= 0.5) and torch.any(r == 0.5)


@settings(max_examples=40, deadline=None)
@given(st.one_of(st.floats(min_value=-40, max_value=40), st.sampled_from([36.0, 37.5, 38.0])),
       st.sampled_from(["none", "nan", "inf", "-inf"]))
def test_extreme_latents_stay_finite(log_scale, poison):
    dec = trained_like_decoder(seed=5)
    head = RelevancyHead.from_decoder(dec)
    z = torch.randn(64, 16, generator=torch.Generator().manual_seed(0)) * float(10.0 ** log_scale)
    if poison != "none":
        z[::3, 1] = float(poison)
    refs = l2_normalize(torch.randn(4, 48, generator=torch.Generator().manual_seed(1)))
    q = l2_normalize(torch.randn(1, 48, generator=torch.Generator().manual_seed(2)))
    r = head.relevancy_many(z, q, refs, scale=10.0)
    assert torch.isfinite(r).all() and (r >= 0).all() and (r <= 1).all()
    if poison == "none" and abs(log_scale) <= 6:
        np.testing.assert_allclose(r.numpy(), reference(dec, z.double().numpy(), q.double().numpy(),
                                                        refs.double().numpy()), atol=2e-5)


def test_only_qualifying_decoders_get_a_head():
    assert RelevancyHead.from_decoder(FeatureDecoder((16, 24, 32, 48)).train()) is None  # batch statistics
    assert RelevancyHead.from_decoder(FeatureDecoder((16, 24, 32, 48)).eval().to(torch.bfloat16)) is None
    assert RelevancyHead.from_decoder(FeatureDecoder((16, 64, 8)).eval()) is None  # nothing to save
    assert RelevancyHead.from_decoder(object()) is None
    assert RelevancyHead.from_decoder(FeatureDecoder((16, 24, 32, 48)).eval()) is not None


class DecoderField:
    """A field with a real FeatureDecoder; ``use_head=False`` hides the decoder from the engine."""

    canonical_phrases = CANON

    def __init__(self, latents, decoder, use_head=True):
        self.latents = latents
        self._decoder = decoder
        if use_head:
            self.decoder = decoder

    @torch.no_grad()
    def decode(self, z):
        return self._decoder(torch.nan_to_num(torch.as_tensor(z, dtype=torch.float32)))


@pytest.mark.parametrize("spatial", ["exact", "fast"])
def test_engine_with_and_without_head_agree(spatial):
    scene, field, enc, _ = two_cluster_scene()
    T, N, d = field.latents.shape
    dec = trained_like_decoder(dims=(d, 12, 10, 16), seed=7)  # D=16: the helper encoder's dimension
    lat = np.asarray(field.latents, dtype=np.float32)
    with_head = QueryEngine(scene, DecoderField(lat, dec), enc, spatial=spatial)
    plain = QueryEngine(scene, DecoderField(lat, dec, use_head=False), enc, spatial=spatial)
    assert with_head.head is not None and plain.head is None
    q = "a ball flying"
    a, b = with_head.temporal(q), plain.temporal(q)
    np.testing.assert_allclose(with_head.gaussian_relevancy(q, 1).numpy(), plain.gaussian_relevancy(q, 1).numpy(),
                               atol=1e-5)
    assert a.segment == b.segment
    cam = scene.cameras.cameras(1, "all")[0]
    np.testing.assert_allclose(with_head.relevancy_map(q, cam, 1)["relevancy"],
                               plain.relevancy_map(q, cam, 1)["relevancy"], atol=1e-5)
