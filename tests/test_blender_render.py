"""The "4-LEGS Splats" render engine (Combined, Depth, Relevancy passes; relevancy only on planned
frames), the compositor's desaturation in the final image, and the video writer."""
from __future__ import annotations

import time

import numpy as np
import pytest

from _blender_helpers import bl, bpy_addon, hand_plan, tiny_scene  # noqa: F401

pytestmark = pytest.mark.blender
OpenEXR = pytest.importorskip("OpenEXR")


@pytest.fixture
def highlight(bl):
    """Tiny scene + hand-made plan with desaturation; relevancy 1 for x < 0 Gaussians, 0 elsewhere."""
    from fourlegs_addon import importer, operators, render_engine

    scene = tiny_scene(N=400)
    obj = importer.import_scene(bl.context.scene, scene)
    calls = []

    def provider(t):
        calls.append(t)
        return (scene.gaussians.means[t][:, 0] < 0.1 * t).astype(np.float32)

    importer.set_relevancy_provider(obj, provider)
    operators.generate_highlight(bl.context.scene, hand_plan(desaturate=True))
    render_engine.reset_stats()
    return bl.context.scene, scene, calls


def _render_passes(bl, frame: int, path) -> dict[str, np.ndarray]:
    scene = bl.context.scene
    scene.frame_set(frame)
    bl.ops.render.render()
    if hasattr(scene.render.image_settings, "media_type"):  # Blender 5.0+
        scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    scene.render.image_settings.file_format = "OPEN_EXR_MULTILAYER"
    bl.data.images["Render Result"].save_render(str(path))
    out = {}
    for part in OpenEXR.File(str(path)).parts:
        for name, channel in part.channels.items():
            out[name] = np.asarray(channel.pixels, dtype=np.float32)
    return out


def test_passes_are_written_and_relevancy_only_on_planned_frames(highlight, bl, tmp_path):
    from fourlegs_addon import render_engine

    scene, src, calls = highlight
    planned = _render_passes(bl, 9, tmp_path / "f9.exr")  # frame 9 is in the plan's relevancy range
    rgba = planned["ViewLayer.Combined"]
    depth = planned["ViewLayer.Depth.Z"]
    rel = planned["ViewLayer.Relevancy.X"]
    assert rgba.shape == (24, 32, 4)
    hit = depth < 1e9
    assert 20 < hit.sum() < hit.size  # the cube covers part of the frame
    assert rgba[..., :3][hit].max() > 0.2 and rgba[..., :3][~hit].max() < 0.05
    cam_dist = np.linalg.norm(np.array(scene.camera.matrix_world.translation))
    assert depth[hit].min() > cam_dist - 1.5 and depth[hit].max() < cam_dist + 1.5
    assert 0.0 <= rel.min() and rel.max() <= 1.0 and rel[hit].max() > 0.9 and rel[hit].min() < 0.1
    assert calls == [2]  # the scene timestep held at frame 9 is 2.0: relevancy of timestep 2, once
    assert render_engine.stats["relevancy_frames"] == [9]

    unplanned = _render_passes(bl, 3, tmp_path / "f3.exr")  # outside the relevancy range
    assert calls == [2] and render_engine.stats["relevancy_frames"] == [9]
    assert np.all(unplanned["ViewLayer.Relevancy.X"] == 0.0)
    assert unplanned["ViewLayer.Combined"][..., :3].max() > 0.2
    assert render_engine.stats["frames"] == 2 and render_engine.stats["last_error"] is None


def test_compositor_desaturates_the_irrelevant_background(highlight, bl, tmp_path):
    passes = _render_passes(bl, 9, tmp_path / "f9.exr")  # desaturation weight 1 at frame 9
    combined, final = passes["ViewLayer.Combined"][..., :3], passes["Composite.Combined"][..., :3]
    rel = passes["ViewLayer.Relevancy.X"]
    hit = passes["ViewLayer.Depth.Z"] < 1e9
    saturation = lambda img: img.max(-1) - img.min(-1)  # noqa: E731
    irrelevant = hit & (rel < 0.2) & (saturation(combined) > 0.1)
    relevant = hit & (rel > 0.8) & (saturation(combined) > 0.1)
    assert irrelevant.sum() > 3 and relevant.sum() > 3
    assert saturation(final)[irrelevant].max() < 0.02  # grey
    np.testing.assert_allclose(final[relevant], combined[relevant], atol=0.02)  # untouched
    passes = _render_passes(bl, 3, tmp_path / "f3.exr")  # weight 0 outside the range: unchanged
    np.testing.assert_allclose(passes["Composite.Combined"][..., :3], passes["ViewLayer.Combined"][..., :3],
                               atol=0.02)


