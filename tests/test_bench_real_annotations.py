"""Honest annotations of the ball: colour masks, triangulation, and the in-the-air / held split from geometry."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from fourlegs_bench.real_annotations import (BALL_RADIUS_M, BallTrack, ball_mask, holding_mask, in_air_flags,
                                             projection_matrix, triangulate, write_annotations)
from fourlegs_engine.scene.camera import Camera

ORANGE = (214, 92, 44)
WALL = (200, 203, 196)
SKIN = (226, 180, 150)
W, H = 240, 180


def ring_cameras(n: int = 6, radius: float = 4.0) -> list[Camera]:
    return [Camera.look_at((radius * math.cos(2 * math.pi * i / n), -1.5, radius * math.sin(2 * math.pi * i / n)),
                           (0.0, -1.0, 0.0), up=(0.0, -1.0, 0.0), width=W, height=H, focal=200.0, near=0.5,
                           far=100.0, name=str(i + 1)) for i in range(n)]


def draw_disc(img: np.ndarray, centre: tuple[float, float], radius: float, colour) -> np.ndarray:
    ys, xs = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    inside = (xs + 0.5 - centre[0]) ** 2 + (ys + 0.5 - centre[1]) ** 2 <= radius ** 2
    img[inside] = colour
    return inside


def test_the_ball_mask_keeps_the_ball_fills_its_seams_and_drops_skin_and_stray_pixels():
    img = np.tile(np.array(WALL, np.uint8), (H, W, 1))
    truth = draw_disc(img, (60.0, 50.0), 14.0, ORANGE)
    img[49:51, 46:74] = (40, 30, 30)                      # a dark seam across the ball
    draw_disc(img, (120.0, 80.0), 10.0, SKIN)               # a face: orange-ish but unsaturated
    img[10, 10] = ORANGE                                    # one stray orange pixel
    mask = ball_mask(img)
    assert mask[truth].mean() == 1.0                        # seam filled
    assert not mask[~truth].any()
    assert not ball_mask(np.tile(np.array(WALL, np.uint8), (H, W, 1))).any()


def test_the_ball_mask_rejects_a_wrong_shape():
    with pytest.raises(ValueError, match="H, W, 3"):
        ball_mask(np.zeros((4, 4), np.uint8))


def test_holding_mask_is_the_foreground_component_touching_the_ball():
    fg = np.zeros((40, 60), bool)
    fg[5:35, 10:20] = True                                  # the holder
    fg[5:35, 45:55] = True                                  # a bystander
    ball = np.zeros_like(fg)
    ball[15:22, 21:28] = True                               # one pixel off the holder's hand
    held = holding_mask(fg, ball)
    assert held[5:35, 10:20].all() and held[ball].all()
    assert not held[:, 45:55].any()
    assert not holding_mask(fg, np.zeros_like(fg)).any()


@settings(max_examples=40, deadline=None)
@given(x=st.floats(-1.0, 1.0), y=st.floats(-2.0, -0.2), z=st.floats(-1.0, 1.0), noise=st.floats(0.0, 0.5))
def test_triangulation_recovers_the_centre_and_drops_an_outlier_view(x, y, z, noise):
    cams = ring_cameras(7)
    X = np.array([x, y, z])
    P = np.stack([projection_matrix(c) for c in cams])
    rng = np.random.default_rng(0)
    pts = np.stack([c.project(X[None])[0][0] for c in cams]) + rng.uniform(-noise, noise, (len(cams), 2))
    pts[3] += (40.0, -25.0)                                 # one view found something else
    found, used = triangulate(pts, P)
    assert found is not None and np.all(np.isfinite(found))
    assert np.linalg.norm(found - X) < 0.02
    assert not used[3] and used.sum() == len(cams) - 1


def test_triangulation_gives_none_when_views_disagree():
    cams = ring_cameras(3)
    P = np.stack([projection_matrix(c) for c in cams])
    pts = np.array([[10.0, 10.0], [150.0, 20.0], [80.0, 110.0]])
    found, _ = triangulate(pts, P)
    assert found is None


def test_in_air_flags_count_people_within_reach_not_the_ball_itself():
    centres = np.array([[0.0, -1.5, 0.0], [0.0, -1.5, 0.0], [np.nan] * 3])
    ball = np.random.default_rng(1).normal(size=(50, 3)) * 0.03 + centres[0]          # the ball's own Gaussians
    far_person = np.random.default_rng(2).normal(size=(200, 3)) * 0.1 + [1.5, -1.0, 0.0]
    near_person = np.random.default_rng(3).normal(size=(200, 3)) * 0.1 + [0.0, -1.5, BALL_RADIUS_M + 0.2]
    means = [np.concatenate([ball, far_person]), np.concatenate([ball, near_person]), far_person]
    in_air, near = in_air_flags(BallTrack(centres, np.array([6, 6, 0])), means)
    assert in_air.tolist() == [True, False, False]
    assert near[0] == 0 and near[1] > 20 and near[2] == 0


def write_tiny_capture(root, cams, ball_centres, person_centre):
    """Frames with an orange ball at the given 3D centres and a blue 'person' disc (also in seg/)."""
    meta = {"w": W, "h": H, "k": [], "w2c": [], "fn": [], "cam_id": []}
    for t, centre in enumerate(ball_centres):
        meta["k"].append([c.K.tolist() for c in cams])
        meta["w2c"].append([c.w2c.tolist() for c in cams])
        meta["fn"].append([f"{c.name}/{t:06d}.png" for c in cams])
        meta["cam_id"].append([int(c.name) for c in cams])
        for c in cams:
            img = np.tile(np.array(WALL, np.uint8), (H, W, 1))
            (pc,), _ = c.project(np.asarray(person_centre)[None])
            depth = float((c.w2c @ np.append(person_centre, 1.0))[2])
            person = draw_disc(img, tuple(pc), 0.35 * c.fx / depth, (40, 60, 160))
            (bc,), _ = c.project(np.asarray(centre)[None])
            depth = float((c.w2c @ np.append(centre, 1.0))[2])
            ball = draw_disc(img, tuple(bc), BALL_RADIUS_M * c.fx / depth, ORANGE)
            for folder, arr in (("ims", img), ("seg", ((person | ball) * 255).astype(np.uint8))):
                (root / folder / c.name).mkdir(parents=True, exist_ok=True)
                Image.fromarray(arr).save(root / folder / c.name / f"{t:06d}.png")
    (root / "train_meta.json").write_text(json.dumps(meta))
    return root


def test_write_annotations_splits_the_ball_in_the_air_from_the_ball_held(tmp_path):
    from fourlegs_engine.scene.bundle import write_bundle
    from fourlegs_engine.scene.camera import CameraRig
    from fourlegs_engine.scene.gaussians import GaussianSequence
    from fourlegs_engine.scene.scene import Scene

    cams = ring_cameras(6)
    person = np.array([0.0, -1.0, 0.0])
    ball_centres = [np.array([0.0, -1.0, 1.2]),                      # well away: in the air
                    np.array([0.0, -1.0, 0.2 + BALL_RADIUS_M])]      # against the person: held
    capture = write_tiny_capture(tmp_path / "cap", cams, ball_centres, person)
    rng = np.random.default_rng(0)
    person_pts = person + rng.normal(size=(300, 3)) * [0.12, 0.3, 0.12]
    means = np.stack([np.concatenate([person_pts, c + rng.normal(size=(40, 3)) * 0.03]) for c in ball_centres])
    N = means.shape[1]
    seq = GaussianSequence(means=means, rotations=np.tile([1.0, 0, 0, 0], (2, N, 1)),
                           log_scales=np.full((N, 3), math.log(0.03)), opacity_logits=np.full(N, 3.0),
                           colors=np.full((N, 3), 0.5), foreground=np.ones(N, bool))
    bundle = write_bundle(Scene(gaussians=seq, cameras=CameraRig.static(cams, [], 2), name="tiny"), tmp_path / "scene")

    report = write_annotations(capture, bundle, tmp_path / "ann", progress=False)
    assert report["ball_found_timesteps"] == 2
    assert report["in_air_runs"] == [[0, 0]]
    assert report["ball_pixels_inside_foreground"] == 1.0
    centre0 = report["per_timestep"][0]["centre"]
    assert np.linalg.norm(np.asarray(centre0) - ball_centres[0]) < 0.03

    def mask(phrase, cam, t):
        return np.asarray(Image.open(tmp_path / "ann" / phrase / cam / f"{t:06d}.png")) > 0

    for cam in ("1", "4"):
        assert mask("the ball in the air", cam, 0).sum() == mask("the ball", cam, 0).sum() > 20
        assert not mask("the ball in the air", cam, 1).any()
        assert not mask("a person holding the ball", cam, 0).any()
        held = mask("a person holding the ball", cam, 1)
        assert held.sum() > mask("the ball", cam, 1).sum()
    assert not list((tmp_path / "ann").rglob(".*.part"))
