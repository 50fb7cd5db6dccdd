"""Fused CPU kernels (numba) for the counter-based hashing of the simulated video encoder.

The simulated encoder draws its corruptions from SplitMix64 hashes of per-clip keys
(:mod:`.simulated`). Written with numpy, one clip key folds its F·C quantized coverage values in
F·C separate passes over the batch, and the 768 noise uniforms of a clip take two SplitMix64 rounds
of about a dozen full-array uint64 passes each. These kernels do the same integer arithmetic
element by element in one pass. Integer arithmetic wraps identically and the uint64 -> float64
conversion is exact, so the results are bit-identical to the numpy reference (which stays the
fallback where numba is missing, and the oracle of the tests). The transcendental functions of the
Box-Muller transform stay in numpy, so they round exactly as before.
"""
from __future__ import annotations

import numpy as np

from ..jit_cache import JIT_CACHE

try:  # pragma: no cover - exercised when numba is missing
    import numba
except ImportError:  # pragma: no cover
    numba = None

GOLDEN = 0x9E3779B97F4A7C15
MIX1 = 0xBF58476D1CE4E5B9
MIX2 = 0x94D049BB133111EB
COUNTER_MULTIPLIER = 0xD1B54A32D192ED03


def available() -> bool:
    """True when numba is importable."""
    return numba is not None


def _splitmix64_scalar_py(x):  # pragma: no cover - compiled by numba
    z = x + np.uint64(GOLDEN)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(MIX1)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(MIX2)
    return z ^ (z >> np.uint64(31))


def _fold_keys_py(head, values, out):  # pragma: no cover - compiled by numba
    """out[b] = splitmix64(...splitmix64(splitmix64(head ^ values[b,0]) ^ values[b,1])... ^ values[b,K-1])."""
    for b in range(values.shape[0]):
        key = head
        for k in range(values.shape[1]):
            key = _splitmix64(key ^ values[b, k])
        out[b] = key


def _uniforms_py(keys, first_counter, out):  # pragma: no cover - compiled by numba
    """out[b, j] = uniform(keys[b], first_counter + j), as :func:`.simulated._uniform`."""
    scale = 1.0 / float(1 << 53)
    for b in range(keys.shape[0]):
        base = keys[b] * np.uint64(COUNTER_MULTIPLIER)
        for j in range(out.shape[1]):
            bits = _splitmix64(_splitmix64(base + np.uint64(first_counter + j))) >> np.uint64(11)
            out[b, j] = (float(bits) + 0.5) * scale


if numba is not None:
    _splitmix64 = numba.njit(nogil=True, cache=JIT_CACHE, inline="always")(_splitmix64_scalar_py)
    _fold_keys = numba.njit(nogil=True, cache=JIT_CACHE)(_fold_keys_py)
    _uniforms = numba.njit(nogil=True, cache=JIT_CACHE)(_uniforms_py)
else:  # pragma: no cover
    _splitmix64 = _fold_keys = _uniforms = None


def fold_keys(head: int, values: np.ndarray) -> np.ndarray:
    """(B,) uint64 keys: ``head`` with every column of ``values`` (B, K) uint64 folded in, in order."""
    values = np.ascontiguousarray(values, dtype=np.uint64)
    out = np.empty(values.shape[0], dtype=np.uint64)
    _fold_keys(np.uint64(head), values, out)
    return out


def uniforms(keys: np.ndarray, first_counter: int, count: int) -> np.ndarray:
    """(B, count) float64 uniforms in (0, 1) for counters ``first_counter .. first_counter + count - 1``."""
    keys = np.ascontiguousarray(keys, dtype=np.uint64)
    out = np.empty((keys.shape[0], int(count)), dtype=np.float64)
    _uniforms(keys, int(first_counter), out)
    return out