def test_render_engine_reports_errors_instead_of_crashing(highlight, bl, tmp_path):
    from fourlegs_addon import render_engine

    scene, _, _ = highlight
    scene.camera.data.type = "ORTHO"
    scene.frame_set(2)
    with pytest.raises(RuntimeError, match="needs a perspective camera"):
        bl.ops.render.render()
    assert "perspective" in render_engine.stats["last_error"]


def test_video_is_written_decodable_and_never_overwritten(highlight, bl, tmp_path):
    from fourlegs_addon import render_engine, video

    scene, _, calls = highlight
    done = []
    out = video.render_animation(scene, tmp_path / "clip.mp4", on_frame=lambda d, n: done.append((d, n)))
    assert out.is_file() and out.stat().st_size > 0
    assert video.movie_frame_count(out) == 12
    assert done[-1] == (12, 12) and len(done) == 12
    assert render_engine.stats["relevancy_frames"] == list(range(7, 13))
    assert sorted(set(calls)) == [2]  # cached: one relevancy evaluation for the held timestep
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary left behind
    mtime = out.stat().st_mtime_ns
    with pytest.raises(FileExistsError):
        video.render_animation(scene, out)
    assert out.stat().st_mtime_ns == mtime
    scene.frame_end = 3
    frames = video.render_animation(scene, tmp_path / "frames", fmt="PNG")
    assert sorted(p.name for p in frames.iterdir()) == [f"frame_{i:04d}.png" for i in range(1, 4)]


def test_reopened_file_computes_relevancy_from_the_plans_query(bl, tmp_path):
    """Without a provider (a saved .blend opened again) the engine asks the scene's language field."""
    from _blender_helpers import language_bundle
    from fourlegs_addon import importer, operators, render_engine

    bundle = language_bundle(tmp_path / "scene")
    scene = importer.load_engine_scene(bundle)
    importer.import_scene(bl.context.scene, scene, source=str(bundle))
    plan = hand_plan(desaturate=True)
    plan["query"] = "the red cube"
    operators.generate_highlight(bl.context.scene, plan)
    render_engine.reset_stats()
    passes = _render_passes(bl, 9, tmp_path / "f9.exr")  # timestep 2: the cube half is relevant
    rel = passes["ViewLayer.Relevancy.X"][passes["ViewLayer.Depth.Z"] < 1e9]
    assert rel.max() > 0.9 and rel.min() < 0.2
    assert render_engine.stats["relevancy_frames"] == [9]


def test_written_frames_reproduce_the_rasterizers_colours(highlight, bl, tmp_path):
    """PNG pixels == the engine's RGB for the same camera and timestep (to 8-bit rounding)."""
    import torch

    from fourlegs_addon import render_engine, video
    from fourlegs_engine.render import rasterize

    scene, src, _ = highlight
    scene.frame_start = scene.frame_end = 4
    frames = video.render_animation(scene, tmp_path / "frames", fmt="PNG")
    img = bl.data.images.load(str(frames / "frame_0004.png"))
    img.colorspace_settings.name = "Non-Color"  # raw 8-bit values
    w, h = img.size
    png = np.array(img.pixels[:], np.float32).reshape(h, w, 4)[::-1, :, :3]
    scene.frame_set(4)
    camera = render_engine.scene_camera(scene, bl.context.evaluated_depsgraph_get(), w, h)
    t = scene.fourlegs.timestep
    lo, frac = int(np.floor(t)), t - np.floor(t)
    g = src.gaussians
    means = (1 - frac) * g.means[lo] + frac * g.means[min(lo + 1, 3)]
    colors = (1 - frac) * g.colors[lo] + frac * g.colors[min(lo + 1, 3)]
    with torch.no_grad():
        ref = rasterize(torch.from_numpy(means), torch.from_numpy(g.rotations[round(t)]),
                        torch.from_numpy(g.log_scales), torch.from_numpy(g.opacity_logits), camera,
                        colors=torch.from_numpy(colors))["rgb"].numpy()
    assert np.abs(png - np.clip(ref, 0, 1)).max() <= 1.5 / 255


def test_render_video_operator_reports_existing_output(highlight, bl, tmp_path):
    from fourlegs_addon import video

    scene, _, _ = highlight
    scene.frame_end = 3
    props = scene.fourlegs
    props.output_path = str(tmp_path / "clip.mp4")
    assert bl.ops.fourlegs.render_video() == {"FINISHED"}
    assert video.movie_frame_count(tmp_path / "clip.mp4") == 3
    with pytest.raises(RuntimeError, match="already exists"):
        bl.ops.fourlegs.render_video()
    props.overwrite = True
    assert bl.ops.fourlegs.render_video() == {"FINISHED"}


