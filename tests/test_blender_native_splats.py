"""Blender 5.3+: the 4D scene as Blender's own Gaussian splats, and highlights rendered by EEVEE and Cycles.

Runs on bpy 5.3 (the Python 3.13 job, without PyTorch); skipped on older bpy. The attribute conventions
are Blender's own: a PLY read by ``bpy.ops.wm.ply_import`` is the reference for what the add-on writes.
"""
from __future__ import annotations

import math
import shutil

import numpy as np
import pytest

from _blender_helpers import bl, bpy_addon, tiny_scene  # noqa: F401

pytestmark = pytest.mark.blender
bpy = pytest.importorskip("bpy")
if bpy.app.version < (5, 3, 0):
    pytest.skip("native Gaussian splats need Blender 5.3", allow_module_level=True)

QUERY = "a ball flying in the air"


def _attributes(data) -> dict[str, np.ndarray]:
    from fourlegs_addon import native_splats

    return {a.name: native_splats.read_attribute(data, a.name) for a in data.attributes
            if not a.name.startswith(".") and a.name != native_splats.INDEX_ATTR}


def _sh_scene(degree: int):
    """tiny_scene with random SH of ``degree`` (no RGB colours), random rotations, scales and opacities."""
    scene = tiny_scene(T=1, N=50, seed=3)
    g = scene.gaussians
    rng = np.random.default_rng(degree)
    g.sh = rng.normal(0.0, 0.5, (g.num_gaussians, (degree + 1) ** 2, 3)).astype(np.float32)
    g.colors = None
    g.rotations = rng.normal(size=g.rotations.shape).astype(np.float32) * 3.0  # not unit length in the file
    g.log_scales = rng.uniform(-4.0, -1.0, g.log_scales.shape).astype(np.float32)
    g.opacity_logits = rng.normal(0.0, 2.0, g.num_gaussians).astype(np.float32)
    return scene


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_native_splats_match_blenders_own_ply_importer(bl, tmp_path, degree):
    """The same Gaussians through Blender's importer and through the add-on: the same attributes, values
    equal to float32 rounding (opacity as sigmoid, scales linear, rotations unit, SH per coefficient)."""
    from fourlegs_addon import native_splats
    from fourlegs_engine.scene.ply import write_ply_scene

    scene = _sh_scene(degree)
    path = write_ply_scene(scene, tmp_path / "splats.ply")
    assert bl.ops.wm.ply_import(filepath=str(path)) == {"FINISHED"}
    reference = bl.data.objects["splats"].data
    assert reference.type == "GAUSSIAN_SPLAT"
    ours = native_splats.create_object("ours", scene.gaussians).data
    assert ours.type == "GAUSSIAN_SPLAT"
    want, got = _attributes(reference), _attributes(ours)
    assert sorted(got) == sorted(want)
    assert len([n for n in want if n.startswith("radiance:sh_")]) == (degree + 1) ** 2 - 1
    for name in want:
        assert reference.attributes[name].data_type == ours.attributes[name].data_type, name
        np.testing.assert_allclose(got[name], want[name], rtol=2e-6, atol=2e-6, err_msg=name)
    g = scene.gaussians
    np.testing.assert_allclose(got["radiance:base"][:, 3], 1 / (1 + np.exp(-g.opacity_logits)), rtol=1e-6)
    np.testing.assert_allclose(got["scale"], np.exp(g.log_scales), rtol=1e-6)


def test_a_static_ply_goes_through_blenders_importer_and_keeps_extra_properties(bl, tmp_path):
    """Import 4D Scene of one PLY file: Blender's own importer reads it (a point attribute per extra
    property, e.g. a label), the object is the panel's scene and a view camera sees it."""
    import plyfile

    from fourlegs_addon import importer
    from fourlegs_engine.scene.ply import write_ply_scene

    path = write_ply_scene(_sh_scene(1), tmp_path / "static.ply")
    vertex = plyfile.PlyData.read(str(path))["vertex"].data
    labels = np.arange(len(vertex), dtype=np.float32) % 3
    table = np.empty(len(vertex), dtype=vertex.dtype.descr + [("segment", "f4")])
    for name in vertex.dtype.names:
        table[name] = vertex[name]
    table["segment"] = labels
    plyfile.PlyData([plyfile.PlyElement.describe(table, "vertex")]).write(str(path))
    assert bl.ops.fourlegs.import_scene(filepath=str(path)) == {"FINISHED"}
    obj = bl.context.scene.fourlegs.splat_object
    assert obj.type == "POINTCLOUD" and obj.data.type == "GAUSSIAN_SPLAT"
    np.testing.assert_array_equal(_attributes(obj.data)["segment"][:, 0], labels)
    assert importer.source_key(obj) == str(path.resolve())
    assert bl.context.scene.camera is not None  # a scene without cameras gets one that sees it
    assert bl.context.scene.render.engine in ("BLENDER_EEVEE", "CYCLES")


