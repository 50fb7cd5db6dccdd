"""Per-timestep result stores: selection parsing, sharding, manifests and config-change refusal."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from fourlegs_engine.errors import ConfigMismatchError, InputError
from fourlegs_engine.language.store import (StepStore, config_hash, format_ranges, parse_shard, parse_timesteps,
                                            select_timesteps)


def test_timestep_selection_syntax():
    assert parse_timesteps(None, 5) == [0, 1, 2, 3, 4]
    assert parse_timesteps("1:3", 5) == [1, 2]
    assert parse_timesteps("-2:", 5) == [3, 4]
    assert parse_timesteps("0:5:2", 5) == [0, 2, 4]
    assert parse_timesteps("4,1,1", 5) == [1, 4]
    for bad in ("x", "1:2:3:4", "9", "3:1"):
        with pytest.raises(InputError):
            parse_timesteps(bad, 5)


def test_shard_syntax():
    assert parse_shard(None) == (0, 1)
    assert parse_shard("2/4") == (2, 4)
    for bad in ("4/4", "1/0", "a/b", "1"):
        with pytest.raises(InputError, match="--shard"):
            parse_shard(bad)


@given(st.integers(1, 60), st.integers(1, 7))
def test_shards_partition_the_selection(T, n):
    parts = [select_timesteps(T, None, f"{i}/{n}") for i in range(n)]
    merged = sorted(t for p in parts for t in p)
    assert merged == list(range(T))


def test_format_ranges():
    assert format_ranges([0, 1, 2, 5, 7, 8]) == "0-2, 5, 7-8"
    assert format_ranges([]) == ""


def test_store_refuses_another_configuration(tmp_path):
    store = StepStore(tmp_path / "s", "latents", {"a": 1}, 3).open()
    store.save(1, np.ones((2, 2), np.float16))
    assert store.done() == [1] and store.missing() == [0, 2]
    assert StepStore(tmp_path / "s", "latents", {"a": 1}, 3).open().is_done(1)   # same config: resume
    with pytest.raises(ConfigMismatchError, match="changed: a"):
        StepStore(tmp_path / "s", "latents", {"a": 2}, 3).open()
    fresh = StepStore(tmp_path / "s", "latents", {"a": 2}, 3).open(overwrite=True)
    assert fresh.done() == [] and fresh.read_manifest()["config_hash"] == config_hash({"a": 2})
    fresh.save(0, np.zeros((2, 2), np.float16))
    (tmp_path / "s" / "t000002.npy").write_bytes(b"garbage")
    report = fresh.check((2, 2))
    assert report["missing"] == [1] and report["bad"][0]["t"] == 2 and not report["complete"]


def test_config_hash_is_order_independent_and_rejects_nan():
    assert config_hash({"a": 1, "b": [1, 2]}) == config_hash({"b": [1, 2], "a": 1})
    with pytest.raises(ValueError):
        config_hash({"a": float("nan")})


@given(st.lists(st.booleans(), min_size=1, max_size=40), st.integers(0, 2 ** 31 - 1))
def test_steps_with_mostly_zero_rows_are_stored_without_them_and_read_back_exactly(zero_rows, seed):
    import tempfile
    from pathlib import Path

    rng = np.random.default_rng(seed)
    array = rng.normal(size=(len(zero_rows), 3, 2)).astype(np.float16)
    array[np.asarray(zero_rows)] = 0
    with tempfile.TemporaryDirectory() as tmp:
        store = StepStore(Path(tmp) / "s", "features", {"a": 1}, 2).open()
        store.save(1, array)
        sparse = sum(zero_rows) >= 0.25 * len(zero_rows)
        assert store.rows_path(1).is_file() == sparse
        assert store.step_file_names(1) == (["t000001.rows.npy"] if sparse else []) + ["t000001.npy"]
        stored = np.load(store.step_path(1), allow_pickle=False)
        assert stored.shape[0] == (len(zero_rows) - sum(zero_rows) if sparse else len(zero_rows))
        back = store.load(1)
        assert back.dtype == array.dtype and back.shape == array.shape
        np.testing.assert_array_equal(back, array)
        assert store.done() == [1] and store.check(array.shape)["bad"] == []
        store.save(1, np.ones_like(array))  # rewritten whole: the row index goes
        assert not store.rows_path(1).exists() and np.all(store.load(1) == 1)
        store.clear()
        assert list((Path(tmp) / "s").iterdir()) == []


def test_a_row_index_that_does_not_match_its_rows_is_one_clear_error(tmp_path):
    store = StepStore(tmp_path / "s", "features", {"a": 1}, 1).open()
    array = np.zeros((6, 4), np.float16)
    array[2] = 1
    store.save(0, array)
    np.save(store.rows_path(0), np.array([6, 2, 3], np.int64))
    with pytest.raises(InputError, match="row index does not match"):
        store.load(0)
    np.save(store.rows_path(0), np.array([6, 9], np.int64))
    with pytest.raises(InputError, match="increasing and below 6"):
        store.load(0)