def test_no_depth_is_computed_when_the_plan_lists_none(bl):
    from fourlegs_addon import importer, operators, render_engine

    importer.import_scene(bl.context.scene, tiny_scene())
    plan = hand_plan(desaturate=False)
    plan["passes"]["depth"] = []
    operators.generate_highlight(bl.context.scene, plan)
    render_engine.reset_stats()
    bl.context.scene.frame_set(2)
    bl.ops.render.render()
    assert render_engine.stats["frames"] == 1
    assert render_engine.stats["depth_frames"] == [] and render_engine.stats["relevancy_frames"] == []
    assert not bl.context.scene.view_layers[0].use_pass_z


def test_frame_by_frame_rendering_resumes_and_encodes(highlight, bl, tmp_path):
    from fourlegs_addon import render_engine, video

    scene, _, _ = highlight
    scene.frame_end = 5
    frames = video.render_frames(scene, tmp_path / "frames")
    assert [p.name for p in frames] == [f"frame_{i:04d}.png" for i in range(1, 6)]
    kept = {p: p.stat().st_mtime_ns for p in frames if p.name not in ("frame_0002.png", "frame_0005.png")}
    frames[1].unlink()
    frames[4].unlink()  # as if interrupted
    render_engine.reset_stats()
    again = video.render_frames(scene, tmp_path / "frames")
    assert again == frames and render_engine.stats["frames"] == 2  # only the missing frames
    assert all(p.stat().st_mtime_ns == t for p, t in kept.items())
    assert not [p for p in (tmp_path / "frames").iterdir() if p.name.startswith(".")]
    movie = video.encode_mp4(again, tmp_path / "clip.mp4", fps=12)
    assert video.movie_frame_count(movie) == 5
    with pytest.raises(FileExistsError):
        video.encode_mp4(again, tmp_path / "clip.mp4", fps=12)


def test_render_job_renders_one_frame_per_step_and_cancel_leaves_nothing(highlight, bl, tmp_path):
    """What the modal Render Video does on each timer tick: one frame, progress, cancel removes it all."""
    from fourlegs_addon import video

    scene, _, _ = highlight
    scene.frame_end = 4
    scene.frame_set(2)
    job = video.RenderJob(scene, tmp_path / "clip.mp4")
    assert (job.total, job.done) == (4, 0)
    assert job.step() and job.done == 1 and job.written[0].name == "frame_0001.png"
    assert job.step() and job.done == 2
    job.cancel()
    assert list(tmp_path.iterdir()) == []  # no movie, no temporary frames
    assert scene.frame_current == 2 and scene.render.image_settings.file_format == "FFMPEG"

    job = video.RenderJob(scene, tmp_path / "clip.mp4")
    for n in range(1, 5):  # one frame per step; the encoder starts on the step after the last frame
        assert job.step() and job.done == n and job.encoder is None
    while job.step():
        time.sleep(0.01)
    out = job.finish()
    assert video.movie_frame_count(out) == 4
    assert [p.name for p in tmp_path.iterdir()] == ["clip.mp4"]
    with pytest.raises(FileExistsError):
        video.RenderJob(scene, out)

    seq = video.RenderJob(scene, tmp_path / "frames", fmt="PNG")
    while seq.step():
        pass
    frames = seq.finish()
    assert sorted(p.name for p in frames.iterdir()) == [f"frame_{i:04d}.png" for i in range(1, 5)]


def test_mp4_encodes_in_a_child_process_while_each_step_returns_within_a_second(highlight, bl, tmp_path):
    """Render Video's timer ticks during the encode: each step returns at once (the child encodes), the
    encoder's progress counts up to every frame, and the movie appears complete, only at the end."""
    from fourlegs_addon import video

    scene, _, _ = highlight
    scene.frame_end = 6
    job = video.RenderJob(scene, tmp_path / "clip.mp4")
    while job.encoder is None:
        assert job.step()
    child = job.encoder._proc
    ticks, progress = [], []
    while True:
        t0 = time.perf_counter()
        more = job.step()
        ticks.append(time.perf_counter() - t0)
        progress.append(job.encoder.encoded)
        if not more:
            break
        assert not (tmp_path / "clip.mp4").exists()
        time.sleep(0.01)  # the modal timer's interval
    assert max(ticks) < 1.0 and len(ticks) > 10  # control came back many times while the child encoded
    assert child.returncode == 0 and progress == sorted(progress) and progress[-1] == 6
    out = job.finish()
    assert video.movie_frame_count(out) == 6 and [p.name for p in tmp_path.iterdir()] == ["clip.mp4"]


