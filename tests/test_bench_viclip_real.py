"""``fourlegs bench viclip --dataset``: the real-frames ViCLIP cost bench on tiny captures and configs."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from PIL import Image

from _viclip_helpers import tiny_config
from fourlegs_bench import viclip_real
from fourlegs_bench.viclip_real import (bench_viclip_real, parse_subsets, preprocess_camera_timestep,
                                    real_report_markdown, sample_clips, write_real_report)
from fourlegs_engine.errors import InputError, OutputExistsError
from fourlegs_engine.language.pyramid import CLIP_MEAN, CLIP_STD, crop_layout, pyramid_ratios

BASKETBALL = Path(__file__).resolve().parents[2] / "shared" / "data" / "panoptic-basketball"
WIDTH, HEIGHT, STEPS = 64, 36, 10


def write_noise_capture(root: Path, cameras=("1", "2"), steps: int = STEPS) -> Path:
    """A Dynamic 3D Gaussians layout of random frames (lossless PNG): only the frames matter here."""
    rng = np.random.default_rng(0)
    K = [[50.0, 0, WIDTH / 2], [0, 50.0, HEIGHT / 2], [0, 0, 1]]
    meta = {"w": WIDTH, "h": HEIGHT, "k": [], "w2c": [], "fn": [], "cam_id": []}
    for t in range(steps):
        meta["k"].append([K for _ in cameras])
        meta["w2c"].append([np.eye(4).tolist() for _ in cameras])
        meta["fn"].append([f"{c}/{t:06d}.png" for c in cameras])
        meta["cam_id"].append([int(c) for c in cameras])
        for c in cameras:
            (root / "ims" / c).mkdir(parents=True, exist_ok=True)
            pixels = rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)
            Image.fromarray(pixels).save(root / "ims" / c / f"{t:06d}.png")
    (root / "train_meta.json").write_text(json.dumps(meta))
    return root


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory) -> Path:
    return write_noise_capture(tmp_path_factory.mktemp("capture"))


@pytest.fixture(scope="module")
def report(capture_dir) -> dict:
    return bench_viclip_real(capture_dir, size=tiny_config(), cameras=("1", "2"), timesteps=(0, 9),
                             dtypes=("float32", "bfloat16"), batch_sizes=(1, 3), clips=5, phrases=3,
                             subsets="all:27x150,two cameras:2x10")


def test_real_bench_counts_every_clip_of_the_pyramid_and_extrapolates_its_own_figures(report):
    layout = crop_layout(WIDTH, HEIGHT, pyramid_ratios())
    assert report["clips_per_camera_timestep"] == layout.num_crops == sum(report["clips_per_scale"])
    assert report["paper_clips_per_camera_timestep"] is None  # 572 is the paper's figure at 640x360 only
    assert report["random_weights"] and "random weights" in report["weights"]
    # 5 clips spread evenly over the 2 cameras x 2 timesteps (4 x num_crops clips in all) reach each of them
    assert len(report["sampled_clips"]) == 5
    assert {(s["camera"], s["timestep"]) for s in report["sampled_clips"]} == {("1", 0), ("2", 0), ("1", 9), ("2", 9)}
    pre = report["preprocess"]
    assert pre["decode_seconds_per_frame"] > 0 and pre["crop_resize_seconds_per_camera_timestep"] > 0
    rows = {(r["dtype"], r["batch_size"], r["reference"]): r for r in report["rows"]}
    assert set(rows) == {("float64", 1, True), ("float32", 1, False), ("float32", 3, False),
                         ("bfloat16", 1, False), ("bfloat16", 3, False)}
    assert all(r["supported"] and r["finite"] and r["clips"] == 5 for r in rows.values())
    assert rows["float64", 1, True]["video_min_cosine"] == pytest.approx(1.0, abs=1e-12)
    for batch in (1, 3):
        fp32, bf16 = rows["float32", batch, False], rows["bfloat16", batch, False]
        assert fp32["video_min_cosine"] > 1 - 1e-6 and fp32["text_min_cosine"] > 1 - 1e-6
        assert 0.9 < bf16["video_min_cosine"] < fp32["video_min_cosine"]
    n = report["clips_per_camera_timestep"]
    for r in rows.values():
        per_ct = pre["decode_seconds_per_frame"] + pre["crop_resize_seconds_per_camera_timestep"] + \
            n * r["seconds_per_clip"]
        assert r["seconds_per_camera_timestep"] == pytest.approx(per_ct, rel=1e-12)
        assert r["extrapolated_hours"]["all"] == pytest.approx(27 * 150 * per_ct / 3600, rel=1e-12)
        assert r["extrapolated_hours"]["two cameras"] == pytest.approx(20 * per_ct / 3600, rel=1e-12)
        cpu_ct = pre["decode_cpu_seconds_per_frame"] + pre["crop_resize_cpu_seconds_per_camera_timestep"] + \
            n * r["cpu_seconds_per_clip"]
        assert r["extrapolated_cpu_hours"]["all"] == pytest.approx(27 * 150 * cpu_ct / 3600, rel=1e-12)


def test_real_bench_writes_table_json_and_plot_and_keeps_existing_outputs(report, tmp_path):
    paths = write_real_report(report, tmp_path / "real", command="fourlegs bench viclip --dataset X")
    assert [p.suffix for p in paths] == [".json", ".md", ".png"] and all(p.stat().st_size > 0 for p in paths)
    saved = json.loads(paths[0].read_text())
    assert "_thumbnails" not in saved and saved["command"] == "fourlegs bench viclip --dataset X"
    assert saved["rows"] == json.loads(json.dumps(report["rows"]))
    table = paths[1].read_text()
    assert "RANDOM WEIGHTS" in table and "| bfloat16 | 3 |" in table and "float64 (reference) | 1 |" in table
    assert f"= **{report['clips_per_camera_timestep']} clips per camera-timestep**" in table
    assert "all (27 cams × 150 t)" in table
    with Image.open(paths[2]) as image:
        assert image.size[0] > 1000
    with pytest.raises(OutputExistsError):
        write_real_report(report, tmp_path / "real", overwrite=False)


def test_the_clips_are_extractions_crops_in_layout_order():
    """With no resize, clip i is exactly the zero-padded window of its scale's (iy, ix), CLIP-normalized."""
    gen = torch.Generator().manual_seed(1)
    tube = torch.rand(8, 3, 36, 64, generator=gen, dtype=torch.float64).float()
    layout = crop_layout(64, 36, (0.5,))
    grid = layout.scales[0]
    k, s, p = grid.kernel, grid.stride, grid.padding
    picks = [0, grid.nx + 1, grid.num_crops - 1]
    kept, produced = preprocess_camera_timestep(tube, layout, crop_size=k, keep=picks, batch_size=4)
    assert produced == layout.num_crops and sorted(kept) == picks
    padded = F.pad(tube, (p, p, p, p))
    mean, std = torch.tensor(CLIP_MEAN).view(1, 3, 1, 1), torch.tensor(CLIP_STD).view(1, 3, 1, 1)
    for index in picks:
        iy, ix = divmod(index, grid.nx)
        window = padded[:, :, iy * s:iy * s + k, ix * s:ix * s + k]
        torch.testing.assert_close(kept[index], (window - mean) / std, rtol=0, atol=1e-6)


