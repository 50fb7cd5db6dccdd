"""``fourlegs fit``: a synthetic capture fitted back, the priors, resume, bad input, the real capture."""
from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

import _fit_helpers as fh
from fourlegs_engine.commands.main import main
from fourlegs_engine.errors import ConfigMismatchError, InputError, OutputExistsError
from fourlegs_engine.fit import Capture, FitOptions, fit_capture
from fourlegs_engine.fit.losses import Priors, psnr
from fourlegs_engine.render import RasterOptions, rasterize
from fourlegs_engine.scene.bundle import load_bundle

BASKETBALL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "panoptic-basketball"
#: small but enough for the synthetic scene: 64×48, 8 cameras; the box moves 4 cm per timestep, which 12
#: steps cover at twice the default centre step (sized for the capture's ~38 steps per timestep)
SYNTH_OPTIONS = FitOptions(resolution_scale=1.0, first_iterations=80, iterations=12, init_background=1500,
                           background_stride=4, voxel=0.04, max_gaussians=4000, lr_means_later=0.0016)


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory) -> Path:
    return fh.write_capture(tmp_path_factory.mktemp("capture"), num_timesteps=3)


@pytest.fixture(scope="module")
def fitted(capture_dir, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("fit") / "scene"
    fit_capture(capture_dir, out, SYNTH_OPTIONS, progress=False)
    return out


def _render_bundle(scene, i, cam):
    g = scene.gaussians
    with torch.no_grad():
        return rasterize(torch.from_numpy(np.array(g.means[i])), torch.from_numpy(np.array(g.rotations[i])),
                         torch.from_numpy(np.array(g.log_scales)), torch.from_numpy(np.array(g.opacity_logits)),
                         cam, colors=torch.from_numpy(np.array(g.rgb(i))), options=RasterOptions())["rgb"]


@pytest.mark.slow
def test_synthetic_capture_fitted_back_matches_its_images(capture_dir, fitted):
    scene = load_bundle(fitted)
    assert scene.num_timesteps == 3 and scene.gaussians.foreground is not None
    assert 0 < scene.gaussians.foreground.mean() < 1
    cc = scene.metadata["color_correction"]
    # the colours are the average training camera's: its log-gains average to zero
    assert np.abs(np.mean(cc["cam_m"], axis=0)).max() < 1e-6
    scores = []
    for t in range(3):
        images = fh.load_images(capture_dir, "train", t)
        for cam in scene.cameras.cameras(t, "train"):
            m, c = np.array(cc["cam_m"][int(cam.name) - 1]), np.array(cc["cam_c"][int(cam.name) - 1])
            img = np.exp(m) * _render_bundle(scene, t, cam).double().numpy() + c
            scores.append(psnr(torch.from_numpy(img), torch.from_numpy(images[cam.name])))
    per_t = np.array(scores).reshape(3, -1).mean(1)
    assert per_t.min() >= 24.0, per_t
    # the held-out camera (never trained on) at the first timestep
    test_cam = scene.cameras.cameras(0, "test")[0]
    test_img = fh.load_images(capture_dir, "test", 0)[test_cam.name]
    assert psnr(_render_bundle(scene, 0, test_cam).double(), torch.from_numpy(test_img)) >= 20.0


@pytest.mark.slow
def test_rigid_motion_stays_rigid_and_is_recovered(fitted):
    """The foreground box moves rigidly: its fitted Gaussians keep their neighbour distances, and their
    centroid follows the true translation (12 iterations per timestep recover part of it)."""
    scene = load_bundle(fitted)
    g = scene.gaussians
    fg = np.asarray(g.foreground)
    x0, x2 = np.asarray(g.means[0])[fg].astype(np.float64), np.asarray(g.means[2])[fg].astype(np.float64)
    from scipy.spatial import cKDTree
    _, nb = cKDTree(x0).query(x0, k=9)
    d0 = np.linalg.norm(x0[nb[:, 1:]] - x0[:, None], axis=-1)
    d2 = np.linalg.norm(x2[nb[:, 1:]] - x2[:, None], axis=-1)
    assert np.median(np.abs(d2 - d0)) < 0.015  # metres; the box is 50 cm wide and moves 8 cm
    _, true_t = fh.rigid_motion(2)
    shift = x2.mean(0) - x0.mean(0)
    assert shift @ true_t / (np.linalg.norm(shift) * np.linalg.norm(true_t)) > 0.9
    assert 0.35 * np.linalg.norm(true_t) < np.linalg.norm(shift) < 1.3 * np.linalg.norm(true_t)
    bg = ~fg
    assert np.array_equal(np.asarray(g.means[0])[bg], np.asarray(g.means[2])[bg])  # background held still


def test_priors_vanish_for_rigid_motion_and_pull_a_deformation_back():
    g = torch.Generator().manual_seed(0)
    x0 = torch.randn(60, 3, generator=g, dtype=torch.float64) * 0.05
    q0 = torch.nn.functional.normalize(torch.randn(60, 4, generator=g, dtype=torch.float64), dim=-1)
    from scipy.spatial import cKDTree
    dist, nb = cKDTree(x0.numpy()).query(x0.numpy(), k=7)
    priors = Priors(torch.from_numpy(nb[:, 1:]), torch.from_numpy(np.exp(-2000 * dist[:, 1:] ** 2)),
                    torch.from_numpy(dist[:, 1:]))
    R = torch.tensor(fh._rot_y(0.3), dtype=torch.float64)
    qR = torch.tensor(fh._quat_from_matrix(fh._rot_y(0.3)), dtype=torch.float64)
    from fourlegs_engine.fit.losses import quat_multiply
    x1 = x0 @ R.T + torch.tensor([0.1, -0.2, 0.05], dtype=torch.float64)
    q1 = quat_multiply(qR.expand_as(q0), q0)
    rigid = priors(x1, q1, x0, q0)
    assert all(float(v) < 1e-9 for v in rigid.values()), rigid
    # a shear is not rigid: every term sees it, and descending the priors alone undoes most of it
    shear = torch.eye(3, dtype=torch.float64)
    shear[0, 1] = 0.4
    x_bad = (x1 @ shear.T).clone().requires_grad_(True)
    before = priors(x_bad, q1, x0, q0)
    assert float(before["rigid"].detach()) > 1e-4 and float(before["iso"].detach()) > 1e-4
    opt = torch.optim.Adam([x_bad], lr=1e-3)
    for _ in range(300):
        terms = priors(x_bad, q1, x0, q0)
        loss = terms["rigid"] + terms["iso"]
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = priors(x_bad.detach(), q1, x0, q0)
    assert float(after["rigid"]) < 0.2 * float(before["rigid"].detach())


def test_killed_fit_resumes_to_the_identical_bundle(capture_dir, tmp_path, monkeypatch):
    # one intra-op thread: multi-threaded BLAS reductions may sum in a different order run to run
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        _kill_and_resume(capture_dir, tmp_path)
    finally:
        torch.set_num_threads(threads)


def _kill_and_resume(capture_dir, tmp_path):
    opts = FitOptions(resolution_scale=0.5, first_iterations=20, iterations=4, init_background=400,
                      background_stride=4, voxel=0.05)
    fit_capture(capture_dir, tmp_path / "straight", opts, progress=False)

    def kill_after_timestep_1(ev):
        if ev.kind == "timestep" and ev.timestep == 1:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        fit_capture(capture_dir, tmp_path / "resumed", opts, progress=kill_after_timestep_1)
    work = tmp_path / ".resumed.fit"
    assert not (tmp_path / "resumed").exists()
    assert sorted(p.name for p in work.glob("t*.npz")) == ["t000000.npz", "t000001.npz"]
    events = []
    fit_capture(capture_dir, tmp_path / "resumed", opts, progress=events.append)
    resumed = [e.timestep for e in events if e.kind == "timestep" and e.resumed]
    assert resumed == [0, 1]
    assert not work.exists()
    for name in ("means", "rotations", "log_scales", "opacity_logits", "colors", "foreground"):
        a = np.load(tmp_path / "straight" / f"{name}.npy")
        b = np.load(tmp_path / "resumed" / f"{name}.npy")
        assert a.dtype == b.dtype and np.array_equal(a, b), name
    # other options on top of the partial fit are refused, the finished output is not overwritten
    with pytest.raises(OutputExistsError):
        fit_capture(capture_dir, tmp_path / "resumed", opts, progress=False)


def test_partial_fit_with_other_options_is_refused(capture_dir, tmp_path):
    opts = FitOptions(resolution_scale=0.5, first_iterations=3, iterations=1, init_background=200, voxel=0.06)

    def stop(ev):
        if ev.kind == "timestep":
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        fit_capture(capture_dir, tmp_path / "s", opts, progress=stop)
    with pytest.raises(ConfigMismatchError, match="overwrite"):
        fit_capture(capture_dir, tmp_path / "s", FitOptions(resolution_scale=0.5, first_iterations=4), progress=False)


def _copy(capture_dir: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "ds"
    shutil.copytree(capture_dir, dst)
    return dst


def test_bad_datasets_give_one_clear_error(capture_dir, tmp_path, capsys):
    ds = _copy(capture_dir, tmp_path)
    (ds / "ims" / "3" / "000001.png").unlink()
    with pytest.raises(InputError, match=r"ims/3/000001.png: missing frame \(timestep 1, camera 3\)"):
        fit_capture(ds, tmp_path / "o1", FitOptions(first_iterations=1), progress=False)
    assert main(["fit", str(ds), "-o", str(tmp_path / "o1")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "missing frame" in err[0]
    assert not (tmp_path / "o1").exists() and not (tmp_path / ".o1.fit").exists()
    # a frame restricted away by --timesteps is not needed
    fit_capture(ds, tmp_path / "o2", FitOptions(timesteps=(0, 1), first_iterations=1, init_background=100, voxel=0.08),
                progress=False)

    ds2 = _copy(capture_dir, tmp_path / "b")
    meta = json.loads((ds2 / "train_meta.json").read_text())
    meta["w2c"][2][4][0][0] = 3.0  # not a rotation
    (ds2 / "train_meta.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match=r"train_meta.json: w2c\[2\]\[4\]: is not a rigid transform"):
        Capture(ds2)

    ds3 = _copy(capture_dir, tmp_path / "c")
    from PIL import Image
    Image.new("RGB", (65, 48)).save(ds3 / "ims" / "2" / "000000.png")
    with pytest.raises(InputError, match=r"ims/2/000000.png: is 65x48 but the metadata says 64x48"):
        fit_capture(ds3, tmp_path / "o3", FitOptions(first_iterations=1), progress=False)

    ds4 = _copy(capture_dir, tmp_path / "d")
    meta = json.loads((ds4 / "train_meta.json").read_text())
    meta["fn"] = meta["fn"][:2]
    (ds4 / "train_meta.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match=r"train_meta.json: fn: has 2 timesteps, k has 3"):
        Capture(ds4)
    with pytest.raises(InputError, match="timesteps"):
        fit_capture(capture_dir, tmp_path / "o5", FitOptions(timesteps=(2, 9)), progress=False)
    with pytest.raises(InputError, match="no train camera '42'"):
        fit_capture(capture_dir, tmp_path / "o6", FitOptions(cameras=("42",)), progress=False)


def test_cli_fit_writes_a_bundle_that_info_reads(capture_dir, tmp_path, capsys):
    out = tmp_path / "cli"
    assert main(["fit", str(capture_dir), "-o", str(out), "--timesteps", "1:3", "--cameras", "1,2,3,5,6,7",
                 "--resolution-scale", "0.5", "--first-iterations", "5", "--iterations", "2",
                 "--init-background", "300"]) == 0
    scene = load_bundle(out)
    assert scene.num_timesteps == 2 and scene.metadata["first_timestep"] == 1
    assert [c.name for c in scene.cameras.cameras(0, "train")] == ["1", "2", "3", "5", "6", "7"]
    assert scene.cameras.cameras(0, "train")[0].width == fh.WIDTH  # full-resolution cameras in the bundle
    from fourlegs_engine.fit.evaluate import evaluate_test_views

    metrics = evaluate_test_views(out, capture_dir, resolution_scale=0.5)
    closing = capsys.readouterr().out.strip().splitlines()[-1]  # the held-out cameras' PSNR closes the run
    assert closing.startswith(f"test cameras {', '.join(metrics.cameras)}: PSNR {metrics.mean_psnr:.2f} dB, "
                              f"SSIM {metrics.mean_ssim:.3f} (mean over 2 timesteps"), closing
    assert main(["info", str(out)]) == 0
    assert "foreground" in capsys.readouterr().out
    assert main(["fit", str(capture_dir), "-o", str(out), "--timesteps", "1:3"]) == 2
    assert "already exists" in capsys.readouterr().err


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (and gsplat: pip install 'fourlegs[cuda]')")
def test_fit_on_cuda_through_gsplat_matches_its_images(capture_dir, tmp_path):
    from fourlegs_engine.render.backends import gsplat_available
    if not gsplat_available():
        pytest.skip("gsplat is not installed (pip install 'fourlegs[cuda]')")
    fit_capture(capture_dir, tmp_path / "gpu", replace(SYNTH_OPTIONS, device="cuda", first_iterations=300,
                                                       iterations=40), progress=False)
    scene = load_bundle(tmp_path / "gpu")
    images = fh.load_images(capture_dir, "train", 2)
    cams = scene.cameras.cameras(2, "train")
    scores = [psnr(_render_bundle(scene, 2, cam).double(), torch.from_numpy(images[cam.name])) for cam in cams]
    assert np.mean(scores) >= 24.0, scores


@pytest.mark.slow
@pytest.mark.skipif(not BASKETBALL.is_dir(), reason=f"the shared Panoptic capture is not at {BASKETBALL}")
def test_basketball_cameras_at_low_resolution_reach_a_stated_psnr(tmp_path):
    """Six cameras, two timesteps at 80×45: the fitted scene reproduces its training views."""
    cams = ("1", "5", "9", "14", "20", "25")
    opts = FitOptions(timesteps=(0, 2), cameras=cams, resolution_scale=0.125, first_iterations=80, iterations=6,
                      init_background=3000, background_stride=3, voxel=0.04, max_gaussians=8000)
    fit_capture(BASKETBALL, tmp_path / "bb", opts, progress=False)
    scene = load_bundle(tmp_path / "bb")
    cap = Capture(BASKETBALL)
    cc = scene.metadata["color_correction"]
    scores = []
    for i, t in enumerate((0, 1)):
        for j, cam in enumerate(scene.cameras.cameras(i, "train")):
            small = cam.scaled(0.125)
            img = _render_bundle(scene, i, small).double().numpy()
            img = np.exp(cc["cam_m"][j]) * img + np.array(cc["cam_c"][j])
            target = cap.load_image("train", t, cap.camera_indices("train", [cam.name])[0], (small.width, small.height))
            scores.append(psnr(torch.from_numpy(img), torch.from_numpy(target).double()))
    assert np.mean(scores) >= 22.0, scores
