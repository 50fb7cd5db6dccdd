"""The sketch path (QueryOptions(path="sketch")): the per-pair sketch's margins bound the exact path's, the
temporal counts it decides equal exact counting, R_avg is exact when its sample covers Rel and within its
interval otherwise, the sketch is stored beside the field, reused, rebuilt when the head changes, and a
cancelled build leaves nothing."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import example, given, settings
from hypothesis import strategies as st

from fourlegs_engine.errors import InputError
from fourlegs_engine.query import sketch as sketch_module
from fourlegs_engine.query.engine import QueryEngine, QueryOptions
from fourlegs_engine.query.head import RelevancyHead
from fourlegs_engine.query.lerf import l2_normalize
from fourlegs_engine.query.sketch import build_sketch, ensure_sketch, head_key, load_sketch
from fourlegs_engine.query.sketch_path import _Correction, _counts, _Pairs
from fourlegs_engine.query.temporal import counts_from_relevancy

from _query_helpers import CANON, TableTextEncoder, two_cluster_scene
from test_query_head import DecoderField, decaying_decoder, trained_like_decoder

Q = "a ball flying"


def _latents(T=5, N=70, d=16, seed=0, poison=False) -> np.ndarray:
    rng = np.random.default_rng(seed)
    lat = (rng.normal(size=(T, N, d)) * rng.uniform(0.05, 2.0, size=(T, N, 1))).astype(np.float32)
    if poison:
        lat[1, ::7, 2] = np.nan
        lat[2, 3, 0] = np.inf
        lat[3, 5] = 3e37  # u overflows float32 on the exact path
    return lat


def _exact_margins(head: RelevancyHead, lat: np.ndarray, q: torch.Tensor, refs: torch.Tensor, scale: float):
    """(T,N) the exact path's float32 margin min_k scale·(q − c_k)·φ(z)."""
    T, N, d = lat.shape
    diffs = q[None].double() - refs.double()
    return head.margins(torch.from_numpy(lat.reshape(-1, d)), diffs, scale).min(dim=1).values.reshape(T, N).numpy()


@settings(max_examples=30, deadline=None)
@given(st.integers(min_value=0, max_value=10_000), st.sampled_from([1, 3, 8, 64]), st.booleans(),
       st.sampled_from([1.0, 10.0]))
def test_every_exact_margin_lies_within_the_sketch_radius(seed, rank, poison, scale):
    """Any seed, rank (1 up to beyond the head's width H = 48), extreme and non-finite latents."""
    dec = (decaying_decoder if seed % 2 else trained_like_decoder)((16, 24, 48, 96), seed=seed % 7)
    head = RelevancyHead.from_decoder(dec)
    lat = _latents(seed=seed, poison=poison)
    refs = l2_normalize(torch.randn(4, 96, generator=torch.Generator().manual_seed(seed)))
    sk = build_sketch(head, refs, lat, rank=rank)
    assert sk.rank == min(rank, 48) and np.allclose(sk.basis.T @ sk.basis, np.eye(sk.rank), atol=1e-9)
    for j in range(3):
        q = l2_normalize(torch.randn(96, generator=torch.Generator().manual_seed(seed + 100 + j)))
        m, rad = sk.margins(head, q, scale, np.arange(lat.shape[0]))
        exact = _exact_margins(head, lat, q, refs, scale)
        assert np.all(np.abs(exact - m) <= rad), np.max(np.abs(exact - m) - rad)
        assert np.isfinite(m).all() and (rad > 0).all()
        if poison:  # the exact path's zero-feature rows are left to exact scoring
            assert np.isinf(rad[3, 5])


def test_a_query_inside_the_basis_gets_tight_radii_and_a_full_rank_basis_is_exact_to_rounding():
    dec = decaying_decoder((16, 24, 48, 96), seed=2)
    head = RelevancyHead.from_decoder(dec)
    lat = _latents(seed=3)
    refs = l2_normalize(torch.randn(4, 96, generator=torch.Generator().manual_seed(0)))
    q = l2_normalize(torch.randn(96, generator=torch.Generator().manual_seed(1)))
    full = build_sketch(head, refs, lat, rank=48)  # V spans every u: only float32 rounding is left
    m, rad = full.margins(head, q, 10.0, np.arange(5))
    exact = _exact_margins(head, lat, q, refs, 10.0)
    assert np.max(np.abs(exact - m)) < 1e-3 and np.median(rad) < 1e-3
    low = build_sketch(head, refs, lat, rank=4)
    assert np.median(low.margins(head, q, 10.0, np.arange(5))[1]) > 10 * np.median(rad)


