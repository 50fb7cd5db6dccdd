"""Extraction, autoencoder training and distillation on a micro scene: lift vs least squares, the
sparse rendering map vs the rasterizer, determinism, resume after a real kill, config-change refusal,
sharding and the LanguageField."""
from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from _language_helpers import kill_after_first_step, micro_bundle, one_thread  # noqa: F401 (one_thread: autouse fixture)
from fourlegs_engine.commands.main import main
from fourlegs_engine.errors import ConfigMismatchError, InputError
from fourlegs_engine.language.autoencoder import AETrainOptions, train_autoencoder
from fourlegs_engine.language.distill import DistillOptions, distill_scene
import fourlegs_engine.demo  # noqa: F401 (registers the "simulated" encoder)
from fourlegs_engine.language.encoders import get_encoder
from fourlegs_engine.language.latent_solvers import lift_latents, optimize_latents
from fourlegs_engine.language.view_operator import view_operator
from fourlegs_engine.language.extract import ExtractOptions, check_features, extract_features
from fourlegs_engine.language.field import LanguageField
from fourlegs_engine.render import rasterize
from fourlegs_engine.scene.bundle import load_bundle
from fourlegs_engine.scene.camera import Camera
from fourlegs_engine.scene.gaussians import GaussianFrame

AE_ARGS = ["--epochs", "2", "--samples", "2048", "--ae-batch-size", "256"]


