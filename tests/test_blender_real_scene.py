"""A scene written by the real fitter, imported through the add-on's operator: points, foreground, scrubbing.

Also what a real calibration and a real-size bundle exposed: nearly square pixels (Blender cannot write a
multilayer EXR with non-square ones) and the loader's whole-file checks (fast float32 quaternion check,
validated pages unmapped from the process).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import _fit_helpers as fh
from _blender_helpers import bl, bpy_addon, tiny_scene  # noqa: F401
from fourlegs_engine.fit import FitOptions, fit_capture
from fourlegs_engine.scene import Camera, CameraRig, GaussianSequence, Scene, write_bundle
from fourlegs_engine.scene.bundle import load_bundle
from fourlegs_engine.scene.gaussians import quaternions_need_normalizing

#: the smallest fit that still runs every stage of the fitter (first timestep with densification, a tracked one)
TINY_FIT = FitOptions(resolution_scale=0.5, first_iterations=3, iterations=1, init_background=300,
                      background_stride=8, voxel=0.1, max_gaussians=800)


@pytest.fixture(scope="module")
def fitted_bundle(tmp_path_factory) -> Path:
    """A 2-timestep bundle written by ``fit_capture`` from the synthetic capture (one torch thread: a
    fraction of the CPU time when the cores are shared)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        capture = fh.write_capture(tmp_path_factory.mktemp("capture"), num_timesteps=2)
        out = tmp_path_factory.mktemp("fit") / "scene"
        fit_capture(capture, out, TINY_FIT, progress=False)
    finally:
        torch.set_num_threads(threads)
    return out


def _positions(mesh) -> np.ndarray:
    co = np.empty(len(mesh.vertices) * 3, np.float32)
    mesh.vertices.foreach_get("co", co)
    return co.reshape(-1, 3)


def _evaluated_positions(bpy, obj) -> np.ndarray:
    geometry = obj.evaluated_get(bpy.context.evaluated_depsgraph_get()).evaluated_geometry()
    cloud = geometry.pointcloud
    out = np.empty(len(cloud.points) * 3, np.float32)
    cloud.attributes["position"].data.foreach_get("vector", out)
    return out.reshape(-1, 3)


@pytest.mark.blender
def test_fitted_scene_imports_through_the_operator_and_scrubs_to_each_timestep(bl, fitted_bundle):
    from fourlegs_addon import importer, keyframes

    means = np.load(fitted_bundle / "means.npy")
    foreground = np.load(fitted_bundle / "foreground.npy")
    T, N = means.shape[:2]
    assert T == 2 and 0 < foreground.sum() < N  # the fitter marked some Gaussians foreground, not all
    moved = np.abs(means[1] - means[0]).max(axis=1)
    assert moved[foreground].max() > 1e-3 and moved[~foreground].max() == 0.0  # fg tracked, bg held still

    assert bl.ops.fourlegs.import_scene(filepath=str(fitted_bundle)) == {"FINISHED"}
    scene = bl.context.scene
    obj = scene.fourlegs.splat_object
    mesh = obj.data
    assert len(mesh.vertices) == N and scene.fourlegs.num_timesteps == T
    np.testing.assert_array_equal(_positions(mesh), means[0])
    flag = np.empty(N, bool)
    mesh.attributes[importer.FOREGROUND_ATTR].data.foreach_get("value", flag)
    np.testing.assert_array_equal(flag, foreground)
    for name in (importer.RADIUS_ATTR, importer.OPACITY_ATTR, importer.RGB_ATTR):
        assert name in mesh.attributes
    assert len([o for o in scene.objects if o.type == "CAMERA"]) == 9  # 8 training + 1 test camera

    # the import keys the scene time so the timeline plays the capture: frame f shows timestep f - 1
    assert keyframes.keyed_frames(scene, keyframes.TIMESTEP_PATH) == [1.0, float(T)]
    scene.frame_set(2)
    assert scene.fourlegs.timestep == pytest.approx(1.0)
    np.testing.assert_array_equal(_positions(mesh), means[1])
    np.testing.assert_array_equal(_evaluated_positions(bl, obj), means[1])  # the point instances follow
    scene.frame_set(1)
    np.testing.assert_array_equal(_evaluated_positions(bl, obj), means[0])


@pytest.mark.blender
def test_bench_real_scene_measures_the_fitted_scene(bpy_addon, fitted_bundle):
    from fourlegs_bench.blender import bench_real_scene

    result = bench_real_scene(str(fitted_bundle), viewport_frames=1, viewport_size=(64, 48))
    means = np.load(fitted_bundle / "means.npy", mmap_mode="r")
    assert (result["timesteps"], result["gaussians"]) == means.shape[:2]
    scrub = result["scrub"]
    assert scrub["frames"] == means.shape[0] and scrub["max_abs_position_error"] == 0.0
    assert 0 < scrub["median_s"] <= scrub["max_s"] and result["import"]["import_s"] > 0
    assert scrub["with_relevancy_median_s"] > 0 and scrub["fractional_median_s"] > 0
    draw = result["viewport"]["draws"][0]
    assert result["viewport"]["image"] == [64, 48] and 0.05 < draw["coverage"] <= 1.0  # the scene is in view