# ------------------------------------------------------------------------ the counts
def _fake_pairs(seed: int, S: int = 6, N: int = 400, noise: float = 0.05):
    """Exact relevancies with several timesteps near the mean count, sketched margins off by at most their
    radius, and a scorer that returns the exact values."""
    rng = np.random.default_rng(seed)
    level = rng.uniform(-1.0, 1.5, size=(S, 1))
    exact_margin = level + rng.normal(scale=1.2, size=(S, N))
    exact = 1.0 / (1.0 + np.exp(-exact_margin))
    exact = exact.astype(np.float32).astype(np.float64)          # the exact path's float32 scores
    radius = rng.uniform(0.2, 1.0, size=(S, N)) * noise
    margin = exact_margin + rng.uniform(-1, 1, size=(S, N)) * radius
    calls = []

    def score(idx):
        calls.append(idx.size)
        return exact.reshape(-1)[idx]

    return _Pairs(margin.astype(np.float32), (radius * 1.0001).astype(np.float32), score), exact, calls


@settings(max_examples=40, deadline=None)
@given(st.integers(min_value=0, max_value=10_000), st.sampled_from([0.01, 0.05, 0.3]))
def test_counts_equal_exact_counting_when_the_sample_covers_rel(seed, noise):
    pairs, exact, _ = _fake_pairs(seed, noise=noise)
    S = exact.shape[0]
    counts, r_avg, n_rel, undecided = _counts(pairs, np.ones(S, dtype=np.int64), 10 ** 9,
                                              np.random.default_rng(0))
    want, want_r, want_n = counts_from_relevancy(exact.astype(np.float32))
    np.testing.assert_array_equal(counts, want)
    assert n_rel == want_n and r_avg == pytest.approx(want_r, abs=1e-12) and not undecided.any()


@settings(max_examples=40, deadline=None)
@given(st.integers(min_value=0, max_value=10_000))
@example(1583)                       # the larger sample's interval lies outside the first one's
def test_a_small_sample_leaves_undecided_every_timestep_it_may_misjudge(seed):
    """With R_avg from 8 draws its interval is wide: every timestep whose decision (count·T > total)
    differs from exact counting is among the undecided ones, and the count of Rel stays exact."""
    pairs, exact, _ = _fake_pairs(seed, S=10)
    S = exact.shape[0]
    counts, _, n_rel, undecided = _counts(pairs, np.ones(S, dtype=np.int64), 8, np.random.default_rng(seed))
    want, _, want_n = counts_from_relevancy(exact.astype(np.float32))
    assert n_rel == want_n
    wrong = (counts * S > counts.sum()) != (want * S > want.sum())
    assert not np.any(wrong & ~undecided)


def test_only_the_pairs_the_sketch_cannot_decide_are_scored():
    pairs, exact, calls = _fake_pairs(1, noise=0.01)
    _counts(pairs, np.ones(exact.shape[0], dtype=np.int64), 64, np.random.default_rng(0))
    assert 0 < pairs.rescored < 0.1 * exact.size and pairs.sampled <= 64 * 16


def test_importance_sampled_correction_is_unbiased_and_exact_when_it_covers_every_pair():
    rng = np.random.default_rng(0)
    n = 5000
    sketch = rng.uniform(0.6, 0.99, size=n)
    bound = rng.uniform(1e-5, 1e-3, size=n)
    exact = sketch + rng.uniform(-1, 1, size=n) * bound
    pairs = _Pairs(np.zeros((1, n), np.float32), np.zeros((1, n), np.float32), lambda idx: exact[idx])
    idx = np.arange(n)
    truth = float((exact - sketch).sum())
    estimates, errors = [], []
    for seed in range(200):
        est = _Correction(pairs, idx, sketch, bound / bound.sum(), np.random.default_rng(seed))
        value, se = est.grow_to(256)
        estimates.append(value)
        errors.append(se)
    estimates = np.array(estimates)
    assert abs(estimates.mean() - truth) < 4 * estimates.std() / np.sqrt(200)
    assert np.mean(errors) == pytest.approx(estimates.std(), rel=0.25)  # the reported error is the spread
    whole = _Correction(pairs, idx, sketch, bound / bound.sum(), np.random.default_rng(0))
    assert whole.grow_to(n) == (pytest.approx(truth, abs=1e-9), 0.0) and whole.exact


