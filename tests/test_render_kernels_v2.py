"""The v2 fused CPU path (RasterOptions(kernel="v2")): fused projection, exact-footprint tile lists,
chunked lane kernels with the α recurrence (tests/test_render_lane_kernels.py holds their numerics),
forward and backward — against the float64 oracle, the torch path, finite differences, and brute force
for the tile extents."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings, strategies as st

from _render_helpers import as_numpy, random_scene, view_cameras
from _render_oracle import render as oracle_render
from fourlegs_engine.render import RasterOptions, cpu_kernels, rasterize, splat
from fourlegs_engine.render import blend_kernels, kernel_backend
from fourlegs_engine.render.kernel_projection import project_gaussians_fused
from fourlegs_engine.render.projection import project_gaussians
from fourlegs_engine.render.tile_lists import build_tile_lists, ellipse_reaches_rect
from fourlegs_engine.scene import Camera
from fourlegs_engine.threads import kernel_threads

pytestmark = pytest.mark.skipif(not cpu_kernels.available(), reason="numba is not installed")

NAMES = ("means", "rotations", "log_scales", "opacity_logits", "colors", "features")
GEOM = NAMES[:4]
OUTS = ("rgb", "features", "depth", "alpha")
V1 = RasterOptions(kernel="v1", cpu_kernel=False)  # the torch reference path
TOL = {torch.float64: 1e-5, torch.float32: 1e-4}


def _render(scene, cam, options, outputs=OUTS, background=(0.2, 0.4, 0.6)):
    return rasterize(*(scene[k] for k in GEOM), cam, colors=scene["colors"], features=scene["features"],
                     background=list(background), outputs=outputs, options=options)


# ------------------------------------------------------------------------------------ forward
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("options", [RasterOptions(), RasterOptions(tile_size=5), RasterOptions(tile_size=64)],
                         ids=["auto", "tile5", "tile64"])
def test_v2_forward_matches_the_oracle(dtype, options):
    """Every view of the shared camera set (near cut, camera inside the cloud, off-centre principal
    point), 4 and 129 blended channels (the narrow and the wide kernel)."""
    scene64 = random_scene(250, 2)
    scene64["features"] = torch.randn(250, 128, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    scene = {k: v.to(dtype) for k, v in scene64.items()}
    s = as_numpy(scene64)
    for cam in view_cameras(40, 30):
        ref = oracle_render(s["means"], s["rotations"], s["log_scales"], s["opacity_logits"], cam,
                            np.concatenate([s["colors"], s["features"]], axis=1),
                            background=[0.2, 0.4, 0.6] + [0.0] * 128)
        with torch.no_grad():
            narrow = _render(scene, cam, options, outputs=("rgb", "alpha"))
            wide = _render(scene, cam, options, outputs=("rgb", "features", "depth", "alpha"))
        for out in (narrow, wide):
            assert out["rgb"].dtype == dtype
            assert np.abs(out["rgb"].double().numpy() - ref["color"][..., :3]).max() <= TOL[dtype], cam.name
            assert np.abs(out["alpha"][..., 0].double().numpy() - ref["alpha"]).max() <= TOL[dtype], cam.name
        assert np.abs(wide["features"].double().numpy() - ref["color"][..., 3:]).max() <= TOL[dtype], cam.name
        assert np.abs(wide["depth"][..., 0].double().numpy() - ref["depth"]).max() / 3.0 <= TOL[dtype], cam.name


def test_v2_forward_equals_the_torch_path_in_float64_on_a_dense_scene():
    """A few thousand overlapping splats (pixels saturate: the stop rule and skipped rows are exercised):
    v2 and the batched torch path agree to float64 rounding, and so does v1's fused kernel."""
    scene = random_scene(3000, 4, log_scale=-2.6)
    cam = view_cameras(96, 72)[0]
    with torch.no_grad():
        ref = _render(scene, cam, V1)
        for options in (RasterOptions(), RasterOptions(kernel="v1"), RasterOptions(tile_size=3)):
            out = _render(scene, cam, options)
            for k in OUTS:
                assert (out[k] - ref[k]).abs().max().item() < 1e-10, (options, k)
    assert (1.0 - ref["alpha"]).min().item() < 1e-3  # some pixels are saturated


