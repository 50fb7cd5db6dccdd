"""``splat``: the transpose of rendering features, checked against the materialized blending weights
(float64) and the adjoint identity <render(f), v> = <f, splat(v)>."""
from __future__ import annotations

import pytest
import torch

from fourlegs_engine.errors import InputError
from fourlegs_engine.render import RasterOptions, cpu_kernels, rasterize, splat

from _render_helpers import random_scene, view_cameras

GEOM = ("means", "rotations", "log_scales", "opacity_logits")


needs_numba = pytest.mark.skipif(not cpu_kernels.available(), reason="numba is not installed")
PATHS = [pytest.param(RasterOptions(), id="kernel", marks=needs_numba),
         pytest.param(RasterOptions(tile_size=8, chunk=5), id="kernel-tile8", marks=needs_numba),
         pytest.param(RasterOptions(cpu_kernel=False), id="torch"),
         pytest.param(RasterOptions(tile_size=8, chunk=5, cpu_kernel=False), id="torch-tile8-chunk5")]


@pytest.mark.parametrize("cam_index", [0, 3, 4, 5])
@pytest.mark.parametrize("opts", PATHS)
def test_splat_equals_the_weights_transpose(cam_index, opts):
    scene = random_scene(120, seed=3)
    cam = view_cameras(29, 21)[cam_index]           # odd size: tile padding is exercised
    g = torch.Generator().manual_seed(cam_index)
    values = torch.randn(cam.height, cam.width, 5, generator=g, dtype=torch.float64)
    out = splat(*(scene[k] for k in GEOM), cam, values, options=opts)
    w = rasterize(*(scene[k] for k in GEOM), cam, outputs=("weights",), options=opts)["weights"]
    ref = torch.zeros(120, 5, dtype=torch.float64)
    ref.index_add_(0, w.gaussian, w.weight[:, None] * values.reshape(-1, 5)[w.pixel])
    assert out.dtype == torch.float64 and out.shape == (120, 5)
    torch.testing.assert_close(out, ref, rtol=1e-12, atol=1e-12)
    assert ref.abs().sum() > 0


