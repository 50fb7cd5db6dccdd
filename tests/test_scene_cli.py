"""``fourlegs info``: the facts it prints, --json, --demo wiring, one-line errors with exit code 2."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from fourlegs_engine.commands.main import main
from fourlegs_engine.scene import write_bundle
from fourlegs_engine.scene.ply import write_ply_scene

from _scene_helpers import random_scene


@pytest.fixture()
def bundle(tmp_path):
    scene = random_scene(T=4, N=30, sh_degree=None, colors=True)
    scene.gaussians.latents = np.zeros((4, 30, 16), np.float32)
    return scene, write_bundle(scene, tmp_path / "scene")


def test_info_text(bundle, capsys):
    scene, path = bundle
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    lo, hi = scene.gaussians.bounds()
    fg = 100 * scene.gaussians.foreground.mean()
    for needle in ("timesteps (T)   4 at 25 fps", "Gaussians (N)   30", "cameras         3 train, 1 test",
                   "image size      64x48", f"foreground      {fg:.1f}%", "language field  yes (latent dim 16",
                   "bounds min      " + " ".join(f"{v:.3f}" for v in lo),
                   "bounds max      " + " ".join(f"{v:.3f}" for v in hi), "memory          0.0 MiB"):
        assert needle in out, (needle, out)


def test_info_json(bundle, capsys):
    scene, path = bundle
    assert main(["info", str(path), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert (s["num_timesteps"], s["num_gaussians"], s["num_train_cameras"], s["num_test_cameras"]) == (4, 30, 3, 1)
    assert s["image_size"] == [64, 48] and s["language_field"] and s["latent_dim"] == 16
    assert s["foreground_share"] == pytest.approx(float(np.mean(scene.gaussians.foreground)))
    expected = sum(np.asarray(getattr(scene.gaussians, k)).nbytes for k in
                   ("means", "rotations", "log_scales", "opacity_logits", "colors", "foreground"))
    assert s["memory_bytes"] == expected and s["latents_bytes_on_disk"] == 4 * 30 * 16 * 4


def test_info_on_ply(tmp_path, capsys):
    write_ply_scene(random_scene(T=1, N=5, sh_degree=3), tmp_path / "one.ply")
    assert main(["info", str(tmp_path / "one.ply"), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["num_timesteps"] == 1 and s["color_model"] == "sh3" and not s["language_field"]


def test_info_demo_uses_the_synthetic_demo_bundle(bundle, capsys, monkeypatch):
    import fourlegs_engine.demo.synthetic as synthetic
    _, path = bundle
    calls = []
    monkeypatch.setattr(synthetic, "ensure_demo_bundle", lambda *a, **k: calls.append((a, k)) or path)
    assert main(["info", "--demo", "--json"]) == 0
    assert calls == [((), {})] and json.loads(capsys.readouterr().out)["num_gaussians"] == 30


@pytest.mark.parametrize("argv,needle", [([], "give either a scene PATH or --demo"),
                                         (["PATH", "--demo"], "give either a scene PATH or --demo"),
                                         (["MISSING"], "does not exist")])
def test_info_usage_errors(tmp_path, capsys, argv, needle):
    argv = [str(tmp_path / "x") if a in ("PATH", "MISSING") else a for a in argv]
    assert main(["info", *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fourlegs: error: ") and needle in err and err.count("\n") == 1


def test_bad_input_is_one_line_without_traceback(tmp_path):
    (tmp_path / "cloud.ply").write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n"
                                        "property float y\nproperty float z\nend_header\n0 0 0\n")
    proc = subprocess.run([sys.executable, "-m", "fourlegs_engine.commands.main", "info", str(tmp_path / "cloud.ply")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr == (f"fourlegs: error: {tmp_path / 'cloud.ply'}: vertex: is a point cloud, not Gaussian "
                           "splats: the vertices have no opacity, scale_0, scale_1, scale_2, rot_0, rot_1, rot_2, "
                           "rot_3 properties\n")


def test_info_reports_what_the_bundle_takes_on_disk_by_part(tmp_path, capsys):
    import os
    import shutil

    from fourlegs_engine.scene.disk_usage import bundle_disk_usage

    scene = random_scene(T=2, N=40)
    path = write_bundle(scene, tmp_path / "b")
    (path / "features").mkdir()
    (path / "features" / "t000000.npy").write_bytes(os.urandom(300_000))
    (path / "query").mkdir()
    (path / "query" / "big.bin").write_bytes(os.urandom(100_000))
    os.link(path / "query" / "big.bin", path / "query" / "same.bin")  # one file, two names
    usage = bundle_disk_usage(path)
    assert usage["features"] >= 300_000 and 100_000 <= usage["query"] < 200_000
    geometry = sum(os.lstat(p).st_blocks * 512 for p in path.iterdir() if p.is_file())
    assert usage["geometry"] == geometry
    assert usage["total"] == usage["geometry"] + usage["features"] + usage["query"]
    assert main(["info", str(path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["disk_bytes"] == usage
    assert main(["info", str(path)]) == 0
    line = [l for l in capsys.readouterr().out.splitlines() if l.startswith("on disk")][0]
    assert f"{usage['total'] / 2**20:.1f} MiB (features" in line and "query" in line and "geometry" in line
    shutil.rmtree(path / "features")
    assert "features" not in bundle_disk_usage(path)