def test_v2_results_do_not_depend_on_the_worker_count():
    scene = random_scene(3000, 6, dtype=torch.float32)
    cam = view_cameras(160, 120)[1]
    options = RasterOptions(tile_size=8)
    leaves = {k: v.clone().requires_grad_() for k, v in scene.items()}
    results = []
    for workers in (1, 3):
        with kernel_threads(workers):
            out = _render(leaves, cam, options)
            loss = sum((out[k] * (1 + torch.arange(out[k].numel()).reshape(out[k].shape) % 5)).sum() for k in OUTS)
            grads = torch.autograd.grad(loss, list(leaves.values()))
        results.append(({k: out[k].detach() for k in OUTS}, grads))
    (out1, g1), (out3, g3) = results
    for k in OUTS:
        assert torch.equal(out1[k], out3[k]), k
    for name, a, b in zip(NAMES, g1, g3):  # per-worker gradient buffers are summed: rounding only
        # (a float32 ulp of the largest terms, which cancel in the smallest gradients)
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6 * a.abs().max().item(), msg=name)


# ----------------------------------------------------------------------------------- backward
@pytest.mark.parametrize("options", [RasterOptions(tile_size=4), RasterOptions(tile_size=64)], ids=["tile4", "wide"])
def test_v2_gradcheck_all_inputs(options):
    """Finite differences for every input through the v2 backward (geometry, values, T_final)."""
    g = torch.Generator().manual_seed(2)
    scene = random_scene(9, 12, channels=6, spread=0.25, log_scale=-1.7)
    cam = Camera.look_at((0.0, -2.0, 0.4), (0, 0, 0), width=13, height=9, fov_y=0.8)
    weights = {k: torch.randn(3, cam.height, cam.width, c, generator=g, dtype=torch.float64)
               for k, c in (("rgb", 3), ("features", 6), ("depth", 1), ("alpha", 1))}

    def fn(*inputs):
        out = rasterize(*inputs[:4], cam, colors=inputs[4], features=inputs[5], background=[0.3, 0.1, 0.2],
                        outputs=OUTS, options=options)
        return sum((weights[k] * out[k][None]).flatten(1).sum(1) for k in OUTS)

    inputs = tuple(scene[k].clone().requires_grad_() for k in NAMES)
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("wanted", [NAMES, ("colors",), ("features",), ("means", "opacity_logits")])
def test_v2_gradients_equal_the_torch_path(wanted):
    """Any subset of inputs needing a gradient (features only is the splat kernel; geometry only
    projects through torch): the same gradients as the batched torch path, to float64 rounding."""
    scene = random_scene(400, 3, channels=5)
    for cam in view_cameras(36, 28)[:4]:
        grads = []
        for options in (RasterOptions(), V1):
            leaves = {k: (v.clone().requires_grad_() if k in wanted else v) for k, v in scene.items()}
            out = _render(leaves, cam, options)
            g = torch.Generator().manual_seed(7)
            loss = sum((out[k] * torch.randn(out[k].shape, generator=g, dtype=torch.float64)).sum() for k in OUTS)
            grads.append(torch.autograd.grad(loss, [leaves[k] for k in wanted]))
        for name, a, b in zip(wanted, *grads):
            scale = b.abs().max().item()
            assert scale > 0, (cam.name, name)
            assert (a - b).abs().max().item() <= 1e-9 * scale, (cam.name, name)


