"""What the add-on tells the user: one line without PyTorch (what to install, where), the panel's own
words (Prepare, the Overwrite checkbox), and loose PLY files imported the way an editor expects."""
from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from _blender_helpers import bl, bpy_addon, hand_plan, tiny_scene  # noqa: F401

pytestmark = pytest.mark.blender
HAS_TORCH = importlib.util.find_spec("torch") is not None
no_torch = pytest.mark.skipif(HAS_TORCH, reason="PyTorch is installed here (the bpy 5.3 job runs without it)")
with_torch = pytest.mark.skipif(not HAS_TORCH, reason="needs PyTorch")


def _one_line(bl, capfd, operator, **kw) -> str:
    """Run ``operator``: it must fail with one line naming what to install and where, no traceback, and
    leave that same line (without a nested "Error:") in the panel's status."""
    with pytest.raises(RuntimeError) as err:
        operator(**kw)
    printed = capfd.readouterr()
    message = str(err.value)
    assert "Traceback" not in printed.out + printed.err and "\n" not in message.strip()
    assert "torch is missing" in message and "Preferences > Add-ons > 4-LEGS Highlights" in message
    status = bl.context.scene.fourlegs.status
    assert status.startswith("error: torch is missing") and "Error" not in status and not bl.context.scene.fourlegs.running
    return message


@no_torch
def test_without_torch_every_operator_says_in_one_line_what_to_install(bl, tmp_path, capfd):
    from fourlegs_addon import highlight_ops, importer
    from fourlegs_engine.scene import write_bundle

    write_bundle(tiny_scene(T=3, N=32), tmp_path / "a")
    write_bundle(tiny_scene(T=3, N=32, seed=1), tmp_path / "b")
    for name in ("a", "b"):
        assert bl.ops.fourlegs.import_scene(filepath=str(tmp_path / name / "scene.json")) == {"FINISHED"}
    props = bl.context.scene.fourlegs
    props.query = "the cube"
    _one_line(bl, capfd, bl.ops.fourlegs.run_query)
    _one_line(bl, capfd, bl.ops.fourlegs.prepare_field)
    _one_line(bl, capfd, bl.ops.fourlegs.find_best_scene)
    _one_line(bl, capfd, bl.ops.fourlegs.generate_highlight)  # planning from the query needs the field
    props.renderer = "FOURLEGS"
    highlight_ops.generate_highlight(bl.context.scene, hand_plan(desaturate=False))
    props.output_path = str(tmp_path / "clip.mp4")
    _one_line(bl, capfd, bl.ops.fourlegs.render_video)
    # F12 with the 4-LEGS engine: Blender's own error line, naming what to install, once
    with pytest.raises(RuntimeError, match="torch is missing.*Install PyTorch") as err:
        bl.ops.render.render()
    assert str(err.value).count("Error") == 1
    assert importer.splat_objects(bl.context.scene)


@with_torch
def test_run_query_before_a_field_exists_says_press_prepare(bl):
    from fourlegs_addon import importer

    importer.import_scene(bl.context.scene, tiny_scene())
    bl.context.scene.fourlegs.query = "the cube"
    with pytest.raises(RuntimeError, match="press Prepare Language Field") as err:
        bl.ops.fourlegs.run_query()
    assert "`fourlegs" not in str(err.value)


def test_an_existing_output_names_the_panels_overwrite_checkbox(bl, tmp_path):
    from fourlegs_addon import highlight_ops, importer

    importer.import_scene(bl.context.scene, tiny_scene())
    highlight_ops.generate_highlight(bl.context.scene, hand_plan(desaturate=False))
    scene = bl.context.scene
    scene.render.engine = "CYCLES"
    (tmp_path / "clip.mp4").write_bytes(b"an earlier video")
    scene.fourlegs.output_path = str(tmp_path / "clip.mp4")
    with pytest.raises(RuntimeError, match="tick Overwrite") as err:
        bl.ops.fourlegs.render_video()
    assert "--overwrite" not in str(err.value) and (tmp_path / "clip.mp4").read_bytes() == b"an earlier video"