def test_a_bundle_imports_as_gaussian_splats_that_follow_the_timeline_and_keep_deletions(bl, tmp_path):
    from fourlegs_addon import importer, native_splats
    from fourlegs_engine.scene import write_bundle

    scene = tiny_scene(T=4, N=64)
    write_bundle(scene, tmp_path / "b")
    assert bl.ops.fourlegs.import_scene(filepath=str(tmp_path / "b" / "scene.json")) == {"FINISHED"}
    obj = bl.context.scene.fourlegs.splat_object
    assert obj.type == "POINTCLOUD" and obj.data.type == "GAUSSIAN_SPLAT"
    g = scene.gaussians
    for frame in (1, 3, 4):
        bl.context.scene.frame_set(frame)  # frame f shows timestep f - 1
        np.testing.assert_allclose(native_splats.read_attribute(obj.data, "position"), g.means[frame - 1], atol=1e-6)
        base = native_splats.read_attribute(obj.data, "radiance:base")
        np.testing.assert_allclose(0.5 + base[:, :3] * 0.28209479177387814, g.colors[frame - 1], atol=1e-5)
    # an editor deletes every other point (edit mode, Delete): the rest keep following their Gaussians
    bl.context.view_layer.objects.active = obj
    bl.ops.object.mode_set(mode="EDIT")
    selection = obj.data.attributes.get(".selection") or obj.data.attributes.new(".selection", "BOOLEAN", "POINT")
    selection.data.foreach_set("value", np.arange(64) % 2 == 1)
    bl.ops.pointcloud.delete()
    bl.ops.object.mode_set(mode="OBJECT")
    assert len(obj.data.points) == 32
    bl.context.scene.frame_set(2)
    np.testing.assert_allclose(native_splats.read_attribute(obj.data, "position"), g.means[1][::2], atol=1e-6)
    np.testing.assert_array_equal(importer.kept_indices(obj, 64), np.arange(0, 64, 2))


def test_the_demo_scene_imports_as_gaussian_splats_that_move_with_the_timeline(bl):
    """The --demo scene (30k Gaussians, 48 timesteps) through Import 4D Scene: one GAUSSIAN_SPLAT point
    cloud whose positions are those of the timestep each frame shows."""
    from fourlegs_addon import importer, native_splats
    from fourlegs_engine.demo.synthetic import ensure_demo_bundle

    path = ensure_demo_bundle("demo")
    assert bl.ops.fourlegs.import_scene(filepath=str(path / "scene.json")) == {"FINISHED"}
    obj = bl.context.scene.fourlegs.splat_object
    assert obj.type == "POINTCLOUD" and obj.data.type == "GAUSSIAN_SPLAT" and len(obj.data.points) == 30_000
    g = importer.engine_scene_for(obj).gaussians
    moved = []
    for frame in (1, 34, 48):
        bl.context.scene.frame_set(frame)
        pos = native_splats.read_attribute(obj.data, "position")
        np.testing.assert_array_equal(pos, np.asarray(g.means[frame - 1], np.float32))
        moved.append(pos)
    assert np.abs(moved[1] - moved[0]).max() > 0.1  # the people and the ball move