def test_sampled_clips_are_central_crops_spread_over_scales_and_camera_timesteps():
    layout = crop_layout(640, 360, pyramid_ratios())
    first, last = layout.scales[0], layout.scales[-1]
    # scale 0 is 24 x 14 crops: the centre one is row 7, column 12; scale 4 (offset 548) is 6 x 4: row 2, column 3
    assert (first.nx, first.ny, last.nx, last.ny, last.offset) == (24, 14, 6, 4, 548)
    assert sample_clips(layout, 1, 2) == [(0, 7 * 24 + 12), (0, 548 + 2 * 6 + 3)]
    assert [i for _, i in sample_clips(layout, 1, 5)] == [g.offset + (g.ny // 2) * g.nx + g.nx // 2
                                                        for g in layout.scales]
    seven = sample_clips(layout, 1, 7)      # more picks than scales: a repeated crop moves one to the right
    assert len(set(seven)) == 7 and (0, 7 * 24 + 12) in seven and (0, 7 * 24 + 13) in seven
    assert {p for p, _ in sample_clips(layout, 2, 3)} == {0, 1}


def test_a_precision_the_device_cannot_run_is_a_row_saying_so(capture_dir, monkeypatch):
    real_encode = viclip_real._encode

    def refuse_half(model, clips, batch, dtype, device):
        if dtype == torch.float16:
            raise RuntimeError("\"addmm_impl_cpu_\" not implemented for 'Half'")
        return real_encode(model, clips, batch, dtype, device)

    monkeypatch.setattr(viclip_real, "_encode", refuse_half)
    report = bench_viclip_real(capture_dir, size=tiny_config(), cameras=("2",), timesteps=(4,),
                               dtypes=("float16", "float32"), batch_sizes=(2,), clips=2, phrases=2,
                               subsets="x:1x1")
    half = next(r for r in report["rows"] if r["dtype"] == "float16")
    assert half["supported"] is False and "not implemented for 'Half'" in half["error"]
    assert next(r for r in report["rows"] if r["dtype"] == "float32")["supported"]
    assert "| float16 | 2 | not supported on cpu: RuntimeError" in real_report_markdown(report)


def test_bad_real_bench_input_is_one_clear_error(capture_dir, tmp_path):
    with pytest.raises(InputError, match="--subsets.*CAMERASxTIMESTEPS"):
        parse_subsets("all:27by150")
    with pytest.raises(InputError, match="--subsets.*positive"):
        parse_subsets("0x5")
    assert parse_subsets("8x30, all:27x150") == [viclip_real.Subset("8x30", 8, 30),
                                                 viclip_real.Subset("all", 27, 150)]
    with pytest.raises(InputError, match="cameras: no train camera '7'"):
        bench_viclip_real(capture_dir, size=tiny_config(), cameras=("7",))
    with pytest.raises(InputError, match="--timesteps: timestep 10 is outside 0..9"):
        bench_viclip_real(capture_dir, size=tiny_config(), timesteps=(10,))
    with pytest.raises(InputError, match="train_meta.json"):
        bench_viclip_real(tmp_path, size=tiny_config())


def test_the_cli_refuses_existing_outputs_and_checkpoints_before_any_work(capture_dir, tmp_path):
    from fourlegs_bench.commands import register_bench
    parser = argparse.ArgumentParser()
    register_bench(parser.add_subparsers())
    (tmp_path / "v.md").write_text("mine")
    args = parser.parse_args(["viclip", "--dataset", str(capture_dir), "--out", str(tmp_path / "v")])
    with pytest.raises(OutputExistsError, match="v.md"):
        args.func(args)
    args = parser.parse_args(["viclip", "--dataset", str(capture_dir), "--checkpoint", "w.pth",
                              "--out", str(tmp_path / "w")])
    with pytest.raises(InputError, match="--checkpoint"):
        args.func(args)
    assert (tmp_path / "v.md").read_text() == "mine" and not list(tmp_path.glob("w.*"))


@pytest.mark.skipif(not BASKETBALL.is_dir(), reason=f"the shared Panoptic capture is not at {BASKETBALL}")
def test_the_real_640x360_frames_give_the_papers_572_clips(tmp_path):
    report = bench_viclip_real(BASKETBALL, size=tiny_config(), cameras=("1",), timesteps=(0,),
                               dtypes=("float32",), batch_sizes=(2,), clips=3, phrases=2, subsets="all:27x150")
    assert report["image_size"] == [640, 360]
    assert report["clips_per_scale"] == [336, 112, 60, 40, 24]
    assert report["clips_per_camera_timestep"] == report["paper_clips_per_camera_timestep"] == 572
    # real frames, not padding: every sampled clip has visible structure
    assert all(float(clip.std()) > 0.05 for clip in report["_thumbnails"])


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_real_bench_on_cuda_measures_half_precision(capture_dir):
    report = bench_viclip_real(capture_dir, size=tiny_config(), cameras=("1",), timesteps=(3,),
                               dtypes=("float16", "bfloat16"), batch_sizes=(2,), clips=2, phrases=2,
                               subsets="x:1x1", device="cuda")
    assert report["device"].startswith("cuda")
    rows = {r["dtype"]: r for r in report["rows"] if not r["reference"]}
    assert rows["float16"]["supported"] and rows["float16"]["video_min_cosine"] > 0.99