# ------------------------------------------------------------------------ the engine
def _soft_scene():
    """Two clusters with noisy latents and a decoder whose last layer concentrates (as trained ones do):
    relevancies spread over (0, 1), texts embedded where the clusters decode."""
    scene, field, _, _ = two_cluster_scene(T=8, active=(2, 3, 4), D=128)
    T, N, d = field.latents.shape
    dec = decaying_decoder((d, 24, 48, 128), seed=7)
    rng = np.random.default_rng(0)
    lat = (np.asarray(field.latents) + rng.normal(scale=0.3, size=(T, N, d))).astype(np.float32)
    with torch.no_grad():
        at = {name: dec(torch.from_numpy(lat[t, rows].mean(0, keepdims=True))).numpy()[0]
              for name, t, rows in ((Q, 2, slice(0, N // 2)), ("object", 0, slice(N // 2, N)))}
    table = dict(at, **{c: rng.normal(size=128) for c in CANON[1:]})
    return scene, lat, dec, TableTextEncoder(table, 128)


@pytest.mark.parametrize("samples", [10 ** 9, 16])
def test_sketch_path_answers_as_the_exact_path(tmp_path, samples):
    scene, lat, dec, enc = _soft_scene()
    exact = QueryEngine(scene, DecoderField(lat, dec), enc, QueryOptions.exact())
    sketched = QueryEngine(scene, DecoderField(lat, dec), enc,
                           QueryOptions(path="sketch", sketch_rank=6, codebook_samples=samples), codebook_dir=tmp_path)
    for q in (Q, "object", "things", "something else"):
        want, got = exact.temporal(q), sketched.temporal(q)
        assert (got.segments, got.peak) == (want.segments, want.peak), q
        np.testing.assert_array_equal(got.positive, want.positive)
        assert got.num_relevant == want.num_relevant
        if samples > lat.size:  # R_avg from every relevant pair's exact score
            assert got.r_avg == pytest.approx(want.r_avg, abs=1e-6)
    assert sketched.stats["codebook_load"] == 0 and sketched.stats["sketch_load"] == 1
    # stride: every second timestep, weighted as the exact path does
    assert sketched.temporal(Q, stride=2).segments == exact.temporal(Q, stride=2).segments


def test_without_a_head_the_sketch_path_answers_from_the_codebook(tmp_path):
    scene, field, enc, _ = two_cluster_scene(T=4, active=(1, 2))
    eng = QueryEngine(scene, field, enc, QueryOptions(path="sketch"), codebook_dir=tmp_path)
    assert not eng.sketch_path.available
    want = QueryEngine(scene, field, enc, QueryOptions.exact()).temporal(Q)
    assert eng.temporal(Q).segments == want.segments and eng.stats["codebook_load"] == 1


def test_sketch_is_stored_reused_and_rebuilt_when_the_head_changes(tmp_path):
    scene, lat, dec, enc = _soft_scene()
    np.save(tmp_path / "latents.npy", lat)
    mm = np.load(tmp_path / "latents.npy", mmap_mode="r")
    head = RelevancyHead.from_decoder(dec)
    refs = l2_normalize(torch.randn(4, 128, generator=torch.Generator().manual_seed(0)))
    built = ensure_sketch(head, refs, mm, tmp_path, rank=5)
    stamp = (tmp_path / "sketch_coords_5.npy").stat().st_mtime_ns
    loaded = load_sketch(tmp_path, 5, mm, head_key(head, refs))
    assert loaded is not None and isinstance(loaded.coords, np.memmap)
    np.testing.assert_array_equal(np.asarray(loaded.coords), np.asarray(built.coords))
    np.testing.assert_array_equal(loaded.basis, built.basis)
    assert ensure_sketch(head, refs, mm, tmp_path, rank=5) is not None
    assert (tmp_path / "sketch_coords_5.npy").stat().st_mtime_ns == stamp  # reused, not rebuilt
    other = RelevancyHead.from_decoder(decaying_decoder((16, 24, 48, 128), seed=8))
    assert load_sketch(tmp_path, 5, mm, head_key(other, refs)) is None  # another decoder: rebuilt
    assert load_sketch(tmp_path, 5, mm, head_key(head, refs[:3])) is None  # other references too
    np.save(tmp_path / "sketch_scalars_5.npy", np.zeros((2, 2, 3), np.float32))
    with pytest.raises(InputError, match="sketch_coords_5.npy.*corrupt sketch arrays"):
        load_sketch(tmp_path, 5, mm, head_key(head, refs))


def test_a_cancelled_build_stores_nothing(tmp_path):
    scene, lat, dec, enc = _soft_scene()
    head = RelevancyHead.from_decoder(dec)
    refs = l2_normalize(torch.randn(4, 128, generator=torch.Generator().manual_seed(0)))

    def progress(fraction, stage):
        if fraction >= 0.5:
            raise KeyboardInterrupt

    before = torch.get_num_threads()
    with pytest.raises(KeyboardInterrupt):
        build_sketch(head, refs, lat, rank=4, out_dir=tmp_path, on_progress=progress)
    assert list(tmp_path.iterdir()) == []
    assert torch.get_num_threads() == before  # restored on the way out too


def test_build_restores_the_torch_thread_count(monkeypatch):
    scene, lat, dec, enc = _soft_scene()
    head = RelevancyHead.from_decoder(dec)
    refs = l2_normalize(torch.randn(4, 128, generator=torch.Generator().manual_seed(0)))
    before = torch.get_num_threads()
    whole = build_sketch(head, refs, lat, rank=4)
    monkeypatch.setattr(sketch_module, "BUILD_BLOCK_ROWS", 50)  # several blocks per timestep, on workers
    sk = build_sketch(head, refs, lat, rank=4)
    assert torch.get_num_threads() == before
    np.testing.assert_array_equal(sk.coords, whole.coords)


def test_per_gaussian_relevancy_is_within_the_bound_and_exact_around_one_half(tmp_path):
    scene, lat, dec, enc = _soft_scene()
    exact = QueryEngine(scene, DecoderField(lat, dec), enc, QueryOptions.exact())
    sketched = QueryEngine(scene, DecoderField(lat, dec), enc, QueryOptions(path="sketch", sketch_rank=4),
                           codebook_dir=tmp_path)
    for q in (Q, "object"):
        want = exact.gaussian_relevancy(q, 3).numpy()
        got = sketched.gaussian_relevancy(q, 3).numpy()
        m, rad = sketched.sketch_path.load().margins(sketched.head, sketched.embed_query(q), 10.0, np.array([3]))
        lo, hi = 1 / (1 + np.exp(-(m[0] - rad[0]))), 1 / (1 + np.exp(-(m[0] + rad[0])))
        assert np.all((want >= lo - 1e-6) & (want <= hi + 1e-6))
        assert np.all(np.abs(got - want) <= hi - lo + 1e-6)
        np.testing.assert_array_equal(got > 0.5, want > 0.5)  # membership exact
    assert sketched.stats["decoded_latents"] < exact.stats["decoded_latents"]


def test_the_temporal_pass_keeps_the_per_gaussian_relevancy_the_maps_need(tmp_path):
    scene, lat, dec, enc = _soft_scene()
    fresh = QueryEngine(scene, DecoderField(lat, dec), enc, QueryOptions(path="sketch", sketch_rank=4),
                        codebook_dir=tmp_path)
    want = {t: fresh.gaussian_relevancy(Q, t).numpy() for t in (0, 3, 7)}
    eng = QueryEngine(scene, DecoderField(lat, dec), enc, QueryOptions(path="sketch", sketch_rank=4),
                      codebook_dir=tmp_path)
    eng.temporal(Q)
    before = dict(eng.stats)
    for t, w in want.items():  # the same values (exact scores from another batch: float32 rounding apart)
        np.testing.assert_allclose(eng.gaussian_relevancy(Q, t).numpy(), w, rtol=0, atol=1e-6)
    assert eng.stats["rescored_latents"] == before.get("rescored_latents", 0)  # no work of their own
    assert eng.stats["decoded_latents"] == before.get("decoded_latents", 0)
    eng.forget_query(Q)
    assert eng.sketch_path.relevancy_at(Q, 3) is None
    np.testing.assert_allclose(eng.gaussian_relevancy(Q, 3).numpy(), want[3], rtol=0, atol=1e-6)
