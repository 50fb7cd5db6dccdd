"""Preprocessing on a local Ray cluster (2 CPUs): same bytes as the single-process run, retries of a
killed task, failures reported with their chunk, resume; and the message when Ray is missing."""
from __future__ import annotations

import os
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch

from _cluster_helpers import KillOnceFactory, count_then_fail, simulated_factory
from _language_helpers import micro_bundle
from fourlegs_engine import cluster
from fourlegs_engine.cluster import stages
from fourlegs_engine.commands.main import main
from fourlegs_engine.language.distill import distill_scene
from fourlegs_engine.scene.bundle import load_bundle

TESTS_DIR = Path(__file__).resolve().parent
AE_ARGS = ["--epochs", "1", "--samples", "1024", "--ae-batch-size", "256"]


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    """A micro bundle (3 timesteps, 2 cameras) extracted, autoencoder-trained and lifted in one process;
    ``reference.parent / "prepared"`` is the same before the lift."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("cluster")
    path = micro_bundle(root / "prepared", T=3, cameras=2)
    assert main(["extract", str(path), "--no-progress"]) == 0
    assert main(["train-ae", str(path), *AE_ARGS]) == 0
    shutil.copytree(path, root / "reference")
    distill_scene(load_bundle(root / "reference"), mode="lift")
    torch.set_num_threads(old)
    return root / "reference"


@pytest.fixture(scope="module")
def ray_cluster():
    ray = pytest.importorskip("ray", reason='needs Ray: pip install "fourlegs[cluster]"')
    old = os.environ.get("PYTHONPATH")
    os.environ["PYTHONPATH"] = os.pathsep.join([str(TESTS_DIR)] + ([old] if old else []))  # task bodies
    ray.init(num_cpus=2, include_dashboard=False, logging_level="WARNING", log_to_driver=False)
    yield ray
    ray.shutdown()
    if old is None:
        os.environ.pop("PYTHONPATH", None)
    else:
        os.environ["PYTHONPATH"] = old


def _fresh_copy(reference: Path, dst: Path) -> Path:
    """The prepared bundle (trained autoencoder) without its features and latents."""
    shutil.copytree(reference.parent / "prepared", dst)
    shutil.rmtree(dst / "features")
    return dst


def _same_files(a: Path, b: Path, pattern: str) -> list[str]:
    names = sorted(p.name for p in a.glob(pattern))
    assert names and names == sorted(p.name for p in b.glob(pattern))
    for name in names:
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    return names


@pytest.mark.cluster
@pytest.mark.parametrize("shared", [True, False], ids=["shared-fs", "object-store"])
def test_extract_and_lift_on_ray_give_the_single_process_bytes(reference, ray_cluster, tmp_path, shared):
    path = _fresh_copy(reference, tmp_path / "bundle")
    flags = ["--no-progress"] + ([] if shared else ["--ray-no-shared-fs"])
    assert main(["extract", "--ray", str(path), *flags, "--ray-chunk", "2"]) == 0    # --ray BUNDLE: local
    flags.append("--ray")
    assert _same_files(reference / "features", path / "features", "t*.npy") == [
        "t000000.npy", "t000001.npy", "t000002.npy"]
    assert main(["distill", str(path), *flags]) == 0
    assert (path / "language" / "latents.npy").read_bytes() == (reference / "language" / "latents.npy").read_bytes()
    assert not (path / "language" / "steps").exists()                      # merged, parts dropped
    assert not [p for p in path.rglob("*") if ".part" in p.name]           # nothing half-written left
    assert main(["distill", str(path), "--check"]) == 0
    if not shared:                                                  # node-local copies removed
        assert not list((Path(tempfile.gettempdir()) / "fourlegs-cluster").glob("*/bundle"))


STRIDE_2 = ["--timestep-stride", "2"]


@pytest.fixture(scope="module", params=["latents", "interpolate"])
def strided_reference(request, tmp_path_factory) -> tuple[Path, str]:
    """A micro bundle (5 timesteps) extracted every 2nd timestep with ``--fill FILL``, autoencoder-trained
    and lifted in one process (timesteps 1 and 3 filled from their neighbours: features, or with
    ``latents`` the lifted latents); ``.parent / "prepared"`` is the same before the extraction."""
    fill = request.param
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp(f"cluster_{fill}")
    prepared = micro_bundle(root / "prepared", T=5, cameras=2)
    reference = root / "reference"
    shutil.copytree(prepared, reference)
    assert main(["extract", str(reference), "--no-progress", *STRIDE_2, "--fill", fill]) == 0
    assert main(["train-ae", str(reference), *AE_ARGS]) == 0
    result = distill_scene(load_bundle(reference), mode="lift")
    assert result.filled == ([1, 3] if fill == "latents" else [])
    torch.set_num_threads(old)
    return reference, fill


@pytest.mark.cluster
@pytest.mark.parametrize("shared", [True, False], ids=["shared-fs", "object-store"])
def test_a_strided_plan_on_ray_gives_the_single_process_bytes(strided_reference, ray_cluster, tmp_path, shared):
    # the tasks encode each grid timestep once and lift what has features; the driver fills the rest
    reference, fill = strided_reference
    path = tmp_path / "bundle"
    shutil.copytree(reference.parent / "prepared", path)
    flags = ["--no-progress"] + ([] if shared else ["--ray-no-shared-fs"])
    assert main(["extract", "--ray", str(path), *flags, *STRIDE_2, "--fill", fill, "--ray-chunk", "2"]) == 0
    stored = ["t000000.npy", "t000002.npy", "t000004.npy"]
    if fill == "interpolate":
        stored = sorted(stored + ["t000001.npy", "t000003.npy"])
    assert _same_files(reference / "features", path / "features", "t*.npy") == stored
    (path / "language").mkdir(exist_ok=True)
    for name in ("autoencoder.json", "encoder.pt", "decoder.pt"):   # the same autoencoder as the reference's
        shutil.copy(reference / "language" / name, path / "language")
    assert main(["distill", str(path), *flags, "--ray"]) == 0
    assert (path / "language" / "latents.npy").read_bytes() == (reference / "language" / "latents.npy").read_bytes()


def test_plan_chunks_splits_at_gaps_and_size():
    assert cluster.plan_chunks([5, 0, 1, 2, 3, 9, 6], 3) == [(0, 1, 2), (3,), (5, 6), (9,)]
    assert cluster.plan_chunks([], 4) == []
    assert cluster.auto_chunk(150, 8, "rgb") == 1                  # encoding dominates: balance
    assert cluster.auto_chunk(150, 8, "labels") == 19 and cluster.auto_chunk(3, 64, "labels") == 1


@pytest.mark.cluster
def test_a_killed_task_is_retried_and_a_run_resumes(reference, ray_cluster, tmp_path):
    path = _fresh_copy(reference, tmp_path / "bundle")
    (path / "features").mkdir()
    shutil.copy(reference / "features" / "manifest.json", path / "features")
    shutil.copy(reference / "features" / "t000001.npy", path / "features")   # finished by an earlier run
    marker = tmp_path / "killed"
    scene = load_bundle(path)
    report, tasks = cluster.extract_on_ray(scene, KillOnceFactory(marker), options=cluster.RayOptions(chunk=1))
    assert marker.is_file()                                        # a worker really was killed ...
    assert tasks.failures == [] and sorted(tasks.done) == [(0,), (2,)]   # ... and its task retried
    assert tasks.skipped == [1] and report.timesteps_done == [0, 2]
    _same_files(reference / "features", path / "features", "t*.npy")


@pytest.mark.cluster
def test_failures_are_retried_a_bounded_number_of_times_and_reported_with_their_chunk(ray_cluster, tmp_path):
    attempts = tmp_path / "attempts.txt"
    results = {}
    report = cluster.run_chunks(count_then_fail, str(attempts), [(0,), (2,), (3,)], progress=False,
                                options=cluster.RayOptions(retries=2), stage="test",
                                on_result=lambda chunk, value: results.update({chunk: value}))
    lines = attempts.read_text().split()
    assert lines.count("0") == 1 and lines.count("3") == 1       # bad input is not retried
    assert lines.count("2") == 3                                  # 1 attempt + 2 retries
    assert results == {(0,): 0} and report.done == [(0,)]
    assert sorted(f.chunk for f in report.failures) == [(2,), (3,)]
    with pytest.raises(cluster.ClusterError) as err:
        report.raise_failures()
    message = str(err.value)
    assert "timestep 2: RuntimeError: transient failure that never clears" in message
    assert "timestep 3: ValueError: bad input in timestep 3" in message


@pytest.mark.cluster
def test_map_on_ray_runs_one_task_per_item(ray_cluster):
    assert cluster.map_on_ray(abs, [-3, 4, -5], progress=False) == [3, 4, 5]


@pytest.mark.cluster
def test_a_bundle_the_workers_cannot_see_fails_with_a_clear_line(reference, ray_cluster, tmp_path):
    path = _fresh_copy(reference, tmp_path / "bundle")
    ref = cluster.bundle_ref(ray_cluster, path, cluster.RayOptions())
    ref.scene_json_sha = "0" * 64                                  # as if another bundle were mounted there
    job = cluster.ExtractJob(ref, "run", simulated_factory, None)
    report = cluster.run_chunks(stages.extract_config_task, job, [()], options=cluster.RayOptions(),
                                stage="extract-config", progress=False)
    assert len(report.failures) == 1 and "--ray-no-shared-fs" in report.failures[0].error


def test_missing_ray_names_the_extra_to_install(reference, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)                 # `import ray` raises ImportError
    with pytest.raises(cluster.ClusterError, match=r'pip install "fourlegs\[cluster\]"'):
        cluster.require_ray()
    path = _fresh_copy(reference, tmp_path / "bundle")
    assert main(["extract", str(path), "--ray", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ['fourlegs: error: --ray needs Ray, which is not installed; install it with: '
                   'pip install "fourlegs[cluster]"']
    assert not (path / "features").exists()
    assert main(["distill", str(path), "--ray=auto"]) == 2
    assert 'pip install "fourlegs[cluster]"' in capsys.readouterr().err


def test_list_scheduling_simulation():
    from fourlegs_bench.cluster import SequenceAssumptions, list_schedule, simulate_sequence
    assert list_schedule([3, 1, 1, 1], 2) == (3.0, [3.0, 3.0])
    assert list_schedule([2, 2, 2], 1) == (6.0, [6.0])
    assert list_schedule([5], 4)[0] == 5.0
    a = SequenceAssumptions(jitter=0.0)
    one = simulate_sequence(a, 1, overhead_s=0.0)
    # one GPU: the stages' work back to back: 150 × 27 × (572 clips × 13 ms) + renders + load + AE + distill
    assert one["extract_tasks"] == 150
    work = (150 * 27 * 572 * 0.013 + (150 + 7 * 150) * 27 * 0.01 + 20.0 + 600.0
            + 150 * (300.0 + a.feature_mb / a.transfer_mb_per_s))
    assert one["total_hours"] * 3600 == pytest.approx(work, rel=1e-9)
    assert one["efficiency"] == pytest.approx(1.0)
    many = simulate_sequence(a, 64, overhead_s=0.0)
    assert many["extract_tasks"] == 150 and many["extract_chunk"] == 1
    assert simulate_sequence(a, 8, 0.0, chunk=19)["extract_tasks"] == 8
    # 150 equal distill tasks on 64 GPUs take 3 rounds; the autoencoder stays serial
    assert many["distill_hours"] * 3600 == pytest.approx(3 * (300.0 + a.feature_mb / a.transfer_mb_per_s))
    assert many["total_hours"] > many["autoencoder_hours"] + many["distill_hours"]
    assert 0 < many["efficiency"] < 1


@pytest.mark.cluster
def test_fit_on_ray_runs_one_task_per_capture_with_the_single_process_bytes(ray_cluster, tmp_path, capsys):
    import _fit_helpers as fh
    from fourlegs_engine.fit import FitOptions, fit_capture

    captures = [fh.write_capture(tmp_path / "captures" / name, num_timesteps=2) for name in ("a", "b")]
    knobs = ["--resolution-scale", "0.5", "--first-iterations", "4", "--iterations", "2",
             "--init-background", "200", "--no-densify"]
    assert main(["fit", *map(str, captures), "-o", str(tmp_path / "ray"), *knobs, "--ray"]) == 0
    options = FitOptions(resolution_scale=0.5, first_iterations=4, iterations=2, init_background=200, densify=False)
    old = torch.get_num_threads()
    torch.set_num_threads(1)          # as the one-CPU Ray workers run
    try:
        for capture in captures:
            fit_capture(capture, tmp_path / "single" / capture.name, options, progress=False)
    finally:
        torch.set_num_threads(old)
    for capture in captures:
        assert "means.npy" in _same_files(tmp_path / "single" / capture.name, tmp_path / "ray" / capture.name, "*.npy")
    capsys.readouterr()
    assert main(["fit", str(captures[0]), str(captures[0]), "-o", str(tmp_path / "twice"), "--ray"]) == 2
    assert "share the folder name a" in capsys.readouterr().err
    assert not (tmp_path / "twice").exists()
