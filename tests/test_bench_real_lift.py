"""``fourlegs bench real-lift``'s time window: masks seen from a first timestep, the subset bundle of it."""
from __future__ import annotations

import numpy as np
from PIL import Image

from fourlegs_bench.real_lift import shifted_masks, subset_bundle
from fourlegs_engine.language.annotations import read_mask
from fourlegs_engine.scene.bundle import load_bundle, write_bundle

from _scene_helpers import random_scene


def test_a_window_from_a_first_timestep_takes_its_geometry_and_its_masks(tmp_path):
    scene = random_scene(T=6, N=20)
    source = write_bundle(scene, tmp_path / "scene")
    masks = tmp_path / "masks"
    for cam in ("1", "2"):
        (masks / cam).mkdir(parents=True)
        for t in range(6):
            Image.fromarray(np.full((4, 5), 255 * (t % 2), np.uint8)).save(masks / cam / f"{t:06d}.png")
    shifted = shifted_masks(masks, 3, 2, tmp_path / "shifted")
    assert sorted(p.name for p in (shifted / "1").iterdir()) == ["000000.png", "000001.png"]
    for t in range(2):  # window timestep t is capture timestep 3 + t
        np.testing.assert_array_equal(read_mask(shifted / "2" / f"{t:06d}.png"),
                                      read_mask(masks / "2" / f"{3 + t:06d}.png"))
    assert shifted_masks(masks, 0, 2, tmp_path / "unused") == masks
    cams = load_bundle(source).cameras.cameras(0, "all")
    sub = subset_bundle(source, tmp_path / "sub", cams[:1], cams[1:2], 2, first=3)
    assert sub.num_timesteps == 2
    np.testing.assert_array_equal(np.asarray(sub.gaussians.means), np.asarray(scene.gaussians.means[3:5]))
    assert [c.name for c in sub.cameras.cameras(0, "train")] == [cams[0].name]