@with_torch
def test_a_z_pass_holds_depth_on_every_frame(bl):
    from fourlegs_addon import highlight_ops, importer, render_engine

    scene = bl.context.scene
    scene.fourlegs.renderer = "FOURLEGS"
    importer.import_scene(scene, tiny_scene())
    plan = hand_plan(desaturate=False)
    plan["passes"]["depth"] = [[7, 12]]  # the plan asks depth of the orbit only
    highlight_ops.generate_highlight(scene, plan)
    assert scene.view_layers[0].use_pass_z
    for frame in (2, 9):
        scene.frame_set(frame)
        r = scene.render
        out = render_engine.render_arrays(scene, bl.context.evaluated_depsgraph_get(), r.resolution_x,
                                          r.resolution_y, frame=frame, relevancy_pass=False,
                                          depth=render_engine.depth_wanted(scene, scene.view_layers[0], frame))
        hit = out["rgba"][..., :3].max(axis=-1) > 0.05
        assert hit.any() and np.all(out["depth"][hit] < 100.0), frame


def test_a_loose_ply_gets_a_camera_that_sees_it_and_a_renderer_that_draws_it(bl, tmp_path):
    from fourlegs_addon import native_render, render_engine
    from fourlegs_engine.scene.ply import write_ply_scene

    scene = tiny_scene(T=1, N=300)
    path = write_ply_scene(scene, tmp_path / "loose.ply")
    assert bl.ops.fourlegs.import_scene(filepath=str(path), with_cameras=False) == {"FINISHED"}
    bl_scene = bl.context.scene
    cam = bl_scene.camera
    assert cam is not None
    from fourlegs_addon import convert
    from fourlegs_engine.scene import Camera

    c2w = convert.blender_to_opencv_c2w(np.array(cam.matrix_world))
    K = convert.camera_intrinsics(cam.data.lens, cam.data.sensor_width, cam.data.sensor_height, cam.data.sensor_fit,
                                  bl_scene.render.resolution_x, bl_scene.render.resolution_y)
    view = Camera(K=K, w2c=convert.rigid_inverse(c2w), width=bl_scene.render.resolution_x,
                  height=bl_scene.render.resolution_y)
    uv, z = view.project(np.asarray(scene.gaussians.means[0]))
    inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < view.width) & (uv[:, 1] >= 0) & (uv[:, 1] < view.height)
    assert inside.mean() > 0.95
    engine = bl_scene.render.engine
    assert engine in native_render.NATIVE_ENGINES if bl.app.version >= (5, 3, 0) else engine == render_engine.ENGINE_ID


def test_one_file_of_a_ply_sequence_imports_the_sequence_with_its_extra_properties(bl, tmp_path):
    import plyfile

    from fourlegs_addon import importer, native_splats
    from fourlegs_engine.scene.ply import write_ply_scene

    folder = write_ply_scene(tiny_scene(T=4, N=40), tmp_path / "seq")
    files = sorted(folder.glob("*.ply"))
    assert len(files) == 4
    first = plyfile.PlyData.read(str(files[0]))["vertex"].data
    table = np.empty(len(first), dtype=first.dtype.descr + [("label", "f4")])
    for name in first.dtype.names:
        table[name] = first[name]
    table["label"] = np.arange(len(first)) % 5
    plyfile.PlyData([plyfile.PlyElement.describe(table, "vertex")]).write(str(files[0]))
    assert bl.ops.fourlegs.import_scene(filepath=str(files[2])) == {"FINISHED"}
    obj = bl.context.scene.fourlegs.splat_object
    assert importer.engine_scene_for(obj).num_timesteps == 4 and bl.context.scene.fourlegs.num_timesteps == 4
    np.testing.assert_array_equal(native_splats.read_attribute(obj.data, "label")[:, 0], np.arange(40) % 5)
    bl.ops.wm.read_factory_settings(use_empty=True)
    assert bl.ops.fourlegs.import_scene(filepath=str(files[2]), sequence=False) == {"FINISHED"}
    assert bl.context.scene.fourlegs.num_timesteps == 1