# ----------------------------------------------------------------------------- highlight by EEVEE / Cycles
def desaturate_plan(camera, t: int, width: int, height: int, centre) -> dict:
    """Two frames at timestep ``t`` from ``camera``: frame 1 desaturated (weight 1), frame 2 not."""
    key = {"frame": 1, "c2w": camera.c2w.tolist(), "focal_px": float(camera.fx) * width / camera.width,
           "sensor_width_mm": 36.0, "lens_mm": float(camera.fx) * 36.0 / camera.width}
    return {"format": "fourlegs-highlight-plan", "version": 1,
            "scene": {"name": "demo", "path": None, "num_timesteps": 12, "fps": 30.0}, "query": QUERY,
            "localization": {"found": True, "message": "", "segment": [t, t], "peak": t, "segments": [[t, t]],
                             "scores": [], "action_centre": list(map(float, centre)), "best_view": camera.name},
            "fps": 24, "resolution": [width, height], "frame_start": 1, "frame_end": 2,
            "shots": [{"name": "replay", "effect": "desaturate_background", "frame_start": 1, "frame_end": 2,
                       "camera_keys": [key, dict(key, frame=2)],
                       "time_keys": [{"frame": 1, "timestep": float(t)}, {"frame": 2, "timestep": float(t)}],
                       "interpolation": "linear", "params": {}}],
            "passes": {"rgb": [[1, 2]], "relevancy": [[1, 1]]},
            "desaturate": {"ranges": [[1, 1]], "fade_in": 0, "fade_out": 0, "strength": 1.0,
                           "weights": {"1": 1.0, "2": 0.0}},
            "messages": []}


@pytest.fixture(scope="module")
def ball_scene(tmp_path_factory):
    """The synthetic scene (tiny size: the same generator as the demo) copied, with the ball's relevancy at
    timestep 8 stored beside it as a query engine would have stored it (1 on the ball, 0 elsewhere)."""
    from fourlegs_addon import relevancy_store
    from fourlegs_engine.scene import load_scene
    from fourlegs_engine.demo.synthetic import ensure_demo_bundle

    path = tmp_path_factory.mktemp("native") / "scene"
    shutil.copytree(ensure_demo_bundle("tiny"), path)
    scene = load_scene(path)
    ball = scene.gaussians.labels[8] == scene.metadata["labels"].index("ball flying in the air")
    assert ball.sum() > 20
    relevancy_store.save(scene, QUERY, 8, ball.astype(np.float32))
    return path, ball


def _saturation(rgb: np.ndarray) -> np.ndarray:
    return rgb.max(axis=-1) - rgb.min(axis=-1)


@pytest.mark.parametrize("engine", ["CYCLES", "BLENDER_EEVEE"])
def test_a_highlight_frame_rendered_by_blender_keeps_the_ball_in_colour(bl, ball_scene, tmp_path, engine):
    """Generate Highlight with the EEVEE/Cycles renderer: the relevancy mask is a view layer Blender
    renders (relevancy attribute -> material -> AOV -> compositor), with no PyTorch in this process; the
    desaturated frame is grey except on the ball. Cycles also renders the next frame (weight 0) in colour;
    EEVEE (a software OpenGL without a GPU: minutes per sample) renders the desaturated frame only."""
    from fourlegs_addon import highlight_ops, importer, native_render

    path, ball = ball_scene
    assert bl.ops.fourlegs.import_scene(filepath=str(path / "scene.json")) == {"FINISHED"}
    scene = bl.context.scene
    obj = scene.fourlegs.splat_object
    src = importer.engine_scene_for(obj)
    width, height = (160, 90) if engine == "CYCLES" else (96, 54)
    camera = src.cameras.find("cam01", 8)
    centre = np.asarray(src.gaussians.means[8])[ball].mean(axis=0)
    assert scene.fourlegs.renderer == "NATIVE"
    importer.show_relevancy(obj, True)  # Run Query showed the heat map: Generate goes back to the radiance
    assert len(obj.data.materials) == 1
    highlight_ops.generate_highlight(scene, desaturate_plan(camera, 8, width, height, centre))
    assert len(obj.data.materials) == 0
    assert native_render.LAYER_NAME in scene.view_layers and scene.render.engine == "BLENDER_EEVEE"
    scene.render.engine = engine
    scene.cycles.samples, scene.eevee.taa_render_samples = 8, 1
    images = []
    for frame in (1, 2) if engine == "CYCLES" else (1,):
        scene.frame_set(frame)
        scene.render.filepath = str(tmp_path / f"{engine}_{frame}.png")
        assert bl.ops.render.render(write_still=True) == {"FINISHED"}
        img = bl.data.images.load(scene.render.filepath)
        images.append(np.array(img.pixels[:], np.float32).reshape(height, width, 4)[::-1, :, :3])
    assert native_splats_relevancy(obj).max() == 1.0
    uv, z = camera.scaled(width / camera.width).project(np.asarray(src.gaussians.means[8])[ball])
    inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)
    on_ball = np.zeros((height, width), bool)
    on_ball[uv[inside, 1].astype(int), uv[inside, 0].astype(int)] = True
    assert on_ball.sum() >= 4
    near = np.zeros_like(on_ball)
    ys, xs = np.nonzero(on_ball)
    near[max(ys.min() - 6, 0):ys.max() + 7, max(xs.min() - 6, 0):xs.max() + 7] = True
    background = ~near
    desaturated = images[0]
    assert _saturation(desaturated)[background].mean() < 0.01  # grey everywhere but near the ball ...
    assert _saturation(desaturated)[on_ball].mean() > 0.15  # ... which keeps its orange
    assert desaturated[on_ball][:, 0].mean() > desaturated[on_ball][:, 2].mean() + 0.1
    if len(images) == 2:
        coloured = images[1]
        assert _saturation(coloured)[background].mean() > 0.08  # the scene has colour the highlight takes away
        np.testing.assert_allclose(desaturated[on_ball].mean(axis=0), coloured[on_ball].mean(axis=0), atol=0.1)


