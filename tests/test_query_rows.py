"""Scattered latent rows read with os.pread (query/rows.py) against numpy's own indexing."""
import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fourlegs_engine.errors import InputError
from fourlegs_engine.query import rows as rows_module
from fourlegs_engine.query.rows import RowReader

T, N, D = 3, 50, 6


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    path = tmp_path_factory.mktemp("rows") / "latents.npy"
    values = np.random.default_rng(0).normal(size=(T, N, D)).astype(np.float16)
    np.save(path, values)
    return path, values


@settings(max_examples=60, deadline=None)
@given(st.sets(st.integers(0, T * N - 1), max_size=T * N))
def test_any_sorted_index_set_reads_the_stored_rows(stored, picked):
    path, values = stored
    flat = np.array(sorted(picked), dtype=np.int64)
    reader = RowReader(np.load(path, mmap_mode="r"))
    assert reader.path == str(path)
    got = reader.read(flat)
    assert got.dtype == np.float32 and got.shape == (flat.size, D)
    np.testing.assert_array_equal(got, values.reshape(T * N, D)[flat].astype(np.float32))


def test_runs_first_and_last_rows_and_dtype(stored):
    path, values = stored
    reader = RowReader(np.load(path, mmap_mode="r"))
    flat = np.array([0, 1, 2, N - 1, N, 2 * N + 7, T * N - 2, T * N - 1])  # runs crossing a timestep
    np.testing.assert_array_equal(reader.read(flat, dtype=np.float16), values.reshape(-1, D)[flat])
    assert reader.read(np.zeros(0, dtype=np.int64)).shape == (0, D)


def test_views_and_in_memory_arrays_are_indexed_in_memory(stored):
    path, values = stored
    mm = np.load(path, mmap_mode="r")
    view = mm[1:]  # a view keeps its parent's offset attribute: must not be read from the file
    assert RowReader(view).path is None
    flat = np.array([3, N + 4, N + 5])
    np.testing.assert_array_equal(RowReader(view).read(flat), values[1:].reshape(-1, D)[flat].astype(np.float32))
    assert RowReader(values).path is None
    np.testing.assert_array_equal(RowReader(values).read(flat), values.reshape(-1, D)[flat].astype(np.float32))


def test_a_file_truncated_under_the_reader_is_a_clear_error(tmp_path):
    path = tmp_path / "latents.npy"
    np.save(path, np.ones((T, N, D), dtype=np.float16))
    reader = RowReader(np.load(path, mmap_mode="r"))
    os.truncate(path, os.path.getsize(path) - 4 * D)  # the last rows gone
    np.testing.assert_array_equal(reader.read(np.array([0, 5])), np.ones((2, D)))
    with pytest.raises(InputError, match="latents.npy.*ended early"):
        reader.read(np.array([0, T * N - 1]))


def test_a_file_renamed_over_is_not_read(tmp_path):
    # the reader holds the file it was given open: replacing the path (as an atomic rewrite does)
    # leaves it reading the data its memory mapping shows
    path = tmp_path / "latents.npy"
    np.save(path, np.zeros((T, N, D), dtype=np.float16))
    mm = np.load(path, mmap_mode="r")
    reader = RowReader(mm)
    np.save(tmp_path / "new.npy", np.ones((T, N, D), dtype=np.float16))
    os.replace(tmp_path / "new.npy", path)
    np.testing.assert_array_equal(reader.read(np.array([4, 9])), np.asarray(mm.reshape(-1, D)[[4, 9]]))
    np.testing.assert_array_equal(reader.read(np.array([4, 9])), np.zeros((2, D)))


@settings(max_examples=40, deadline=None)
@given(st.sets(st.integers(0, T * N - 1), max_size=T * N), st.integers(0, 40), st.integers(1, 12))
def test_spans_and_batches_of_any_size_read_the_stored_rows(stored, picked, gap_rows, batch_rows):
    # reads that merge rows across gaps, and batches smaller than one span, still give exactly the rows
    path, values = stored
    flat = np.array(sorted(picked), dtype=np.int64)
    reader = RowReader(np.load(path, mmap_mode="r"))
    row_bytes = D * values.dtype.itemsize
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(rows_module, "GAP_ROWS", gap_rows)
        mp.setattr(rows_module, "BATCH_BYTES", batch_rows * row_bytes)
        got = reader.read(flat)
    np.testing.assert_array_equal(got, values.reshape(T * N, D)[flat].astype(np.float32))