def _scene_with_focals(fx: float, fy: float):
    scene = tiny_scene(T=2, N=32)
    cam = scene.cameras.cameras(0, "train")[0]
    K = cam.K.copy()
    K[0, 0], K[1, 1] = fx, fy
    cam = Camera(K=K, w2c=cam.w2c, width=cam.width, height=cam.height, near=cam.near, far=cam.far, name="cal")
    scene.cameras = CameraRig.static([cam], [], 2)
    return scene, cam


@pytest.mark.blender
def test_nearly_square_pixels_become_square_and_a_multilayer_exr_can_be_written(bl, tmp_path):
    """fx/fy = 1.0027, as Panoptic's calibration: the camera keeps sqrt(fx*fy) and the EXR is written."""
    import OpenEXR

    from fourlegs_addon import importer, render_engine, video

    scene, cam = _scene_with_focals(30.08, 30.0)
    importer.import_scene(bl.context.scene, scene)
    bl_scene = bl.context.scene
    assert (bl_scene.render.pixel_aspect_x, bl_scene.render.pixel_aspect_y) == (1.0, 1.0)
    seen = render_engine.scene_camera(bl_scene, bl.context.evaluated_depsgraph_get(), cam.width, cam.height)
    np.testing.assert_allclose(np.diag(seen.K)[:2], math.sqrt(30.08 * 30.0), rtol=1e-5)
    np.testing.assert_allclose(seen.K[:2, 2], cam.K[:2, 2], atol=1e-4)
    bl_scene.render.engine = render_engine.ENGINE_ID
    bl_scene.view_layers[0].use_pass_z = True
    video.configure_output(bl_scene, "EXR")
    bl_scene.render.filepath = str(tmp_path / "frame")
    bl.ops.render.render(write_still=True)
    written = list(tmp_path.glob("frame*.exr"))
    assert len(written) == 1
    channels = {name for part in OpenEXR.File(str(written[0])).parts for name in part.channels}
    assert any("Combined" in name for name in channels) and any("Depth" in name for name in channels), channels


@pytest.mark.blender
def test_anamorphic_pixels_keep_their_aspect(bl):
    from fourlegs_addon import importer, render_engine

    scene, cam = _scene_with_focals(45.0, 30.0)
    importer.import_scene(bl.context.scene, scene)
    bl_scene = bl.context.scene
    assert bl_scene.render.pixel_aspect_y / bl_scene.render.pixel_aspect_x == pytest.approx(1.5)
    seen = render_engine.scene_camera(bl_scene, bl.context.evaluated_depsgraph_get(), cam.width, cam.height)
    np.testing.assert_allclose(np.diag(seen.K)[:2], [45.0, 30.0], rtol=1e-5)


@pytest.mark.parametrize("norm, needs", [(1.0, False), (1.0009, False), (0.9991, False), (1.0011, True),
                                         (0.9989, True), (0.0, True), (1e20, True), (math.nan, True)])
def test_quaternion_check_at_the_tolerance_edges(norm, needs):
    q = np.zeros((3, 5, 4), np.float32)
    q[..., 0] = 1.0
    q[2, 4] = np.float32([0.5, 0.5, 0.5, 0.5]) * np.float32(norm)  # one quaternion of the last timestep
    assert quaternions_need_normalizing(q) is needs


def test_quaternion_check_of_no_timesteps_is_false():
    assert quaternions_need_normalizing(np.zeros((0, 5, 4), np.float32)) is False


@settings(max_examples=60, deadline=None)
@given(hnp.arrays(np.float32, hnp.array_shapes(min_dims=2, max_dims=3, min_side=1, max_side=6).map(lambda s: s + (4,)),
                  elements=st.floats(-3.0, 3.0, width=32)),
       st.floats(0.0, 2.0))
def test_quaternion_check_matches_the_float64_norms(q, scale):
    """The float32 squared-norm check answers as the float64 norm |‖q‖ - 1| > 1e-3 would."""
    q = q * np.float32(scale)
    norms = np.linalg.norm(q.astype(np.float64), axis=-1)
    assume(np.abs(np.abs(norms - 1.0) - 1e-3).min() > 1e-5)  # not on the tolerance itself
    assert quaternions_need_normalizing(q) is bool((np.abs(norms - 1.0) > 1e-3).any())


def _resident_file_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("RssFile:"):
            return int(line.split()[1]) / 1024.0
    raise AssertionError("no RssFile line")


