"""kNN, neighbourhood attention, the smoothing ablations and the autoencoder."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from fourlegs_engine.errors import InputError
from fourlegs_engine.language import attention_kernels
from fourlegs_engine.language.attention import (NeighbourhoodAttention, _attend, brute_force_knn, knn_indices,
                                                neighbour_blur, smoothness_loss)
from fourlegs_engine.language.autoencoder import FeatureAutoencoder, l2_normalize, reconstruction_loss


@pytest.fixture(autouse=True)
def one_thread():
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


def test_knn_matches_brute_force():
    pts = np.random.default_rng(0).normal(size=(500, 3))
    got = knn_indices(pts, 20).numpy()
    ref = brute_force_knn(pts, 20)
    assert got.shape == (500, 20)
    np.testing.assert_array_equal(got[:, 0], np.arange(500))
    # same neighbour sets (distances are distinct with probability 1)
    np.testing.assert_array_equal(np.sort(got, axis=1), np.sort(ref, axis=1))


@given(st.integers(1, 30), st.integers(1, 25), st.integers(0, 3))
def test_knn_handles_duplicates_and_small_sets(n, k, copies):
    rng = np.random.default_rng(n * 31 + k)
    pts = rng.normal(size=(n, 3))
    if copies:
        pts = np.concatenate([pts] + [pts[:1]] * copies)  # coincident points
    idx = knn_indices(pts, k).numpy()
    m = len(pts)
    assert idx.shape == (m, min(k, m))
    np.testing.assert_array_equal(idx[:, 0], np.arange(m))   # always itself first
    for row in idx:
        assert len(set(row.tolist())) == len(row)           # no repeats
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    for i in range(m):                                       # the others are the nearest others
        others = np.delete(d[i], i)
        kth = np.sort(others)[idx.shape[1] - 2] if idx.shape[1] > 1 else -1
        assert np.all(d[i, idx[i, 1:]] <= kth + 1e-12)


def test_knn_rejects_bad_input():
    with pytest.raises(InputError):
        knn_indices(np.zeros((4, 2)), 3)
    with pytest.raises(InputError):
        knn_indices(np.array([[0, 0, np.nan]]), 1)
    assert knn_indices(np.zeros((0, 3)), 20).shape == (0, 0)


def _reference_attention(att: NeighbourhoodAttention, x: torch.Tensor, nbr: torch.Tensor) -> torch.Tensor:
    """float64 loop over Gaussians."""
    x = x.double()
    W = {k: (getattr(att, k).weight.double(), getattr(att, k).bias.double()) for k in ("q", "k", "v", "out")}
    out = []
    for i in range(x.shape[0]):
        q = W["q"][0] @ x[i] + W["q"][1]
        keys = x[nbr[i]] @ W["k"][0].T + W["k"][1]
        vals = x[nbr[i]] @ W["v"][0].T + W["v"][1]
        a = torch.softmax(keys @ q / math.sqrt(x.shape[1]), 0)
        out.append(W["out"][0] @ (a @ vals) + W["out"][1])
    return torch.stack(out)


def test_attention_shapes_and_reference_values():
    torch.manual_seed(0)
    att = NeighbourhoodAttention(16, chunk=7)
    x = torch.randn(30, 16)
    nbr = knn_indices(torch.randn(30, 3), 5)
    y = att(x, nbr)
    assert y.shape == (30, 16)
    torch.testing.assert_close(y.double(), _reference_attention(att, x, nbr), atol=1e-5, rtol=1e-5)
    # chunked (with checkpointing) and unchunked give the same values and gradients
    big = NeighbourhoodAttention(16, chunk=1000)
    big.load_state_dict(att.state_dict())
    x1 = x.clone().requires_grad_(True)
    x2 = x.clone().requires_grad_(True)
    att(x1, nbr).square().sum().backward()
    big(x2, nbr).square().sum().backward()
    torch.testing.assert_close(x1.grad, x2.grad, atol=1e-5, rtol=1e-5)


def test_attention_only_mixes_neighbours():
    torch.manual_seed(1)
    att = NeighbourhoodAttention(8)
    x = torch.randn(12, 8)
    nbr = knn_indices(torch.randn(12, 3), 4)
    y = att(x, nbr)
    outsider = next(j for j in range(12) if j not in nbr[0].tolist())
    x2 = x.clone()
    x2[outsider] += 10.0
    y2 = att(x2, nbr)
    torch.testing.assert_close(y2[0], y[0])
    insider = int(nbr[0, 1])
    x3 = x.clone()
    x3[insider] += 10.0
    assert not torch.allclose(att(x3, nbr)[0], y[0])


def test_attention_is_stable_for_huge_inputs_and_identity_init_averages():
    att = NeighbourhoodAttention(4).init_near_identity()
    with torch.no_grad():
        att.q.weight.zero_()
        att.k.weight.zero_()
    x = torch.randn(10, 4)
    nbr = knn_indices(torch.randn(10, 3), 3)
    torch.testing.assert_close(att(x, nbr), x[nbr].mean(1), atol=1e-6, rtol=1e-6)
    att2 = NeighbourhoodAttention(4)
    assert torch.isfinite(att2(torch.full((10, 4), 1e18), nbr)).all()


def test_blur_and_smoothness_loss():
    x = torch.tensor([[0.0, 0.0], [3.0, 4.0], [6.0, 8.0]], dtype=torch.float64, requires_grad=True)
    nbr = torch.tensor([[0, 1], [1, 0], [2, 1]])
    torch.testing.assert_close(neighbour_blur(x, nbr), torch.tensor([[1.5, 2.0], [1.5, 2.0], [4.5, 6.0]],
                                                                    dtype=torch.float64))
    loss = smoothness_loss(x, nbr)
    assert float(loss.detach()) == pytest.approx((5 + 5 + 5) / 3, rel=1e-9)
    loss.backward()
    assert torch.isfinite(x.grad).all()
    # coincident latents: finite gradient (eps-guarded norm)
    z = torch.zeros(3, 2, requires_grad=True)
    smoothness_loss(z, nbr).backward()
    assert torch.isfinite(z.grad).all()


def test_autoencoder_architecture_and_normalization():
    ae = FeatureAutoencoder()
    assert ae.encoder.dims == (768, 512, 256, 128) and ae.decoder.dims == (128, 256, 512, 768)
    kinds = [type(m).__name__ for m in ae.encoder.net]
    assert kinds == ["Linear", "BatchNorm1d", "ReLU", "Linear", "BatchNorm1d", "ReLU", "Linear"]
    z, r = ae(torch.randn(8, 768))
    torch.testing.assert_close(z.norm(dim=1), torch.ones(8))
    torch.testing.assert_close(r.norm(dim=1), torch.ones(8))
    assert torch.isfinite(l2_normalize(torch.zeros(2, 3))).all()


def test_first_layer_split_is_exact():
    """Applying the first Linear before a convex combination equals encoding the combination."""
    torch.manual_seed(0)
    enc = FeatureAutoencoder().encoder.eval()
    crops = torch.randn(5, 768, dtype=torch.float64)
    enc = enc.double()
    w = torch.softmax(torch.randn(7, 5, dtype=torch.float64), 1)  # convex weights
    direct = enc(w @ crops)
    split = enc.after_first_layer(w @ enc.first_layer()(crops))
    torch.testing.assert_close(direct, split)


def test_autoencoder_overfits_a_small_set():
    torch.manual_seed(0)
    basis = l2_normalize(torch.randn(6, 768))
    mix = torch.softmax(3 * torch.randn(64, 6), 1)
    x = l2_normalize(mix @ basis)
    ae = FeatureAutoencoder()
    opt = torch.optim.Adam(ae.parameters(), lr=7e-4)
    for _ in range(150):
        _, r = ae(x)
        loss = reconstruction_loss(r, x)
        opt.zero_grad()
        loss.backward()
        opt.step()
    ae.eval()
    _, r = ae(x)
    cos = torch.nn.functional.cosine_similarity(r, x, dim=1)
    assert float(cos.mean().detach()) > 0.97
    assert float(loss.detach()) < 0.01


@pytest.mark.skipif(not attention_kernels.available(), reason="numba is not installed")
@pytest.mark.parametrize("n,k", [(1, 1), (37, 5), (200, 20)])
def test_fused_attention_kernels_match_the_gathered_form_and_gradcheck(n, k):
    """The numba forward/backward against the gathered torch form (float64), and torch's gradcheck."""
    g = torch.Generator().manual_seed(n)
    q = torch.randn(n, 8, generator=g, dtype=torch.float64) * 3.0      # peaked softmax rows too
    lat = torch.randn(n, 8, generator=g, dtype=torch.float64)
    nbr = knn_indices(torch.randn(n, 3, generator=g), k)
    q1, l1 = q.clone().requires_grad_(True), lat.clone().requires_grad_(True)
    q2, l2 = q.clone().requires_grad_(True), lat.clone().requires_grad_(True)
    fused = attention_kernels.NeighbourAttend.apply(q1, l1, nbr)
    gathered = _attend(q2, l2, nbr)
    torch.testing.assert_close(fused, gathered, rtol=1e-12, atol=1e-12)
    weights = torch.randn(n, 8, generator=g, dtype=torch.float64)
    (fused * weights).sum().backward()
    (gathered * weights).sum().backward()
    torch.testing.assert_close(q1.grad, q2.grad, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(l1.grad, l2.grad, rtol=1e-10, atol=1e-10)
    if n <= 40:
        assert torch.autograd.gradcheck(lambda a, b: attention_kernels.NeighbourAttend.apply(a, b, nbr),
                                        (q.clone().requires_grad_(True), lat.clone().requires_grad_(True)))


@pytest.mark.skipif(not attention_kernels.available(), reason="numba is not installed")
def test_fused_attention_is_stable_for_huge_logits():
    nbr = knn_indices(torch.randn(6, 3, generator=torch.Generator().manual_seed(0)), 3)
    lat = torch.full((6, 4), 1e18)
    out = attention_kernels.NeighbourAttend.apply(torch.full((6, 4), 1e18), lat, nbr)
    assert torch.isfinite(out).all()
    torch.testing.assert_close(out, lat)