@pytest.mark.parametrize("opts", PATHS)
def test_splat_is_the_adjoint_of_rendering_features(opts):
    scene = random_scene(80, seed=5, channels=3)
    cam = view_cameras(32, 24)[0]
    v = torch.randn(cam.height, cam.width, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    rendered = rasterize(*(scene[k] for k in GEOM), cam, features=scene["features"], outputs=("features",))
    lhs = (rendered["features"] * v).sum()
    rhs = (scene["features"] * splat(*(scene[k] for k in GEOM), cam, v, options=opts)).sum()
    torch.testing.assert_close(lhs, rhs, rtol=1e-12, atol=1e-12)


def test_splat_of_ones_is_the_rendered_weight_per_gaussian_and_float32_stays_close():
    scene = random_scene(60, seed=7, dtype=torch.float32)
    cam = view_cameras(24, 16)[2]
    ones = torch.ones(cam.height, cam.width, 1)
    den = splat(*(scene[k] for k in GEOM), cam, ones)[:, 0]
    alpha = rasterize(*(scene[k] for k in GEOM), cam, outputs=("alpha",))["alpha"]
    assert den.dtype == torch.float32 and torch.all(den >= 0)
    torch.testing.assert_close(den.sum(), alpha.sum(), rtol=1e-5, atol=1e-5)


def test_splat_rejects_bad_pixel_values():
    scene = random_scene(10, seed=0)
    cam = view_cameras(16, 12)[0]
    with pytest.raises(InputError, match="pixel_values"):
        splat(*(scene[k] for k in GEOM), cam, torch.zeros(12, 15, 2))
    bad = torch.zeros(12, 16, 2)
    bad[3, 4, 1] = float("nan")
    with pytest.raises(InputError, match="NaN"):
        splat(*(scene[k] for k in GEOM), cam, bad)


def test_splat_accumulates_into_out_across_views():
    scene = random_scene(50, seed=11)
    cams = view_cameras(20, 14)[:2]
    vals = [torch.randn(14, 20, 3, generator=torch.Generator().manual_seed(i), dtype=torch.float64) for i in range(2)]
    separate = sum(splat(*(scene[k] for k in GEOM), c, v) for c, v in zip(cams, vals))
    acc = torch.zeros(50, 3, dtype=torch.float64)
    for c, v in zip(cams, vals):
        returned = splat(*(scene[k] for k in GEOM), c, v, out=acc)
        assert returned is acc
    torch.testing.assert_close(acc, separate, rtol=1e-12, atol=1e-12)
    with pytest.raises(InputError, match="out"):
        splat(*(scene[k] for k in GEOM), cams[0], vals[0], out=torch.zeros(50, 3))   # float32 != float64


@needs_numba
@pytest.mark.parametrize("tile_size", [4, 16])
def test_fused_kernel_matches_the_torch_path_where_pixels_saturate(tile_size):
    """Many opaque, overlapping Gaussians: most pixels stop early (T < 1e-4), α hits the 0.99 cap, and
    faint fragments fall under 1/255; the fused per-pixel loop must make the same decisions."""
    scene = random_scene(400, seed=21, dtype=torch.float32)
    scene["opacity_logits"] = scene["opacity_logits"] + 6.0          # nearly opaque: α capped, early stops
    cam = view_cameras(37, 23)[1]
    values = torch.rand(cam.height, cam.width, 129, generator=torch.Generator().manual_seed(4))
    kernel = splat(*(scene[k] for k in GEOM), cam, values, options=RasterOptions(tile_size=tile_size))
    reference = splat(*(scene[k] for k in GEOM), cam, values,
                      options=RasterOptions(tile_size=tile_size, cpu_kernel=False))
    alpha = rasterize(*(scene[k] for k in GEOM), cam, outputs=("alpha",))["alpha"]
    assert int((alpha > 0.999).sum()) >= 20                          # many pixels saturate and stop early
    assert torch.all(torch.isfinite(kernel))
    torch.testing.assert_close(kernel, reference, rtol=1e-4, atol=1e-4)
    assert float(reference.abs().sum()) > 1.0


from hypothesis import given, settings, strategies as st  # noqa: E402


@needs_numba
@settings(max_examples=15, deadline=None)
@given(n=st.integers(0, 40), seed=st.integers(0, 10_000), log_scale=st.floats(-9.0, 1.0),
       opacity_shift=st.floats(-8.0, 12.0), cam_index=st.integers(0, 5), tile_size=st.sampled_from([1, 4, 16]))
def test_fused_kernels_agree_with_the_torch_path_on_random_scenes(n, seed, log_scale, opacity_shift, cam_index,
                                                                  tile_size):
    """Property: blending and splat through the fused kernels equal the torch path (float64) for any
    scene size (incl. empty), sub-pixel to screen-filling Gaussians, transparent to saturating opacity,
    cameras inside the cloud or cutting it with the near plane, and every tile size."""
    scene = random_scene(n, seed, channels=3, log_scale=log_scale)
    scene["opacity_logits"] = scene["opacity_logits"] + opacity_shift
    cam = view_cameras(21, 13)[cam_index]
    geom = [scene[k] for k in GEOM]
    fused, torch_path = RasterOptions(tile_size=tile_size), RasterOptions(tile_size=tile_size, cpu_kernel=False)
    outs = ("rgb", "features", "depth", "alpha")
    with torch.no_grad():
        a = rasterize(*geom, cam, colors=scene["colors"], features=scene["features"], outputs=outs, options=fused)
        b = rasterize(*geom, cam, colors=scene["colors"], features=scene["features"], outputs=outs,
                      options=torch_path)
    for name in outs:
        assert torch.isfinite(a[name]).all()
        torch.testing.assert_close(a[name], b[name], rtol=1e-9, atol=1e-9, msg=name)
    values = torch.randn(cam.height, cam.width, 2, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    torch.testing.assert_close(splat(*geom, cam, values, options=fused), splat(*geom, cam, values, options=torch_path),
                               rtol=1e-9, atol=1e-9)


@needs_numba
def test_blending_kernel_workers_follow_kernel_threads_not_torch_threads(monkeypatch):
    """kernel_threads sets the fused blend's workers independently of torch's threads; the image does
    not depend on the worker count (tiles own disjoint pixels)."""
    from concurrent.futures import ThreadPoolExecutor

    from fourlegs_engine.threads import kernel_thread_count, kernel_threads, torch_threads

    scene = random_scene(3000, seed=5, dtype=torch.float32)
    cam = view_cameras(160, 120)[0]
    pools = []
    real_pool = ThreadPoolExecutor

    def recording_pool(n, *a, **k):
        pools.append(n)
        return real_pool(n, *a, **k)

    monkeypatch.setattr(cpu_kernels, "ThreadPoolExecutor", recording_pool)
    small_tiles = RasterOptions(tile_size=4)  # enough busy tiles for two workers at 160x120
    render = lambda: rasterize(*(scene[k] for k in GEOM), cam, colors=scene["colors"], outputs=("rgb", "alpha"),  # noqa: E731
                               options=small_tiles)
    with torch_threads(1):
        single = render()
        assert pools == [] and kernel_thread_count() == 1
        with kernel_threads(2):
            assert kernel_thread_count() == 2 and torch.get_num_threads() == 1
            double = render()
        assert kernel_thread_count() == 1
    assert pools == [2]
    torch.testing.assert_close(double["rgb"], single["rgb"], rtol=0, atol=0)
    torch.testing.assert_close(double["alpha"], single["alpha"], rtol=0, atol=0)