@pytest.fixture(scope="module")
def prepared(tmp_path_factory) -> Path:
    """Micro bundle with features extracted and the autoencoder trained (through the CLI)."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    path = micro_bundle(tmp_path_factory.mktemp("lang") / "micro")
    assert main(["extract", str(path), "--no-progress"]) == 0
    assert main(["train-ae", str(path), *AE_ARGS]) == 0
    torch.set_num_threads(old)
    return path


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


# ------------------------------------------------------------------------------ rendering map
def _separated_frame(n: int = 5) -> tuple[GaussianFrame, Camera]:
    means = torch.tensor([[x, 0.0, 0.0] for x in np.linspace(-1.6, 1.6, n)], dtype=torch.float32)
    frame = GaussianFrame(means=means, rotations=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                          log_scales=torch.full((n, 3), math.log(0.08)),
                          opacity_logits=torch.linspace(0.5, 4.0, n))
    cam = Camera.look_at((0, -4.0, 0), (0, 0, 0), width=64, height=24, fov_y=math.radians(30))
    return frame, cam


def test_lift_equals_least_squares_when_each_pixel_sees_one_gaussian():
    frame, cam = _separated_frame()
    n = frame.num_gaussians
    args = (frame.means, frame.rotations, frame.log_scales, frame.opacity_logits, cam)
    op = view_operator(frame, cam)
    per_pixel = torch.bincount(op.A.crow_indices().diff(), minlength=3)
    assert per_pixel[2:].sum() == 0 and per_pixel[1] > 20     # precondition: <= 1 Gaussian per pixel
    # the rendering matrix from the rasterizer's feature output (an independent path)
    A = rasterize(*args, features=torch.eye(n, dtype=torch.float64), outputs=("features",))["features"]
    A = A.reshape(-1, n).double()
    rng = np.random.default_rng(0)
    teacher = torch.from_numpy(rng.normal(size=(A.shape[0], 8)))
    ls = torch.linalg.lstsq(A, teacher).solution
    ls = ls / ls.norm(dim=1, keepdim=True)
    lift = lift_latents([op], [teacher.float()]).double()
    torch.testing.assert_close(lift, ls, atol=2e-5, rtol=1e-4)


def test_view_operator_matches_the_rasterizer_values_and_gradients(prepared):
    scene = load_bundle(prepared)
    frame = scene.gaussians.at(1)
    cam = scene.cameras.cameras(1)[0]
    op = view_operator(frame, cam)
    feats = torch.randn(frame.num_gaussians, 6, requires_grad=True)
    ras = rasterize(frame.means, frame.rotations, frame.log_scales, frame.opacity_logits, cam,
                    features=feats, outputs=("features",))["features"].reshape(-1, 6)
    mine = op.render(feats)
    torch.testing.assert_close(mine, ras, atol=1e-5, rtol=1e-5)
    g = torch.randn_like(ras)
    (gr,) = torch.autograd.grad((ras * g).sum(), feats)
    (gm,) = torch.autograd.grad((mine * g).sum(), feats)
    torch.testing.assert_close(gm, gr, atol=1e-5, rtol=1e-5)
    # background pixels render zero; weights per pixel sum to alpha <= 1
    alpha = op.render(torch.ones(frame.num_gaussians, 1))
    assert float(alpha.max()) <= 1.0 + 1e-6


def test_optimize_decreases_the_loss_and_is_deterministic():
    frame, cam = _separated_frame()
    op = view_operator(frame, cam)
    teacher = torch.nn.functional.normalize(torch.randn(64 * 24, 16), dim=1)
    nbr = torch.arange(5)[:, None].repeat(1, 2)
    nbr[:, 1] = (nbr[:, 0] + 1) % 5
    cfg = DistillOptions(mode="optimize", iterations=60, lr_latents=0.05).check()
    a, loss_a = optimize_latents([op], [teacher], nbr, cfg, seed=3)
    b, loss_b = optimize_latents([op], [teacher], nbr, cfg, seed=3)
    assert torch.equal(a, b) and loss_a == loss_b
    first = float((op.render(torch.zeros(5, 16)) - teacher).abs().mean())
    assert loss_a < first
    for smoothing in ("none", "blur"):
        c, _ = optimize_latents([op], [teacher], nbr, DistillOptions(mode="optimize", iterations=5,
                                                                   smoothing=smoothing).check(), seed=3)
        assert c.shape == (5, 16) and torch.isfinite(c).all()


def test_neighbour_mean_equals_the_blur_gather():
    from fourlegs_engine.language.attention import knn_indices, neighbour_blur, neighbour_mean
    g = torch.Generator().manual_seed(0)
    pts, lat = torch.randn(200, 3, generator=g), torch.randn(200, 16, generator=g)
    nb = knn_indices(pts, 7)
    torch.testing.assert_close(neighbour_mean(lat, nb), neighbour_blur(lat, nb))
    assert neighbour_mean(lat[:0], nb[:0]).shape == (0, 16)


def test_lift_knn_blur_option(prepared, tmp_path):
    """lift_smoothing="blur": the plain lift averaged over each Gaussian's kNN and re-normalized; the same
    through the splat path (lift) and the weights path (lift+refine, 0 steps); hashed only when on."""
    from fourlegs_engine.language.attention import knn_indices
    scene = load_bundle(prepared)
    plain = distill_scene(scene, mode="lift", out_dir=tmp_path / "plain", timesteps=[1], merge=False)
    blur = distill_scene(scene, mode="lift", lift_smoothing="blur", neighbours=6, out_dir=tmp_path / "blur",
                         timesteps=[1], merge=False)
    refine0 = distill_scene(scene, mode="lift+refine", iterations=0, lift_smoothing="blur", neighbours=6,
                            out_dir=tmp_path / "refine0", timesteps=[1], merge=False)
    def load(r):
        return torch.from_numpy(np.load(Path(r.out_dir) / "steps" / "t000001.npy").astype(np.float32))

    z0, z1, z2 = load(plain), load(blur), load(refine0)
    nb = knn_indices(scene.gaussians.at(1).means, 6)
    expected = torch.nn.functional.normalize(z0[nb].mean(1), dim=1)
    torch.testing.assert_close(z1, expected, atol=3e-3, rtol=0)       # float16 storage of both
    torch.testing.assert_close(z2, z1, atol=3e-3, rtol=0)
    assert not torch.equal(z1, z0)
    filled = (z0.norm(dim=1) == 0) & (z0[nb].norm(dim=2) > 0).any(1)  # unseen, with a seen neighbour
    assert bool((z1[filled].norm(dim=1) > 0.99).all())
    # existing fields keep their hash: the option is absent from the config while off
    assert "lift_smoothing" not in DistillOptions(mode="lift").to_dict()
    assert "neighbours" not in DistillOptions(mode="lift").to_dict()
    on = DistillOptions(mode="lift", lift_smoothing="blur", neighbours=6).to_dict()
    assert on["lift_smoothing"] == "blur" and on["neighbours"] == 6
    assert blur.config_hash != plain.config_hash
    with pytest.raises(InputError, match="lift-smoothing"):
        DistillOptions(mode="optimize", lift_smoothing="blur").check()
    with pytest.raises(InputError, match="lift-smoothing"):
        DistillOptions(mode="lift", lift_smoothing="attention").check()
    path = _copy(prepared, tmp_path / "cli")
    assert main(["distill", str(path), "--lift-smoothing", "blur", "--neighbours", "6", "--no-progress"]) == 0
    assert load_bundle(path).language["config"]["lift_smoothing"] == "blur"


# ------------------------------------------------------------------------------- the pipeline
def test_pipeline_outputs_and_language_field(prepared, tmp_path):
    path = _copy(prepared, tmp_path / "b")
    report = check_features(load_bundle(path))
    assert report["complete"] and report["missing"] == []
    assert main(["distill", str(path), "--no-progress"]) == 0
    scene = load_bundle(path)
    lang = scene.language
    assert lang["mode"] == "lift" and lang["encoder"] == "simulated" and lang["latent_dim"] == 128
    assert lang["canonical_phrases"] == ["object", "things", "stuff", "texture"]
    assert scene.gaussians.latents.shape == (4, scene.num_gaussians, 128)
    assert scene.gaussians.latents.dtype == np.float16
    field = LanguageField.open(path)
    assert field.latent_dim == 128 and field.encoder_name == "simulated"
    z = field.latents_at(2)
    seen = z.norm(dim=1) > 0
    assert seen.float().mean() > 0.5
    torch.testing.assert_close(z[seen].norm(dim=1), torch.ones(int(seen.sum())), atol=2e-3, rtol=0)
    out = field.decode(z[:10])
    assert out.shape == (10, 768)
    torch.testing.assert_close(out.norm(dim=1), torch.ones(10))
    assert torch.isfinite(field.decode(torch.full((2, 128), float("nan")))).all()
    # the lifted field separates the labels: the decoded latents are closest to their own label text
    enc = get_encoder("simulated", scene=scene)
    text = enc.encode_text(scene.metadata["labels"])
    labels = torch.from_numpy(np.array(scene.gaussians.labels[2], dtype=np.int64))
    pred = (field.decode(z[seen]) @ text.T).argmax(1)
    assert float((pred == labels[seen]).float().mean()) > 0.6


def test_shards_merge_to_the_single_worker_result(prepared, tmp_path):
    single = _copy(prepared, tmp_path / "single")
    split = _copy(prepared, tmp_path / "split")
    distill_scene(load_bundle(single), mode="lift")
    assert main(["distill", str(split), "--shard", "0/2", "--no-progress"]) == 0
    assert not (split / "language" / "latents.npy").exists()
    assert main(["distill", str(split), "--check"]) == 1            # timesteps 1, 3 missing
    assert main(["distill", str(split), "--timesteps", "1:4", "--shard", "0/2", "--no-progress"]) == 0
    assert main(["distill", str(split), "--timesteps", "3", "--no-progress"]) == 0
    np.testing.assert_array_equal(np.load(split / "language" / "latents.npy"),
                                  np.load(single / "language" / "latents.npy"))
    assert main(["distill", str(split), "--check"]) == 0


def test_config_changes_are_refused_unless_overwrite(prepared, tmp_path, capsys):
    path = _copy(prepared, tmp_path / "b")
    scene = load_bundle(path)
    distill_scene(scene, mode="lift", timesteps="0:2")
    with pytest.raises(ConfigMismatchError, match="teacher_stride"):
        distill_scene(scene, mode="lift", teacher_stride=1, timesteps="0:2")
    assert main(["distill", str(path), "--teacher-stride", "1"]) == 2  # one-line error from the CLI
    assert "another configuration" in capsys.readouterr().err
    res = distill_scene(scene, mode="lift", teacher_stride=1, overwrite=True)
    assert res.latents is not None and len(res.timings) == 4
    with pytest.raises(ConfigMismatchError):
        distill_scene(load_bundle(path), mode="lift")                  # merged latents of stride 1
    enc = get_encoder("simulated", scene=scene)
    with pytest.raises(ConfigMismatchError, match="ratios"):
        extract_features(scene, enc, ExtractOptions(ratios=(0.2, 0.5)))
    with pytest.raises(ConfigMismatchError):
        train_autoencoder(scene, AETrainOptions(epochs=3, samples=2048, batch_size=256))
    with pytest.raises(InputError, match="--mode"):
        DistillOptions(mode="magic").check()


def test_autoencoder_resumes_from_its_checkpoint(prepared, tmp_path):
    a = _copy(prepared, tmp_path / "a")
    b = _copy(prepared, tmp_path / "b")
    cfg = AETrainOptions(epochs=2, samples=1024, heldout_samples=256, batch_size=256)
    full = train_autoencoder(load_bundle(a), cfg, overwrite=True)
    assert train_autoencoder(load_bundle(b), cfg, overwrite=True, stop_after_epoch=1) == {"stopped_after_epoch": 1}
    resumed = train_autoencoder(load_bundle(b), cfg)
    assert resumed["loss_history"] == full["loss_history"]
    assert resumed["heldout_cosine"] == full["heldout_cosine"]
    assert full["heldout_camera"] == 2 and 0.0 < full["heldout_cosine"] <= 1.0
    # per epoch: what it bought (held-out cosine; the last one is the report's) and what it cost
    assert resumed["cosine_history"] == full["cosine_history"] and len(full["cosine_history"]) == 2
    assert full["cosine_history"][-1] == pytest.approx(full["heldout_cosine"], abs=1e-6)
    assert len(resumed["epoch_seconds"]) == 2 and all(s > 0 for s in resumed["epoch_seconds"])


def test_resume_after_a_real_kill_gives_the_uninterrupted_result(prepared, tmp_path):
    reference = _copy(prepared, tmp_path / "ref")
    killed = _copy(prepared, tmp_path / "killed")
    args = ["--mode", "optimize", "--iterations", "20", "--no-progress"]
    # both runs in fresh processes with the same thread settings (floating-point reductions depend on them)
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    code = ("import sys, torch; torch.set_num_threads(1); from fourlegs_engine.commands.main import main; "
            "sys.exit(main(sys.argv[1:]))")
    subprocess.run([sys.executable, "-c", code, "distill", str(reference), *args], env=env, check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=300)
    steps = killed / "language" / "steps"
    kill_after_first_step([sys.executable, "-c", code, "distill", str(killed), *args], env, steps)
    done = [p for p in steps.iterdir() if p.suffix == ".npy" and not p.name.startswith(".")]
    assert 1 <= len(done) < 4
    assert not (killed / "language" / "latents.npy").exists()
    subprocess.run([sys.executable, "-c", code, "distill", str(killed), *args], env=env, check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=300)
    np.testing.assert_array_equal(np.load(killed / "language" / "latents.npy"),
                                  np.load(reference / "language" / "latents.npy"))
    assert not any(p.name.endswith(".part.npy") for p in (killed / "language").rglob("*"))


def test_teacher_latents_at_reduced_resolution_and_strides(prepared):
    from fourlegs_engine.language.autoencoder import load_encoder
    from fourlegs_engine.language.latent_solvers import teacher_latents
    from fourlegs_engine.language.extract import feature_store, load_step_features
    scene = load_bundle(prepared)
    enc = load_encoder(prepared / "language" / "encoder.pt")
    feats, layouts, offsets = load_step_features(scene, feature_store(scene), 0)
    lay = layouts[0]
    crops = feats[:lay.num_crops]
    full = teacher_latents(enc, lay, crops, 1)
    assert full.shape == (lay.width * lay.height, 128)
    torch.testing.assert_close(full.norm(dim=1), torch.ones(full.shape[0]))
    # the encoder applied to the interpolated 768-d pixel feature (no first-layer split) agrees
    from fourlegs_engine.language.pyramid import pixel_features
    direct = enc(pixel_features(lay, torch.from_numpy(np.array(crops, dtype=np.float32))).reshape(-1, 768))
    torch.testing.assert_close(full, direct, atol=1e-5, rtol=1e-4)
    for stride in (2, 3):
        approx = teacher_latents(enc, lay, crops, stride)
        cos = (approx * full).sum(1)
        assert float(cos.mean()) > 0.95 and torch.isfinite(approx).all()
    half = teacher_latents(enc, lay, crops, 1, lay.width // 2, lay.height // 2)
    assert half.shape == ((lay.width // 2) * (lay.height // 2), 128)
    res = distill_scene(scene, mode="lift", view_scale=0.5, out_dir=prepared.parent / "half", timesteps=[0])
    lat = np.load(Path(res.out_dir) / "steps" / "t000000.npy").astype(np.float32)
    norms = np.linalg.norm(lat, axis=1)
    assert np.all((np.abs(norms - 1) < 2e-3) | (norms == 0)) and (norms > 0).mean() > 0.5


def test_rgb_encoder_path_with_a_tiny_viclip(tmp_path):
    """RGB frames -> 8-frame crop tubes -> resized, CLIP-normalized -> ViCLIP; then train-ae and lift."""
    from _viclip_helpers import randomize_, tiny_config, write_tiny_vocab
    from fourlegs_engine.language.extract import feature_store
    from fourlegs_engine.language.frames import FrameSource
    from fourlegs_engine.language.pyramid import crop_layout, resize_crops, scale_crops
    from fourlegs_engine.language.viclip import BPETokenizer, ViCLIPEncoder, ViCLIPModel
    torch.manual_seed(0)
    model = randomize_(ViCLIPModel(tiny_config()).eval(), seed=5)
    enc = ViCLIPEncoder(model, BPETokenizer(write_tiny_vocab(tmp_path / "bpe.txt.gz")), batch_size=64)
    path = micro_bundle(tmp_path / "rgb", T=2, cameras=2)
    scene = load_bundle(path)
    cfg = ExtractOptions(ratios=(0.4, 0.6), batch_size=50)
    report = extract_features(scene, enc, cfg)
    assert report.timesteps_done == [0, 1]
    store = feature_store(scene)
    feats = store.load(1)
    layout = crop_layout(32, 18, (0.4, 0.6))
    assert feats.shape == (2 * layout.num_crops, enc.dim) and feats.dtype == np.float16
    # one crop recomputed by hand: camera 1, scale 1, crop 3
    tube = FrameSource(scene, "rgb").tube(1, 1)
    assert tube.shape == (8, 3, 18, 32) and float(tube.min()) >= 0 and float(tube.max()) <= 1
    g = layout.scales[1]
    clip = resize_crops(scale_crops(tube, g)[3:4], enc.image_size, clip_normalize=True)
    expected = enc.encode_video(clip)[0].numpy()
    got = feats[layout.num_crops + g.offset + 3].astype(np.float32)
    np.testing.assert_allclose(got, expected, atol=2e-3)
    ae = train_autoencoder(scene, AETrainOptions(epochs=1, samples=512, heldout_samples=64, batch_size=128))
    assert ae["heldout_camera"] == 1
    res = distill_scene(scene, mode="lift")
    assert LanguageField.open(path).decode(torch.zeros(3, 128)).shape == (3, enc.dim)
    assert res.latents is not None


def test_distill_settings_come_either_as_a_config_or_as_keywords():
    """A keyword beside ``config=`` used to be dropped without a word."""
    with pytest.raises(InputError, match=r"either as config= or as keywords.*iterations, view_scale"):
        distill_scene(object(), config=DistillOptions(mode="lift"), iterations=5, view_scale=0.5)
    with pytest.raises(InputError, match=r"also given: mode"):
        distill_scene(object(), "optimize", config=DistillOptions(mode="lift"))
