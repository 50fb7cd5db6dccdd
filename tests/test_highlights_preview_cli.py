"""The contact-sheet preview and the ``fourlegs plan`` command."""
from __future__ import annotations

import json

import matplotlib.image as mpimg
import numpy as np
import pytest

from _highlights_helpers import FakeLocalizer, tiny_scene
from fourlegs_engine.commands import main as cli
from fourlegs_engine.commands import highlights as plan_commands
from fourlegs_engine.highlights.plan import HighlightPlan
from fourlegs_engine.highlights.planner import plan_highlight
from fourlegs_engine.highlights.presets import load_preset
from fourlegs_engine.highlights.preview import (desaturate, frame_at, key_camera, render_tiles, sample_frames,
                                                write_contact_sheet)

QUERY = "a ball flying in the air"


@pytest.fixture(scope="module")
def scene():
    return tiny_scene()


@pytest.fixture(scope="module")
def plan(scene):
    return plan_highlight(scene, FakeLocalizer(scene), QUERY, load_preset("broadcast"))


def test_fractional_timesteps_blend_the_neighbouring_means(scene):
    g = scene.gaussians
    f = frame_at(g, 20.25)
    expected = 0.75 * np.asarray(g.means[20], np.float64) + 0.25 * np.asarray(g.means[21], np.float64)
    np.testing.assert_allclose(f.means.numpy(), expected, atol=1e-6)
    np.testing.assert_allclose(f.rotations.norm(dim=-1).numpy(), 1.0, atol=1e-6)
    np.testing.assert_array_equal(frame_at(g, 20.0).means.numpy(), g.means[20])
    np.testing.assert_array_equal(frame_at(g, 99.0).means.numpy(), g.means[-1])  # clamped
    np.testing.assert_array_equal(frame_at(g, -3.0).means.numpy(), g.means[0])


def test_key_camera_projects_like_the_plan(plan):
    key = plan.shots[1].camera_keys[5]
    cam = key_camera(key, plan, width=plan.resolution[0])
    centre = np.array(plan.localization["action_centre"])
    uv, z = cam.project(centre[None])
    np.testing.assert_allclose(uv[0], np.array(plan.resolution) / 2, atol=1e-6)  # recentred, zooming in
    small = key_camera(key, plan, width=64)
    assert (small.width, small.height) == (64, 36)
    np.testing.assert_allclose(small.project(centre[None])[0][0], [32, 18], atol=1e-6)


def test_desaturate_keeps_relevant_pixels_and_greys_the_rest():
    rgb = np.random.default_rng(0).uniform(size=(4, 5, 3))
    rel = np.zeros((4, 5))
    rel[1, 2] = 1.0
    out = desaturate(rgb, rel, 1.0)
    np.testing.assert_allclose(out[1, 2], rgb[1, 2])
    luma = rgb[0, 0] @ [0.2126, 0.7152, 0.0722]
    np.testing.assert_allclose(out[0, 0], [luma] * 3)
    np.testing.assert_allclose(desaturate(rgb, rel, 0.0), rgb)


def test_preview_computes_relevancy_only_for_desaturated_frames(scene, plan):
    loc = FakeLocalizer(scene)
    tiles = render_tiles(scene, plan, localizer=loc, per_shot=3, width=48)
    assert len(tiles) == len(sample_frames(plan, 3)) == 12
    desat = [t for t in tiles if t["weight"] > 0]
    assert desat and loc.stats["relevancy_map"] == len(desat)
    for t in tiles:
        img = t["image"]
        assert img.shape == (27, 48, 3) and np.all(np.isfinite(img)) and img.min() >= 0 and img.max() <= 1
    assert max(t["image"].max() for t in tiles) > 0.2  # something was actually drawn
    # the ball is orange; in a desaturated frame the background floor is grey and the ball keeps colour
    loc2 = FakeLocalizer(scene)
    render_tiles(scene, plan, localizer=loc2, per_shot=3, width=48, overlay=True)
    assert loc2.stats["relevancy_map"] == len(tiles)


def test_zoom_only_preview_requests_no_relevancy(scene):
    loc = FakeLocalizer(scene)
    plan = plan_highlight(scene, loc, QUERY, load_preset("broadcast").with_shots(["zoom_in", "bullet_time"]))
    before = loc.stats["relevancy_map"]
    render_tiles(scene, plan, localizer=loc, per_shot=2, width=32)
    assert loc.stats["relevancy_map"] == before


def test_contact_sheet_png(scene, plan, tmp_path):
    out = tmp_path / "sheet.png"
    write_contact_sheet(out, scene, plan, localizer=FakeLocalizer(scene), per_shot=2, width=48)
    img = mpimg.imread(out)
    assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 100
    assert not list(tmp_path.glob(".*part*"))
    with pytest.raises(Exception, match="already exists"):
        write_contact_sheet(out, scene, plan, per_shot=1, width=32)


@pytest.fixture()
def fake_engine(monkeypatch, scene):
    state = {}

    def opener(scene_path, *, demo, **kw):
        state["demo"], state["path"] = demo, scene_path
        state["localizer"] = FakeLocalizer(scene)
        return scene, state["localizer"]

    monkeypatch.setattr(plan_commands, "open_scene_and_localizer", opener)
    return state


def test_cli_plan_with_preview(fake_engine, tmp_path, capsys):
    out, png = tmp_path / "plan.json", tmp_path / "plan.png"
    rc = cli.main(["plan", "--demo", QUERY, "--preset", "broadcast", "-o", str(out), "--preview", str(png),
                   "--per-shot", "2", "--preview-width", "48"])
    assert rc == 0 and fake_engine["demo"] is True
    plan = HighlightPlan.load(out)
    assert plan.effects == ["play", "zoom_in", "bullet_time", "desaturate_background"]
    assert png.is_file()
    text = capsys.readouterr().out
    assert "bullet_time" in text and "passes: rgb" in text
    # existing outputs are kept unless --overwrite
    rc = cli.main(["plan", "--demo", QUERY, "-o", str(out)])
    assert rc == 2 and "already exists" in capsys.readouterr().err
    rc = cli.main(["plan", "--demo", QUERY, "-o", str(out), "--overwrite", "--effects", "zoom_in",
                   "--fps", "30", "--resolution", "320x240"])
    assert rc == 0
    d = json.loads(out.read_text())
    assert [s["effect"] for s in d["shots"]] == ["zoom_in"] and d["fps"] == 30 and d["resolution"] == [320, 240]
    assert set(d["passes"]) == {"rgb"}


@pytest.mark.parametrize("argv,message", [
    (["plan", "--demo", "x", "-o", "{out}", "--preset", "nope"], "unknown preset 'nope'"),
    (["plan", "--demo", "x", "-o", "{out}", "--effects", "sparkles"], "unknown effects"),
    (["plan", "--demo", "x", "-o", "{out}", "--resolution", "big"], "WIDTHxHEIGHT"),
    (["plan", "onlyscene", "-o", "{out}"], "expected SCENE QUERY"),
    (["plan", "--demo", "x"], "missing -o"),
    (["plan", "--demo", "  ", "-o", "{out}"], "query text is empty"),
])
def test_cli_errors_are_one_line(fake_engine, tmp_path, capsys, argv, message):
    argv = [a.replace("{out}", str(tmp_path / "p.json")) for a in argv]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not (tmp_path / "p.json").exists()


def test_cli_lists_presets(capsys):
    assert cli.main(["plan", "--list-presets"]) == 0
    out = capsys.readouterr().out
    for name in ("broadcast", "bullet_time_only", "subtle_desaturate", "social_vertical"):
        assert name in out