LINUX_PROC = pytest.mark.skipif(not Path("/proc/self/status").is_file(),
                                reason="resident memory is read from /proc (Linux)")


@pytest.fixture(scope="module")
def long_bundle(tmp_path_factory) -> Path:
    """64 timesteps x 40,000 Gaussians: means 30 MB + rotations 41 MB on disk."""
    T, N = 64, 40_000
    rng = np.random.default_rng(0)
    means = rng.standard_normal((T, N, 3), dtype=np.float32)
    rotations = rng.standard_normal((T, N, 4), dtype=np.float32)
    rotations /= np.linalg.norm(rotations, axis=-1, keepdims=True)
    g = GaussianSequence(means=means, rotations=rotations, log_scales=np.full((N, 3), -3.0, np.float32),
                         opacity_logits=np.zeros(N, np.float32), colors=np.full((N, 3), 0.5, np.float32))
    return write_bundle(Scene(gaussians=g, cameras=CameraRig(), name="long"), tmp_path_factory.mktemp("long") / "b")


@LINUX_PROC
def test_loading_a_long_bundle_leaves_its_validated_timesteps_unmapped(long_bundle):
    """Loading reads every timestep (finite values, unit quaternions); those pages do not stay resident."""
    before = _resident_file_mb()
    loaded = load_bundle(long_bundle)
    grown = _resident_file_mb() - before
    assert grown < 16.0, f"{grown:.0f} MB of the 71 MB bundle stayed resident after loading"
    expected_last = np.fromfile(long_bundle / "means.npy", np.float32)[-40_000 * 3:].reshape(-1, 3)
    np.testing.assert_array_equal(loaded.gaussians.means[-1], expected_last)  # still readable after unmapping


@LINUX_PROC
@pytest.mark.blender
def test_scrubbing_every_timestep_does_not_keep_them_all_resident(bl, long_bundle, monkeypatch):
    from fourlegs_addon import importer

    monkeypatch.setattr(importer, "RELEASE_EVERY_BYTES", 4 << 20)  # unmapped every 4 MB of the 30 MB read

    assert bl.ops.fourlegs.import_scene(filepath=str(long_bundle)) == {"FINISHED"}
    scene = bl.context.scene
    obj = scene.fourlegs.splat_object
    means = importer.engine_scene_for(obj).gaussians.means
    before = _resident_file_mb()
    for t in range(means.shape[0]):
        scene.fourlegs.timestep = float(t)
    grown = _resident_file_mb() - before
    assert grown < 8.0, f"{grown:.0f} MB of the 30 MB of means stayed resident after scrubbing"
    np.testing.assert_array_equal(_positions(obj.data), means[-1])


@LINUX_PROC
@pytest.mark.blender
def test_rendering_every_timestep_does_not_keep_them_all_resident(bl, long_bundle, monkeypatch):
    """The render engine reads means and rotations per frame (71 MB over the 64 timesteps); a long
    render must not keep them all resident."""
    from fourlegs_addon import importer, render_engine

    monkeypatch.setattr(importer, "RELEASE_EVERY_BYTES", 4 << 20)

    assert bl.ops.fourlegs.import_scene(filepath=str(long_bundle)) == {"FINISHED"}
    scene = bl.context.scene
    g = importer.engine_scene_for(scene.fourlegs.splat_object).gaussians
    before = _resident_file_mb()
    for t in range(g.num_timesteps):
        part = render_engine.gather_gaussians(scene, float(t), with_relevancy=False)
        assert np.isfinite(part["means"]).all() and np.isfinite(part["rotations"]).all()  # read, as a render does
    grown = _resident_file_mb() - before
    assert grown < 8.0, f"{grown:.0f} MB of the 71 MB of means and rotations stayed resident after rendering"
    np.testing.assert_array_equal(part["means"], g.means[-1])
    np.testing.assert_array_equal(part["rotations"], g.rotations[-1])


@pytest.mark.blender
@settings(max_examples=40, deadline=None)
@given(hnp.arrays(np.float32, st.integers(1, 300), elements=st.floats(-0.5, 1.5, width=32) | st.just(math.nan)))
def test_heat_table_matches_the_heat_ramp(bpy_addon, values):
    """The per-frame heat colours (a table lookup) are the heat ramp's to well under one 8-bit level."""
    from fourlegs_addon import importer, mesh_splats

    direct = mesh_splats.rgba(importer.heat_rgb(values))
    looked_up = importer.heat_rgba(values)
    assert looked_up.shape == (len(values), 4) and looked_up.dtype == np.float32
    np.testing.assert_allclose(looked_up, direct, atol=1e-3)
    np.testing.assert_array_equal(importer.heat_rgba(np.float32([0.0, 1.0])),
                                  mesh_splats.rgba(importer.heat_rgb(np.float32([0.0, 1.0]))))