def test_v2_float32_gradients_close_to_float64():
    scene = random_scene(300, 8, channels=3)
    cam = view_cameras()[0]
    weight = torch.randn(cam.height, cam.width, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    grads = {}
    for dtype in (torch.float64, torch.float32):
        leaves = [scene[k].to(dtype).requires_grad_() for k in NAMES]
        out = rasterize(*leaves[:4], cam, colors=leaves[4], features=leaves[5], outputs=("rgb", "features", "alpha"))
        loss = (out["rgb"] * weight.to(dtype)).sum() + (out["features"] ** 2).sum() + out["alpha"].sum()
        grads[dtype] = torch.autograd.grad(loss, leaves)
    for name, a, b in zip(NAMES, grads[torch.float32], grads[torch.float64]):
        assert (a.double() - b).abs().max() <= 1e-3 * b.abs().max() + 1e-6, name


def test_v2_splat_is_the_adjoint_of_v2_features():
    scene = random_scene(500, 9, channels=3)
    for cam in view_cameras(33, 21)[:3]:
        v = torch.randn(cam.height, cam.width, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
        rendered = rasterize(*(scene[k] for k in GEOM), cam, features=scene["features"], outputs=("features",))
        lhs = (rendered["features"] * v).sum()
        rhs = (scene["features"] * splat(*(scene[k] for k in GEOM), cam, v)).sum()
        torch.testing.assert_close(lhs, rhs, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(splat(*(scene[k] for k in GEOM), cam, v),
                                   splat(*(scene[k] for k in GEOM), cam, v, options=V1), rtol=1e-10, atol=1e-12)


# --------------------------------------------------------------------------------- projection
@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), log_scale=st.floats(math.log(1e-9), math.log(1e4)),
       spread=st.floats(0.01, 30.0), float32=st.booleans(), extent=st.sampled_from(["opacity", "3sigma"]))
def test_fused_projection_matches_the_torch_projection(seed, log_scale, spread, float32, extent):
    """Tiny to huge scales, Gaussians behind, at and beside the camera: the same visibility, pixel
    bounds, means, conics, depths and opacities as the torch projection (float64 inside both)."""
    dtype = torch.float32 if float32 else torch.float64
    scene = random_scene(300, seed, spread=spread, log_scale=log_scale, dtype=dtype)
    options = RasterOptions(extent=extent)
    for cam in view_cameras()[3:5]:
        a = project_gaussians(*(scene[k] for k in GEOM), cam, options, dtype)
        b = project_gaussians_fused(*(scene[k] for k in GEOM), cam, options, dtype)
        assert torch.equal(a.visible, b.visible)
        vis = a.visible
        assert torch.equal(a.bounds[vis], b.bounds[vis])
        for name in ("means2d", "conics", "depths", "opacities"):
            x, y = getattr(a, name)[vis].double(), getattr(b, name)[vis].double()
            rel = ((x - y).abs() / x.abs().clamp_min(1e-300)).max().item() if vis.any() else 0.0
            assert rel <= (1e-12 if dtype == torch.float64 else 2.5e-7), name


# ---------------------------------------------------------------------------------- tile extents
conics = st.tuples(st.floats(1e-4, 50.0), st.floats(-0.999, 0.999), st.floats(1e-4, 50.0)).map(
    lambda t: (t[0], t[1] * math.sqrt(t[0] * t[2]), t[2]))  # positive definite: |b| < sqrt(ac)


@settings(max_examples=300, deadline=None)
@given(conic=conics, reach=st.floats(0.0, 12.0), mx=st.floats(-40, 40), my=st.floats(-40, 40),
       rect=st.tuples(st.integers(-20, 20), st.integers(0, 20), st.integers(-20, 20), st.integers(0, 20)))
def test_ellipse_reaches_rect_never_misses_a_pixel_centre(conic, reach, mx, my, rect):
    """Brute force over the rectangle's pixel centres: whenever one lies in the footprint, the tile
    test says the footprint reaches the tile; when none is within a generous margin, it says no."""
    a, b, c = conic
    x0, w, y0, h = rect
    xs, ys = np.meshgrid(np.arange(x0, x0 + w + 1) + 0.5, np.arange(y0, y0 + h + 1) + 0.5)
    dx, dy = xs - mx, ys - my
    q = a * dx * dx + 2 * b * dx * dy + c * dy * dy
    reaches = ellipse_reaches_rect(mx, my, a, b, c, reach, x0 + 0.5, x0 + w + 0.5, y0 + 0.5, y0 + h + 0.5)
    if (q <= reach).any():
        assert reaches
    # a rectangle outside the footprint's bounding box (half-sides sqrt(reach·Σxx), sqrt(reach·Σyy)) is refused
    det = a * c - b * b
    rx, ry = math.sqrt(reach * c / det), math.sqrt(reach * a / det)
    margin = 1e-6 * (1 + rx + ry)
    if (x0 + 0.5 > mx + rx + margin or x0 + w + 0.5 < mx - rx - margin
            or y0 + 0.5 > my + ry + margin or y0 + h + 0.5 < my - ry - margin):
        assert not reaches


def test_tile_lists_hold_every_blended_pair_and_only_footprint_tiles():
    """Every (pixel, Gaussian) blending weight of the torch path lies in a tile whose v2 list holds
    that Gaussian; the lists are front to back; and they have fewer entries than the boxes'."""
    scene = random_scene(600, 5, log_scale=-1.9)
    cam = view_cameras(48, 40)[2]
    options = RasterOptions()
    w = rasterize(*(scene[k] for k in GEOM), cam, outputs=("weights",), options=V1)["weights"]
    proj = project_gaussians(*(scene[k] for k in GEOM), cam, options, torch.float64)
    for tile_w, tile_h in ((4, 4), (16, 8), (48, 40)):
        lists = build_tile_lists(proj.means2d, proj.conics, proj.opacities, proj.depths, proj.visible, proj.bounds,
                                 cam.width, cam.height, tile_w, tile_h, kernel_backend.alpha_floor(options, torch.float64))
        members = set()
        for t in range(lists.num_tiles):
            ranks = lists.tile_ranks[lists.tile_offsets[t]:lists.tile_offsets[t + 1]]
            assert (np.diff(ranks) > 0).all()
            members.update((t, int(lists.order[r])) for r in ranks)
        px, py = w.pixel.numpy() % cam.width, w.pixel.numpy() // cam.width
        tiles = (py // tile_h) * lists.tiles_x + px // tile_w
        assert all((int(t), int(g)) in members for t, g in zip(tiles, w.gaussian.numpy()))
        depths = proj.depths[torch.from_numpy(lists.order)]
        assert (depths[1:] >= depths[:-1]).all()
        assert lists.num_pairs <= lists.pairs_in_boxes
    assert lists.num_pairs < lists.pairs_in_boxes or lists.num_tiles == 1


def test_work_counts_are_consistent_with_the_blending_weights():
    scene = random_scene(800, 11, log_scale=-2.2)
    cam = view_cameras(64, 48)[0]
    work = kernel_backend.count_work(*(scene[k] for k in GEOM), cam)
    w = rasterize(*(scene[k] for k in GEOM), cam, outputs=("weights",), options=V1)["weights"]
    assert work["blended"] == w.weight.numel()
    assert work["in_boxes"] >= work["in_footprints"] >= work["blended"] > 0
    assert work["evaluated"] >= work["blended"]
    assert work["tile_pairs"] <= work["tile_pairs_in_boxes"]


def test_wide_kernel_flushes_its_batch_before_its_entry_arrays_overflow(monkeypatch):
    """A tile whose list goes on past pixels that have stopped: five opaque walls stop columns 0-2 of a
    4x4 tile, column 3 stays open, and 200 small splats behind the walls add no fragment each. The wide
    kernel's batch must flush on its entry count too: run as plain Python, where numpy checks every index,
    with a 64-entry batch, it goes through and equals the compiled kernel. (The compiled kernel used to
    write past its entry arrays there and corrupt the heap: `fourlegs bench accuracy-time --scene bench`
    aborted during extraction.)"""
    from fourlegs_engine.render.tile_lists import TileLists

    floor = 1.0 / 255.0
    walls, small = 5, 200
    n = walls + small
    packed = np.zeros((n, 8))
    boxes = np.zeros((n, 4), dtype=np.int64)
    for k in range(n):
        wall = k < walls
        a = 0.01 if wall else 4.0
        o = 0.99 if wall else 0.5
        packed[k] = (1.5, 2.0 if wall else 1.5, a, 0.0, a, o, np.log(o), 2.0 * (np.log(o) - np.log(floor)))
        boxes[k] = (0, 2, 0, 3) if wall else (1, 1, 1, 1)
    lists = TileLists(order=np.arange(n), packed=packed, boxes=boxes, tile_offsets=np.array([0, n]),
                      tile_ranks=np.arange(n, dtype=np.int32), tiles_x=1, tiles_y=1, tile_w=4, tile_h=4, width=4,
                      height=4, pairs_in_boxes=n)
    values = np.random.default_rng(0).normal(size=(n, 5))

    def run(kernel):
        accum, trans = np.zeros((16, 5)), np.zeros(16)
        kernel(np.arange(1), lists.tile_offsets, lists.tile_ranks, lists.order, lists.packed, lists.boxes, 1, 4, 4,
               4, 4, values, np.nextafter(floor, 0.0), 0.99, 1e-4, accum, trans)
        return accum, trans

    compiled = run(blend_kernels._blend_wide)
    assert (compiled[1].reshape(4, 4)[:, :3] < 1e-3).all() and (compiled[1].reshape(4, 4)[:, 3] == 1.0).all()
    monkeypatch.setattr(blend_kernels, "FRAGMENT_BATCH", 64)
    python = run(blend_kernels._blend_wide_py)
    np.testing.assert_allclose(python[0], compiled[0], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(python[1], compiled[1])
