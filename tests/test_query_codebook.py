"""Codebook: k-means, two-level assignment, histograms, storage, and lookup-based temporal queries."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from fourlegs_engine.query import codebook as cb
from fourlegs_engine.query.temporal import counts_from_code_histogram, counts_from_relevancy


def test_nearest_matches_brute_force():
    g = torch.Generator().manual_seed(0)
    x, c = torch.randn(500, 6, generator=g), torch.randn(37, 6, generator=g)
    brute = torch.cdist(x.double(), c.double()).argmin(1)
    assert torch.equal(cb.nearest(x, c, chunk=64), brute)


def test_kmeans_recovers_separated_clusters():
    rng = np.random.default_rng(0)
    centres = rng.normal(size=(5, 4)) * 10
    x = np.concatenate([c + 0.01 * rng.normal(size=(40, 4)) for c in centres])
    cent = cb.kmeans(torch.tensor(x, dtype=torch.float32), 5, iters=20, seed=1).numpy()
    sse = ((x[:, None] - cent[None]) ** 2).sum(-1).min(1).mean()
    assert sse < ((x - x.mean(0)) ** 2).sum(-1).mean() * 0.5


def test_few_points_become_exact_codes():
    x = torch.tensor([[0.0, 1.0], [1.0, 0.0]])
    cent = cb.kmeans(x, 4)
    assert cent.shape == (4, 2) and torch.equal(cb.nearest(x, cent), torch.tensor([0, 1]))


def test_two_level_assignment_picks_nearest_inside_its_cell():
    g = torch.Generator().manual_seed(2)
    x = torch.randn(2000, 8, generator=g)
    coarse, fine = cb.train(x, 64, num_points=10**12, seed=0, iters=5)  # forced two-level: 8 x 8
    assert coarse.shape == (8, 8) and fine.shape == (64, 8)
    codes = cb.assign(x, coarse, fine)
    cell = cb.nearest(x, coarse)
    assert torch.equal(codes // 8, cell)
    for c in range(8):
        sel = cell == c
        brute = cb.nearest(x[sel], fine[c * 8:(c + 1) * 8]) + c * 8
        assert torch.equal(codes[sel], brute)


def test_build_store_load_and_histogram(tmp_path):
    rng = np.random.default_rng(0)
    protos = rng.normal(size=(6, 16)).astype(np.float32)
    idx = rng.integers(0, 6, size=(5, 300))
    lat = np.lib.format.open_memmap(tmp_path / "latents.npy", mode="w+", dtype=np.float32, shape=(5, 300, 16))
    lat[:] = protos[idx]
    lat.flush()
    lat = np.load(tmp_path / "latents.npy", mmap_mode="r")
    book = cb.build_codebook(lat, 8, out_dir=tmp_path, seed=0)
    assert book.codes.dtype == np.uint16 and book.codes.shape == (5, 300)
    np.testing.assert_array_equal(book.histogram, np.stack([np.bincount(c, minlength=8) for c in book.codes]))
    # every distinct latent is reproduced exactly by its code
    assert book.quantization_error(lat) < 1e-10
    again = cb.load_codebook(tmp_path, 8, lat)
    assert again is not None and np.array_equal(np.asarray(again.codes), np.asarray(book.codes))
    # changed latents -> stale codebook is not reused
    lat2 = np.lib.format.open_memmap(tmp_path / "latents.npy", mode="r+")
    lat2[0, 0] += 1.0
    lat2.flush()
    del lat2
    assert cb.load_codebook(tmp_path, 8, np.load(tmp_path / "latents.npy", mmap_mode="r")) is None


def test_lookup_temporal_counts_equal_exact_counts_when_codes_are_exact():
    rng = np.random.default_rng(4)
    protos = rng.normal(size=(10, 8)).astype(np.float32)
    idx = rng.integers(0, 10, size=(6, 200))
    lat = protos[idx]
    book = cb.build_codebook(lat, 10, seed=0)
    q = rng.normal(size=8)
    score = lambda v: 1 / (1 + np.exp(-(v @ q)))  # any per-latent score
    exact = counts_from_relevancy(score(lat.reshape(-1, 8)).reshape(6, 200))
    coded = counts_from_code_histogram(score(book.centroids.astype(np.float64)), book.histogram)
    np.testing.assert_array_equal(exact[0], coded[0])
    assert exact[2] == coded[2]


# ----------------------------------------------------------------------------- exact re-scoring near thresholds
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from fourlegs_engine.query.temporal import counts_from_codes_refined  # noqa: E402


def _coded_problem(seed: int, S: int = 6, N: int = 300, K: int = 12):
    """Codes (S,N), code scores (K,), exact per-Gaussian scores near their code's score, histogram."""
    rng = np.random.default_rng(seed)
    codes = rng.integers(0, K, size=(S, N))
    code_scores = rng.uniform(0.3, 0.8, size=K)
    exact = np.clip(code_scores[codes] + rng.normal(scale=0.03, size=(S, N)), 0, 1)
    hist = np.stack([np.bincount(codes[t], minlength=K) for t in range(S)]).astype(np.int32)
    return codes, code_scores, exact, hist


