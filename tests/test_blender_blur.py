"""The background blur in Blender: the compositor's blur branch keyed by the plan's blur weights, the
mask used only on blurred frames, and the blur in the final image (4-LEGS Splats engine)."""
from __future__ import annotations

import numpy as np
import pytest

from _blender_helpers import bl, bpy_addon, hand_plan, tiny_scene  # noqa: F401

pytestmark = pytest.mark.blender
RADIUS = 0.15   # of the frame height: 3.6 px at 24 px


def blur_plan() -> dict:
    plan = hand_plan(desaturate=False)
    plan["passes"]["relevancy"] = [[7, 12]]
    plan["blur"] = {"ranges": [[7, 12]], "fade_in": 2, "fade_out": 2, "strength": 1.0, "weights": {},
                    "radius": RADIUS}
    return plan


@pytest.fixture
def blurred(bl):
    """Tiny scene + the blur plan; relevancy 1 for the Gaussians with x < 0.1 t, 0 elsewhere."""
    from fourlegs_addon import importer, operators, render_engine

    bl.context.scene.fourlegs.renderer = "FOURLEGS"
    scene = tiny_scene(N=400)
    obj = importer.import_scene(bl.context.scene, scene)
    importer.set_relevancy_provider(obj, lambda t: (scene.gaussians.means[t][:, 0] < 0.1 * t).astype(np.float32))
    operators.generate_highlight(bl.context.scene, blur_plan())
    render_engine.reset_stats()
    return bl.context.scene


def test_blur_branch_is_keyed_like_the_desaturation_weight(blurred):
    from fourlegs_addon import compositor, video

    scene = blurred
    tree = compositor.compositor_tree(scene)
    assert tree is not None and compositor.has_masking(scene) and not compositor.has_desaturation(scene)
    assert compositor.BLUR_NODE in tree.nodes and compositor.WEIGHT_NODE not in tree.nodes
    weights = compositor.frame_weights(blur_plan(), "blur")
    assert weights[3] == 0.0 and weights[9] == 1.0 and 0.0 < weights[7] < weights[8] < 1.0
    size = tree.nodes[compositor.BLUR_NODE].inputs["Size"]
    for frame in (3, 7, 9, 12):
        scene.frame_set(frame)
        assert compositor.blur_at(scene, frame) == pytest.approx(weights[frame], abs=1e-5)
        assert tuple(size.default_value) == pytest.approx((weights[frame] * RADIUS * 24,) * 2, abs=1e-4)
    # the compositor (and the relevancy mask) only where the blur is on
    assert video.compositing_frames(scene) == {f for f, w in weights.items() if w > 0}


def test_compositor_blurs_only_the_irrelevant_background(blurred, bl, tmp_path):
    OpenEXR = pytest.importorskip("OpenEXR")
    from fourlegs_addon import render_engine

    def passes(frame):
        scene = bl.context.scene
        scene.frame_set(frame)
        bl.ops.render.render()
        if hasattr(scene.render.image_settings, "media_type"):  # Blender 5.0+
            scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
        scene.render.image_settings.file_format = "OPEN_EXR_MULTILAYER"
        path = tmp_path / f"f{frame}.exr"
        bl.data.images["Render Result"].save_render(str(path))
        return {name: np.asarray(ch.pixels, np.float32) for part in OpenEXR.File(str(path)).parts
                for name, ch in part.channels.items()}

    out = passes(9)
    combined, final = out["ViewLayer.Combined"][..., :3], out["Composite.Combined"][..., :3]
    rel = out["ViewLayer.Relevancy.X"]
    relevant, background = rel > 0.99, rel < 0.01
    assert relevant.sum() > 3 and background.sum() > 3
    np.testing.assert_allclose(final[relevant], combined[relevant], atol=0.02)   # the action stays sharp
    assert np.abs(final[background] - combined[background]).max() > 0.05        # the rest is blurred
    assert render_engine.stats["relevancy_frames"] == [9]
    out = passes(3)   # weight 0: unchanged, and no relevancy computed
    np.testing.assert_allclose(out["Composite.Combined"][..., :3], out["ViewLayer.Combined"][..., :3], atol=0.02)
    assert render_engine.stats["relevancy_frames"] == [9]
