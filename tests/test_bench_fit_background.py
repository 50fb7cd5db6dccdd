"""``fourlegs bench fit-background`` on a synthetic capture and the exact Gaussians that rendered it."""
from __future__ import annotations

import json

import numpy as np
from PIL import Image

import _fit_helpers as fh
from fourlegs_engine.commands.main import main
from fourlegs_engine.scene.bundle import write_bundle
from fourlegs_engine.scene.camera import CameraRig
from fourlegs_engine.scene.gaussians import GaussianSequence
from fourlegs_engine.scene.scene import Scene


def test_ground_truth_gaussians_score_near_perfect_and_the_picture_has_its_panels(tmp_path):
    capture = fh.write_capture(tmp_path / "capture", num_timesteps=3)
    g = fh.scene_gaussians()
    frames = [fh.frame_at(g, t) for t in range(3)]
    truth = GaussianSequence(means=np.stack([f[0] for f in frames]).astype(np.float32),
                             rotations=np.stack([f[1] for f in frames]).astype(np.float32),
                             log_scales=g["log_scales"].astype(np.float32),
                             opacity_logits=np.full(len(g["fg"]), 3.0, np.float32),
                             colors=g["colors"].astype(np.float32), foreground=g["fg"])
    train, test = fh.cameras()
    bundle = write_bundle(Scene(gaussians=truth, cameras=CameraRig.static(train, test, 3), name="truth"),
                          tmp_path / "truth")
    out = tmp_path / "bench"
    assert main(["bench", "fit-background", f"truth={bundle}", "--dataset", str(capture), "--out", str(out),
                 "--k", "1", "--picture-camera", "0", "--picture-timesteps", "0,2", "--resolution-scale", "1"]) == 0
    rec = json.loads((out / "fit_background.json").read_text())["records"][0]
    assert rec["run"] == "truth" and rec["k"] == 1 and rec["plate_timesteps"] == [0, 1, 2]
    # renders equal the 8-bit frames up to quantisation (PSNR of uniform ±0.5/255 noise is ≈ 59 dB)
    for part in ("first", "last"):
        assert rec[part]["psnr"] > 45.0, rec
        assert rec[part]["mse_moving"] + rec[part]["mse_static"] < 1e-4
    # the box covers some pixels in 2 of the 3 frames: there the plate shows the box, not the wall
    assert 10.0 < rec["cameras"]["0"]["background_vs_plate_psnr"] < 45.0
    picture = np.asarray(Image.open(out / "fit_background.png"))
    assert picture.shape == (2 * fh.HEIGHT, 4 * fh.WIDTH, 3)
    assert "| truth |" in (out / "fit_background.md").read_text()