def _rescorer(codes, exact, calls):
    def rescore(which):
        calls.append(np.asarray(which))
        mask = np.isin(codes, which)
        rows, _ = np.nonzero(mask)
        return rows, exact[mask]
    return rescore


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000))
def test_refined_counts_with_full_margin_equal_exact_counts(seed):
    codes, code_scores, exact, hist = _coded_problem(seed)
    got = counts_from_codes_refined(code_scores, hist, _rescorer(codes, exact, []), 1.0)
    want = counts_from_relevancy(torch.from_numpy(exact))
    np.testing.assert_array_equal(got[0], want[0])
    assert got[1] == pytest.approx(want[1], abs=1e-12) and got[2] == want[2] and got[3] == codes.size


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000))
def test_refined_counts_with_zero_margin_equal_lookup(seed):
    codes, code_scores, _, hist = _coded_problem(seed)
    calls = []
    got = counts_from_codes_refined(code_scores, hist, _rescorer(codes, None, calls), 0.0)
    want = counts_from_code_histogram(code_scores, hist)
    np.testing.assert_array_equal(got[0], want[0])
    assert got[1] == pytest.approx(want[1]) and got[2] == want[2] and got[3] == 0 and not calls


def test_refined_counts_rescore_only_codes_near_the_thresholds():
    codes, code_scores, exact, hist = _coded_problem(7, K=40)
    calls = []
    counts, r_avg, n_rel, rescored = counts_from_codes_refined(code_scores, hist, _rescorer(codes, exact, calls),
                                                               0.02)
    done = np.concatenate(calls)
    assert len(np.unique(done)) == len(done)  # no code is re-scored twice
    near = (np.abs(code_scores - 0.5) < 0.02) | (np.abs(code_scores - r_avg) < 0.02)
    assert set(np.nonzero(near)[0]) <= set(done.tolist())  # every code near a final threshold is exact
    assert 0 < rescored == np.isin(codes, done).sum() < codes.size
    # the result is the exact counting of a hybrid score array: exact where re-scored, code score elsewhere
    hybrid = np.where(np.isin(codes, done), exact, code_scores[codes])
    np.testing.assert_array_equal(counts, counts_from_relevancy(torch.from_numpy(hybrid))[0])


def test_members_index_lists_each_codes_gaussians(tmp_path):
    rng = np.random.default_rng(3)
    lat = rng.normal(size=(5, 90, 4)).astype(np.float32)
    book = cb.build_codebook(lat, 16, out_dir=tmp_path)
    codes = np.asarray(book.codes, dtype=np.int64)
    for k in (0, 5, 15):
        np.testing.assert_array_equal(book.members_of(np.array([k])), np.flatnonzero(codes.reshape(-1) == k))
    np.testing.assert_array_equal(book.members_of(np.array([2, 9])),
                                  np.flatnonzero(np.isin(codes.reshape(-1), [2, 9])))
    assert (tmp_path / "members_16.npy").is_file()
    (tmp_path / "members_16.npy").unlink()  # a codebook stored before the index existed
    legacy = cb.load_codebook(tmp_path, 16, lat)
    assert legacy.members is None
    np.testing.assert_array_equal(legacy.members_of(np.array([5])), np.flatnonzero(codes.reshape(-1) == 5))
