"""The SIMD lanes of the forward kernels (:mod:`fourlegs_engine.render.lane_kernels`): the LLVM vector code
against its plain-Python reference bit for bit, the row recurrence of α against direct exps (to its
range limits), and the forward kernels compiled against themselves run as plain Python."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings, strategies as st

from _render_helpers import random_scene, view_cameras
from fourlegs_engine.render import RasterOptions, blend_kernels, cpu_kernels, kernel_backend, lane_kernels
from fourlegs_engine.render.kernel_projection import project_gaussians_fused

pytestmark = pytest.mark.skipif(not cpu_kernels.available(), reason="numba is not installed")

LANES = lane_kernels.LANES
FLOOR = float(np.nextafter(np.float32(1 / 255), np.float32(0)))
ALPHA_MAX, T_MIN = 0.99, 1e-4

if cpu_kernels.available():
    import numba

    @numba.njit
    def blend_lanes_compiled(trans, planes, lanes, base, n_lanes, step, vals, floor, alpha_max, t_min):
        return lane_kernels.blend_lanes(trans, planes, lanes, base, n_lanes, step, vals, floor, alpha_max, t_min)

    @numba.njit
    def gradient_lanes_compiled(trans, grads, total, prefix, lanes, base, n_lanes, step, vals, dx_first, dy, sums,
                                floor, alpha_max, t_min):
        return lane_kernels.gradient_lanes(trans, grads, total, prefix, lanes, base, n_lanes, step, vals, dx_first, dy,
                                           sums, floor, alpha_max, t_min)

    @numba.njit
    def start_lanes_compiled(lanes, mx, my, a, b, c, log_o, cx, cy):
        lane_kernels.start_lanes(lanes, mx, my, a, b, c, log_o, cx, cy)

    @numba.njit
    def fragment_lanes_compiled(trans, lanes, base, n_lanes, step, pixel_base, pixels, weights, alphas, n_frag, floor,
                                alpha_max, t_min):
        return lane_kernels.fragment_lanes(trans, lanes, base, n_lanes, step, pixel_base, pixels, weights, alphas,
                                           n_frag, floor, alpha_max, t_min)


def _lane_state(seed: int, base: int, channels: int = 3):
    """A plane of T with stopped pixels (−T), pixels at the stop threshold and fresh ones, channel planes
    (channels, P), and α lanes spanning zero, the floor, ordinary values and above the clamp."""
    rng = np.random.default_rng(seed)
    size = base + LANES + 3
    trans = rng.choice([1.0, 0.5, T_MIN / 0.4, T_MIN * 1.0000001, 0.3], size=size) * rng.choice([1.0, -1.0], size,
                                                                                                p=[0.8, 0.2])
    planes = rng.normal(size=(channels, size))
    gauss = rng.choice([0.0, FLOOR, np.nextafter(FLOOR, 1.0), 0.6, 0.99, 1.7, 1e-300, 0.02], size=LANES)
    ratio = rng.uniform(0.2, 3.0, size=LANES)
    return trans, planes, np.concatenate([gauss, ratio])


@settings(max_examples=150, deadline=None)
@given(seed=st.integers(0, 10_000), base=st.integers(0, 40), n_lanes=st.integers(0, LANES),
       step=st.floats(1e-3, 10.0), values=st.lists(st.floats(-5, 5), min_size=1, max_size=8),
       float32=st.booleans())
def test_blend_lanes_vector_code_equals_the_python_reference(seed, base, n_lanes, step, values, float32):
    trans, planes, lanes = _lane_state(seed, base, len(values))
    vals = np.array(values, dtype=np.float32 if float32 else np.float64)
    python = [trans.copy(), planes.copy(), lanes.copy()]
    compiled = [trans.copy(), planes.copy(), lanes.copy()]
    stopped_py = lane_kernels.blend_lanes(*python, base, n_lanes, step, vals, FLOOR, ALPHA_MAX, T_MIN)
    stopped_jit = blend_lanes_compiled(*compiled, base, n_lanes, step, vals, FLOOR, ALPHA_MAX, T_MIN)
    assert stopped_jit == stopped_py
    for a, b in zip(compiled, python):
        np.testing.assert_array_equal(a, b)
    # only the chunk's lanes changed, and what stopped is stored negated
    untouched = np.r_[0:base, base + n_lanes:trans.size]
    np.testing.assert_array_equal(compiled[0][untouched], trans[untouched])
    assert stopped_py == int(((trans[base:base + n_lanes] > 0) & (compiled[0][base:base + n_lanes] < 0)).sum())


@settings(max_examples=150, deadline=None)
@given(seed=st.integers(0, 10_000), base=st.integers(0, 40), n_lanes=st.integers(0, LANES),
       values=st.lists(st.floats(-5, 5), min_size=1, max_size=8), dx_first=st.floats(-30, 30),
       dy=st.floats(-30, 30))
def test_gradient_lanes_vector_code_equals_the_python_reference(seed, base, n_lanes, values, dx_first, dy):
    """The backward's lanes: T, the prefix sums, the α update and every per-lane gradient sum bit for bit,
    clamped lanes (α ≥ α_max: no exponent gradient) and stopped pixels included."""
    trans, planes, lanes = _lane_state(seed, base, len(values))
    vals = np.array(values)
    rng = np.random.default_rng(seed + 1)
    total, prefix = rng.normal(size=trans.size), rng.normal(size=trans.size)
    sums = rng.normal(size=(lane_kernels.GEOMETRY_SUMS + len(values), LANES))
    runs = []
    for run in (lane_kernels.gradient_lanes, gradient_lanes_compiled):
        state = [trans.copy(), planes.copy(), total.copy(), prefix.copy(), lanes.copy()]
        out = sums.copy()
        stopped = run(*state, base, n_lanes, 0.7, vals, dx_first, dy, out, FLOOR, ALPHA_MAX, T_MIN)
        runs.append((stopped, state, out))
    (s_py, state_py, sums_py), (s_jit, state_jit, sums_jit) = runs
    assert s_jit == s_py
    for a, b in zip(state_jit + [sums_jit], state_py + [sums_py]):
        np.testing.assert_array_equal(a, b)
    blended = (trans[base:base + n_lanes] > 0) & (state_py[0][base:base + n_lanes] > 0) & (
        state_py[0][base:base + n_lanes] != trans[base:base + n_lanes])
    changed = (prefix[base:base + n_lanes] != state_py[3][base:base + n_lanes])
    assert not (changed & ~blended).any()  # only blended pixels add to the prefix sums


@pytest.mark.parametrize("weight_dtype", [np.float64, np.float32])
@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 10_000), base=st.integers(0, 40), n_lanes=st.integers(0, LANES), n_frag=st.integers(0, 5))
def test_fragment_lanes_vector_code_equals_the_python_reference(weight_dtype, seed, base, n_lanes, n_frag):
    trans, _, lanes = _lane_state(seed, base)
    outputs = []
    for run in (lane_kernels.fragment_lanes, fragment_lanes_compiled):
        t, l = trans.copy(), lanes.copy()
        pixels = np.full(n_frag + LANES + 2, 7, dtype=np.uint64)
        weights = np.full(n_frag + LANES + 2, -1.0, dtype=weight_dtype)
        alphas = np.full(n_frag + LANES + 2, -1.0)
        count, stopped = run(t, l, base, n_lanes, 0.5, 1000 + base, pixels, weights, alphas, n_frag, FLOOR, ALPHA_MAX,
                             T_MIN)
        outputs.append((count, stopped, t, l, pixels[:count], weights[:count], alphas[:count]))
    (c_py, s_py, *arrays_py), (c_jit, s_jit, *arrays_jit) = outputs
    assert (c_jit, s_jit) == (c_py, s_py)
    for a, b in zip(arrays_jit, arrays_py):
        np.testing.assert_array_equal(a, b)
    before, after = trans[base:base + n_lanes], outputs[0][2][base:base + n_lanes]
    assert c_py - n_frag == int(((before > 0) & (after > 0) & (after != before)).sum())


@settings(max_examples=200, deadline=None)
@given(x=st.lists(st.floats(-800.0, 800.0), min_size=1, max_size=40))
def test_exp_lanes_is_within_two_ulp_of_exp(x):
    """The polynomial exp of the chunk starts, over and past the range it is used on (clamped at ±708)."""
    got = lane_kernels.exp_lanes(np.array(x))
    want = np.exp(np.clip(x, -lane_kernels.EXP_LIMIT, lane_kernels.EXP_LIMIT))
    assert np.isfinite(got).all() and (got > 0).all()
    np.testing.assert_allclose(got, want, rtol=2 * np.finfo(np.float64).eps, atol=0)


@settings(max_examples=200, deadline=None)
@given(mx=st.floats(-40, 40), my=st.floats(-40, 40), log_a=st.floats(-9, 6), log_c=st.floats(-9, 6),
       rho=st.floats(-0.9999, 0.9999), log_o=st.floats(-6, 0), cx=st.integers(-50, 50), cy=st.integers(-50, 50))
def test_start_lanes_vector_code_equals_the_python_reference(mx, my, log_a, log_c, rho, log_o, cx, cy):
    a, c = math.exp(log_a), math.exp(log_c)
    b = rho * math.sqrt(a * c)
    python, compiled = np.empty(2 * LANES), np.empty(2 * LANES)
    lane_kernels.start_lanes(python, mx, my, a, b, c, log_o, cx, cy)
    start_lanes_compiled(compiled, mx, my, a, b, c, log_o, cx, cy)
    np.testing.assert_array_equal(compiled, python)


def _direct(packed, x, y):
    mx, my, a, b, c, _, log_o, _ = packed[0]
    dx, dy = x + 0.5 - mx, y + 0.5 - my
    return math.exp(log_o - 0.5 * (a * dx * dx + 2 * b * dx * dy + c * dy * dy))


@settings(max_examples=300, deadline=None)
@given(log_a=st.floats(math.log(1e-4), math.log(400.0)), log_c=st.floats(math.log(1e-4), math.log(400.0)),
       rho=st.floats(-0.9999, 0.9999), log_o=st.floats(-5.5, 0.0), mx=st.floats(-30, 30), my=st.floats(-30, 30),
       cx=st.integers(-20, 20), cy=st.integers(-20, 20), width=st.integers(1, LANES), rows=st.integers(1, 40))
def test_chunk_recurrence_matches_direct_exps_or_falls_back(log_a, log_c, rho, log_o, mx, my, cx, cy, width, rows):
    """Over every row of the chunk, α by the row recurrence stays within 1e-12 (relative) of a direct exp;
    where the exponents leave its range the chunk falls back to direct rows, which are the exps."""
    a, c = math.exp(log_a), math.exp(log_c)
    b = rho * math.sqrt(a * c)
    packed = np.array([[mx, my, a, b, c, math.exp(log_o), log_o, 12.0]])
    lanes = np.full(2 * LANES, np.nan)
    step = lane_kernels.chunk_start(packed, 0, cx, cy, cx + width - 1, cy + rows - 1, lanes)
    for y in range(cy, cy + rows):
        if step < 0.0:
            lane_kernels.direct_row(packed, 0, cx, y, lanes)
        for lane in range(width):
            direct = _direct(packed, cx + lane, y)
            assert math.isfinite(lanes[lane])
            assert abs(lanes[lane] - direct) <= 1e-12 * direct + 1e-290, (y, lane)
        if step >= 0.0:
            lanes[:LANES] *= lanes[LANES:]
            lanes[LANES:] *= step
        else:
            np.testing.assert_array_equal(lanes[LANES:], 1.0)
    corners = [math.log(max(_direct(packed, x, y), 1e-320)) for x in (cx, cx + width) for y in (cy, cy + rows)]
    if min(corners) > lane_kernels.RECURRENCE_MIN_EXPONENT + 1.0:
        assert step == pytest.approx(math.exp(-c))


def test_a_chunk_far_out_on_a_thin_gaussian_is_evaluated_directly():
    """A needle-thin, tilted Gaussian: the far corners of a 16 × 40 chunk sit thousands of σ across it,
    e^(−E) would overflow — the chunk must take the direct path, and its α there is the exp."""
    a, c, b = 400.0, 400.0, 399.9
    packed = np.array([[8.0, 20.0, a, b, c, 0.9, math.log(0.9), 12.0]])
    lanes = np.empty(2 * LANES)
    assert lane_kernels.chunk_start(packed, 0, 0, 0, LANES - 1, 39, lanes) < 0
    lane_kernels.direct_row(packed, 0, 0, 20, lanes)
    np.testing.assert_allclose(lanes[:LANES], [_direct(packed, x, 20) for x in range(LANES)], rtol=1e-15, atol=0)


@pytest.mark.parametrize("channels", [3, 9])
def test_forward_kernels_compiled_equal_their_python_run(channels, monkeypatch):
    """The narrow (3 channels) and wide (9 > NARROW_CHANNELS) forward kernels run as plain Python — numpy
    checks every index the lanes touch, the lanes are the Python reference — equal the compiled kernels
    exactly."""
    scene = random_scene(120, 3, log_scale=-1.6)
    cam = view_cameras(40, 21)[0]
    options = RasterOptions(tile_size=20).check()
    proj = project_gaussians_fused(scene["means"], scene["rotations"], scene["log_scales"], scene["opacity_logits"],
                                   cam, options, torch.float64)
    lists = kernel_backend.tile_lists(proj, cam, options, torch.float64, channels)
    values = np.random.default_rng(0).normal(size=(120, channels))
    compiled, python = ((blend_kernels._blend_narrow, blend_kernels._blend_narrow_py)
                        if channels <= blend_kernels.NARROW_CHANNELS else
                        (blend_kernels._blend_wide, blend_kernels._blend_wide_py))

    def run(kernel):
        accum, trans = np.zeros((cam.width * cam.height, channels)), np.zeros(cam.width * cam.height)
        kernel(np.arange(lists.num_tiles), lists.tile_offsets, lists.tile_ranks, lists.order, lists.packed,
               lists.boxes, lists.tiles_x, lists.tile_w, lists.tile_h, lists.width, lists.height, values,
               kernel_backend.alpha_floor(options, torch.float64), ALPHA_MAX, T_MIN, accum, trans)
        return accum, trans

    fast = run(compiled)  # compiled (and cached) with the module's own functions, before they are swapped
    for name in ("_tile_start", "_skip_row", "_entry_fragments"):
        monkeypatch.setattr(blend_kernels, name, getattr(blend_kernels, name + "_py"))
    monkeypatch.setattr(blend_kernels, "chunk_start", lane_kernels.chunk_start_py)
    monkeypatch.setattr(blend_kernels, "direct_row", lane_kernels.direct_row_py)
    slow = run(python)
    assert (fast[1] < 1.0).mean() > 0.3  # the scene covers the view
    np.testing.assert_array_equal(fast[0], slow[0])
    np.testing.assert_array_equal(fast[1], slow[1])


@pytest.mark.parametrize("channels", [1, 3, 6])
def test_lane_backward_equals_the_fragment_backward(channels):
    """The narrow backward (gradient sums formed in the lanes) against the many-channel one (sums over each
    entry's fragments), on the same forward: ∂L/∂values and ∂L/∂geometry agree to float64 rounding."""
    from fourlegs_engine.render import backward_kernels

    scene = random_scene(150, 5, log_scale=-1.7)
    cam = view_cameras(48, 30)[1]
    options = RasterOptions().check()
    proj = project_gaussians_fused(scene["means"], scene["rotations"], scene["log_scales"], scene["opacity_logits"],
                                   cam, options, torch.float64)
    lists = kernel_backend.tile_lists(proj, cam, options, torch.float64, channels)
    rng = np.random.default_rng(1)
    values = rng.normal(size=(150, channels))
    accum, trans = kernel_backend.blend_forward(lists, torch.from_numpy(values), options)
    n_pix = cam.width * cam.height
    grad_accum, grad_trans = rng.normal(size=(n_pix, channels)), rng.normal(size=n_pix)
    grid = (lists.tile_offsets, lists.tile_ranks, lists.order, lists.packed, lists.boxes, lists.tiles_x, lists.tile_w,
            lists.tile_h, lists.width, lists.height)
    rules = (kernel_backend.alpha_floor(options, torch.float64), options.alpha_max, options.transmittance_min)
    results = []
    for kernel in (backward_kernels._backward_narrow, backward_kernels._backward):
        grad_values, grad_geometry = np.zeros((150, channels)), np.zeros((150, 6))
        kernel(np.arange(lists.num_tiles), *grid, values, grad_accum, grad_trans, trans.numpy(), accum.numpy(), *rules,
               True, True, grad_values, grad_geometry)
        results.append((grad_values, grad_geometry))
    assert np.abs(results[1][1]).max() > 0
    for lane, fragment in zip(*results):
        np.testing.assert_allclose(lane, fragment, rtol=1e-9, atol=1e-9 * np.abs(fragment).max())