def native_splats_relevancy(obj) -> np.ndarray:
    from fourlegs_addon import native_splats

    return native_splats.read_attribute(obj.data, native_splats.RELEVANCY_ATTR)[:, 0]


def blur_plan(camera, t: int, width: int, height: int, centre) -> dict:
    """The desaturation plan's two frames with the background blurred instead (weight 1, then 0)."""
    plan = desaturate_plan(camera, t, width, height, centre)
    plan["shots"][0]["effect"] = "blur_background"
    plan["blur"] = dict(plan.pop("desaturate"), radius=0.06)
    plan["desaturate"] = None
    return plan


def test_cycles_blurs_the_background_around_the_ball(bl, ball_scene, tmp_path):
    """The blur through the EEVEE/Cycles path: the same relevancy view layer and AOV mask the compositor's
    blur; the blurred frame loses the background's fine detail and keeps the ball's."""
    from fourlegs_addon import compositor, highlight_ops, importer, native_render

    path, ball = ball_scene
    assert bl.ops.fourlegs.import_scene(filepath=str(path / "scene.json")) == {"FINISHED"}
    scene = bl.context.scene
    obj = scene.fourlegs.splat_object
    src = importer.engine_scene_for(obj)
    width, height = 160, 90
    camera = src.cameras.find("cam01", 8)
    centre = np.asarray(src.gaussians.means[8])[ball].mean(axis=0)
    highlight_ops.generate_highlight(scene, blur_plan(camera, 8, width, height, centre))
    assert native_render.LAYER_NAME in scene.view_layers and compositor.has_masking(scene)
    scene.render.engine = "CYCLES"
    scene.cycles.samples = 8
    images = []
    for frame in (1, 2):
        scene.frame_set(frame)
        scene.render.filepath = str(tmp_path / f"blur_{frame}.png")
        assert bl.ops.render.render(write_still=True) == {"FINISHED"}
        img = bl.data.images.load(scene.render.filepath)
        images.append(np.array(img.pixels[:], np.float32).reshape(height, width, 4)[::-1, :, :3])
    uv, z = camera.scaled(width / camera.width).project(np.asarray(src.gaussians.means[8])[ball])
    inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)
    on_ball = np.zeros((height, width), bool)
    on_ball[uv[inside, 1].astype(int), uv[inside, 0].astype(int)] = True
    ys, xs = np.nonzero(on_ball)
    near = np.zeros_like(on_ball)
    near[max(ys.min() - 8, 0):ys.max() + 9, max(xs.min() - 8, 0):xs.max() + 9] = True

    def detail(img):   # |horizontal + vertical differences| per pixel
        grey = img.mean(axis=-1)
        d = np.zeros_like(grey)
        d[:, 1:] += np.abs(np.diff(grey, axis=1))
        d[1:] += np.abs(np.diff(grey, axis=0))
        return d

    blurred, sharp = images
    # the background is blurred (the synthetic scene's large splats are smooth already: a third of its
    # pixel-to-pixel detail goes), the picture changes there, and the ball keeps its colour
    assert detail(blurred)[~near].mean() < 0.8 * detail(sharp)[~near].mean()
    assert np.abs(blurred - sharp)[~near].mean() > 0.01
    np.testing.assert_allclose(blurred[on_ball].mean(axis=0), sharp[on_ball].mean(axis=0), atol=0.08)
