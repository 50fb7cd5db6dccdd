"""The render stage's shortcuts change nothing in the output: the compositor is skipped only where the
plan's desaturation weight is 0, the plan text is parsed once but re-read when edited, the torch
colour conversion matches the float64 formula, and the headless job's thread setting is restored."""
from __future__ import annotations

import numpy as np
import pytest

from _blender_helpers import bl, bpy_addon, hand_plan, tiny_scene  # noqa: F401

pytestmark = pytest.mark.blender


@pytest.fixture
def highlight(bl):
    """Tiny scene + hand-made plan with desaturation over frames 7..12 (fades of 2 frames)."""
    from fourlegs_addon import importer, operators, render_engine

    scene = tiny_scene(N=300)
    obj = importer.import_scene(bl.context.scene, scene)
    importer.set_relevancy_provider(obj, lambda t: (scene.gaussians.means[t][:, 0] < 0.0).astype(np.float32))
    operators.generate_highlight(bl.context.scene, hand_plan(desaturate=True))
    render_engine.reset_stats()
    return bl.context.scene


def _png(bl, path) -> np.ndarray:
    image = bl.data.images.load(str(path), check_existing=False)
    try:
        pixels = np.empty(image.size[0] * image.size[1] * image.channels, np.float32)
        image.pixels.foreach_get(pixels)
        return pixels
    finally:
        bl.data.images.remove(image)


def test_compositor_runs_only_on_desaturated_frames_and_frames_are_unchanged(highlight, bl, tmp_path):
    from fourlegs_addon import compositor, render_engine, video

    scene = highlight
    weights = compositor.frame_weights(render_engine.plan_of(scene))
    assert video.compositing_frames(scene) == {f for f, w in weights.items() if w > 0}
    assert video.compositing_frames(scene) == set(range(7, 13))  # frames 1..6 skip the compositor

    skipped = video.render_frames(scene, tmp_path / "skipped")
    assert scene.render.use_compositing  # restored after the loop
    # reference: the compositor forced on every frame (what the renderer did before the shortcut)
    scene.render.image_settings.compression = 15
    video.configure_output(scene, "PNG")
    for frame, path in zip(range(scene.frame_start, scene.frame_end + 1), skipped):
        scene.frame_set(frame)
        scene.render.filepath = str(tmp_path / f"ref_{frame:04d}.png")
        bl.ops.render.render(write_still=True)
        ref = _png(bl, tmp_path / f"ref_{frame:04d}.png")
        np.testing.assert_array_equal(_png(bl, path), ref, err_msg=f"frame {frame}")
    # and the desaturated frames really differ from the plain render (the compositor did run there)
    scene.render.use_compositing = False
    scene.frame_set(10)
    scene.render.filepath = str(tmp_path / "plain_0010.png")
    bl.ops.render.render(write_still=True)
    assert np.abs(_png(bl, tmp_path / "plain_0010.png") - _png(bl, skipped[9])).max() > 0.05


def test_no_shortcut_without_the_addons_desaturation(bl):
    from fourlegs_addon import importer, operators, video

    importer.import_scene(bl.context.scene, tiny_scene(N=50))
    operators.generate_highlight(bl.context.scene, hand_plan(desaturate=False))
    assert video.compositing_frames(bl.context.scene) is None  # compositor left as the user set it


def test_plan_is_reparsed_when_its_text_changes(highlight, bl):
    import json

    from fourlegs_addon import render_engine

    scene = highlight
    plan = render_engine.plan_of(scene)
    assert render_engine.plan_of(scene) is plan  # parsed once
    text = bl.data.texts[scene.get("fourlegs_plan_text", render_engine.PLAN_TEXT_NAME)]
    edited = dict(plan, passes=dict(plan["passes"], relevancy=[[1, 2]]))
    text.from_string(json.dumps(edited))
    assert render_engine.relevancy_frames(scene) == [[1, 2]]
    text.from_string("{not json")
    assert render_engine.plan_of(scene) is None


def test_torch_colour_conversion_matches_the_float64_formula(bl):
    import torch

    from fourlegs_addon import convert, render_engine

    rng = np.random.default_rng(0)
    values = np.concatenate([rng.uniform(-0.5, 1.5, 3000), [0.0, 0.04045, np.nextafter(0.04045, 1), 1.0,
                                                             np.nan, -np.inf, np.inf]]).astype(np.float32)
    c = np.clip(np.nan_to_num(values.astype(np.float64), nan=0.0), 0.0, 1.0)
    ref = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    out = render_engine.srgb_to_linear_torch(torch.from_numpy(values.reshape(-1, 1)).expand(-1, 3))
    assert out.dtype == torch.float32 and torch.isfinite(out).all()
    np.testing.assert_allclose(out.numpy()[:, 0], ref, rtol=2e-6, atol=1e-7)
    finite = np.isfinite(values)
    np.testing.assert_allclose(out.numpy()[finite, 0], convert.srgb_to_linear(values[finite]), rtol=2e-6, atol=1e-7)
    # into a strided view (the RGB part of an RGBA buffer)
    rgba = torch.zeros(values.size, 4)
    render_engine.srgb_to_linear_torch(torch.from_numpy(values.reshape(-1, 1)).expand(-1, 3), out=rgba[:, :3])
    np.testing.assert_array_equal(rgba[:, :3].numpy(), out.numpy())
    assert torch.all(rgba[:, 3] == 0)


def test_render_threads_are_set_for_the_block_and_restored(bl):
    import torch

    from fourlegs_addon import headless
    from fourlegs_engine import api

    before = torch.get_num_threads()
    with api.torch_threads(1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before
    with pytest.raises(KeyboardInterrupt), api.torch_threads(1):
        raise KeyboardInterrupt
    assert torch.get_num_threads() == before
    with api.torch_threads(None):
        assert torch.get_num_threads() == before
    assert headless.build_parser().parse_args(["q", "--demo", "-o", "out"]).render_threads == 1