def test_cancel_during_the_encode_ends_the_child_and_leaves_nothing(highlight, bl, tmp_path):
    from fourlegs_addon import video

    scene, _, _ = highlight
    scene.frame_end = 3
    job = video.RenderJob(scene, tmp_path / "clip.mp4")
    while job.encoder is None:
        job.step()
    assert job.encoding
    job.cancel()
    assert job.encoder._proc.returncode is not None and not job.encoding
    assert list(tmp_path.iterdir()) == []


def test_a_failed_encode_is_one_line_and_leaves_nothing(highlight, bl, tmp_path):
    from fourlegs_addon import video

    scene, _, _ = highlight
    scene.frame_end = 2
    job = video.RenderJob(scene, tmp_path / "clip.mp4")
    while job.encoder is None:
        job.step()
    job.encoder.wait()
    for movie in job.encoder.out_dir.glob("movie_*.mp4"):
        movie.unlink()  # as if the encoder had written nothing
    with pytest.raises(RuntimeError, match="encoding the MP4 failed"):
        job.finish()
    assert list(tmp_path.iterdir()) == []


def test_render_video_operator_cancel_button_stops_it_between_frames(highlight, bl, tmp_path):
    from fourlegs_addon import jobs, video

    scene, _, _ = highlight
    scene.frame_end = 5
    props = scene.fourlegs
    props.output_path = str(tmp_path / "clip.mp4")
    rendered = []
    real_step = video.RenderJob.step

    def step_then_press_cancel(job):
        more = real_step(job)
        rendered.append(job.done)
        if job.done == 2:
            bl.ops.fourlegs.cancel_query()  # the panel's Cancel button, as a timer tick would see it
        return more

    video.RenderJob.step = step_then_press_cancel
    try:
        assert bl.ops.fourlegs.render_video() == {"CANCELLED"}
    finally:
        video.RenderJob.step = real_step
    assert rendered == [1, 2] and not props.running and props.status == "render cancelled"
    assert list(tmp_path.iterdir()) == [] and jobs.active() == []


def test_viewport_image_is_the_render_seen_from_the_viewport_matrices(highlight, bl):
    """view_draw's image: the CPU rasterizer from the region's view/window matrices. Given the scene
    camera's own matrices it must equal an F12 render of the same size."""
    from fourlegs_addon import render_engine

    scene, _, _ = highlight
    scene.frame_set(4)
    depsgraph = bl.context.evaluated_depsgraph_get()
    cam = scene.camera.evaluated_get(depsgraph)
    w, h = 32, 24
    window = cam.calc_matrix_camera(depsgraph, x=w, y=h)
    view = cam.matrix_world.inverted()
    img = render_engine.viewport_image(scene, view, window, w, h, near=cam.data.clip_start, far=cam.data.clip_end)
    ref = render_engine.render_arrays(scene, depsgraph, w, h, frame=4, relevancy_pass=False, depth=False, plan=None,
                                      transparent=True)["rgba"]
    assert img.shape == (h, w, 4)
    np.testing.assert_allclose(img, ref, atol=2e-5)
    assert 0.05 < (img[..., 3] > 0.5).mean() < 0.95  # the cube covers part of the view, alpha is coverage
    # a region larger than the interactive size is rasterized smaller, same aspect, then scaled up
    assert render_engine.VIEWPORT_MAX_SIDE == 320
    assert render_engine.viewport_size(1920, 1080) == (320, 180)
    assert render_engine.viewport_size(300, 200) == (300, 200)
    big = render_engine.viewport_image(scene, view, window, 640, 480)
    assert big.shape == (240, 320, 4) and big[..., 3].max() > 0.5
    # the view moved: another image; orthographic: one clear error
    moved = view.copy()
    moved.translation.x += 0.5
    assert np.abs(render_engine.viewport_image(scene, moved, window, w, h) - img).max() > 0.1
    ortho = window.copy()
    ortho[3][2], ortho[3][3] = 0.0, 1.0
    with pytest.raises(RuntimeError, match="perspective"):
        render_engine.viewport_image(scene, view, ortho, w, h)
    # the engine draws in the viewport (Rendered shading), not only on F12
    assert "view_draw" in render_engine.FourlegsRenderEngine.__dict__
    assert "view_update" in render_engine.FourlegsRenderEngine.__dict__
