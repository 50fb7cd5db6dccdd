"""Native bundle round trip and bad inputs, load_scene dispatch, lazy latents, bpy-free imports."""
from __future__ import annotations

import json
import pickle
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from fourlegs_engine.errors import InputError, OutputExistsError
from fourlegs_engine.scene import load_bundle, load_scene, write_bundle
from fourlegs_engine.scene.bundle import update_bundle_meta

from _scene_helpers import assert_rigs_equal, assert_sequences_equal, random_scene

REPO = Path(__file__).resolve().parents[1]


def _bundle(tmp_path, **kw):
    scene = random_scene(**kw)
    return scene, write_bundle(scene, tmp_path / "b")


def test_bundle_round_trip_with_latents_labels_and_language(tmp_path):
    scene = random_scene(T=3, N=12, sh_degree=2, colors=True, per_frame_scales=True)
    g = scene.gaussians
    g.labels = np.arange(36, dtype=np.int32).reshape(3, 12) % 5 - 1
    g.latents = np.random.default_rng(3).normal(size=(3, 12, 8)).astype(np.float32)
    scene.language = {"encoder": "simulated", "latent_dim": 8, "canonical_phrases": ["object"]}
    scene.metadata = {"source_format": "test", "nested": {"a": [1, 2]}}
    path = write_bundle(scene, tmp_path / "b")
    for back in (load_bundle(path), load_scene(path), load_scene(path / "scene.json")):
        assert_sequences_equal(back.gaussians, g)
        np.testing.assert_array_equal(back.gaussians.latents, g.latents)
        assert isinstance(back.gaussians.latents, np.memmap)
        assert_rigs_equal(back.cameras, scene.cameras)
        assert (back.name, back.fps, back.metadata) == (scene.name, scene.fps, scene.metadata)
        assert back.language["encoder"] == "simulated" and back.has_language_field
        frame = back.gaussians.at(2, with_latents=True)
        np.testing.assert_array_equal(frame.latents.numpy(), g.latents[2])
        assert back.gaussians.at(2).latents is None  # latents only read when asked
    with pytest.raises(OutputExistsError):
        write_bundle(scene, path)
    write_bundle(scene, path, overwrite=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b"]


def test_every_format_round_trips_through_load_scene(tmp_path):
    from fourlegs_engine.scene.dynamic3dgs import write_dynamic3dgs
    from fourlegs_engine.scene.ply import write_ply_scene

    rgb_scene = random_scene(T=2, N=9, sh_degree=None, colors=True)
    sh_scene = random_scene(T=2, N=9, sh_degree=3, foreground=False)
    write_bundle(rgb_scene, tmp_path / "bundle")
    write_dynamic3dgs(rgb_scene, tmp_path / "d3dgs")
    write_ply_scene(sh_scene, tmp_path / "plys", encoding="ascii")
    assert_sequences_equal(load_scene(tmp_path / "bundle").gaussians, rgb_scene.gaussians)
    assert_sequences_equal(load_scene(tmp_path / "d3dgs").gaussians, rgb_scene.gaussians, rot_atol=2e-7)
    assert_sequences_equal(load_scene(tmp_path / "plys").gaussians, sh_scene.gaussians, rot_atol=2e-7)
    assert load_scene(tmp_path / "d3dgs").metadata["source_format"] == "dynamic3dgs"


def test_load_scene_rejects_unknown_inputs(tmp_path):
    with pytest.raises(InputError, match=r"nowhere: does not exist; expected a bundle directory"):
        load_scene(tmp_path / "nowhere")
    (tmp_path / "x.txt").write_text("hello")
    with pytest.raises(InputError, match=r"x\.txt: unsupported file type \.txt"):
        load_scene(tmp_path / "x.txt")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match=r"empty: is not a recognised scene"):
        load_scene(tmp_path / "empty")


def test_bundle_object_array_refused_never_unpickled(tmp_path):
    class Payload:
        def __reduce__(self):
            return (open, (str(tmp_path / "fired"), "w"))

    _, path = _bundle(tmp_path)
    np.save(path / "foreground.npy", np.array([Payload()] * 40, dtype=object), allow_pickle=True)
    with pytest.raises(InputError, match=r"foreground\.npy: foreground: holds an object/pickled array"):
        load_scene(path)
    assert not (tmp_path / "fired").exists()
    (path / "foreground.npy").write_bytes(pickle.dumps(Payload()))
    with pytest.raises(InputError, match=r"foreground\.npy: foreground: "):
        load_scene(path)
    assert not (tmp_path / "fired").exists()


def test_bundle_truncated_array(tmp_path):
    _, path = _bundle(tmp_path)
    data = (path / "means.npy").read_bytes()
    (path / "means.npy").write_bytes(data[:-10])
    with pytest.raises(InputError, match=r"means\.npy: means: corrupt or truncated \.npy file"):
        load_scene(path)


def test_bundle_nan_and_zero_quaternion(tmp_path):
    scene, path = _bundle(tmp_path)
    means = np.array(scene.gaussians.means)
    means[1, 3, 0] = np.nan
    np.save(path / "means.npy", means)
    with pytest.raises(InputError, match=r"b: means: contains NaN or Inf"):
        load_scene(path)
    np.save(path / "means.npy", np.asarray(scene.gaussians.means))
    rot = np.array(scene.gaussians.rotations)
    rot[2, 5] = 0
    np.save(path / "rotations.npy", rot)
    with pytest.raises(InputError, match=r"rotations\.npy: rotations: zero-length quaternion at index \[2, 5\]"):
        load_scene(path)


def test_bundle_shape_dtype_and_t_mismatch(tmp_path):
    scene, path = _bundle(tmp_path, T=3, N=40)
    np.save(path / "opacity_logits.npy", np.zeros(39, np.float32))
    with pytest.raises(InputError, match=r"opacity_logits: has shape \(39,\), expected \(40,\)"):
        load_scene(path)
    np.save(path / "opacity_logits.npy", np.zeros(40, np.int64))
    with pytest.raises(InputError, match=r"opacity_logits: has dtype int64, expected a float type"):
        load_scene(path)
    np.save(path / "opacity_logits.npy", np.zeros(40, np.float32))
    np.save(path / "means.npy", np.zeros((4, 40, 3), np.float32))
    with pytest.raises(InputError, match=r"means\.npy: means: has leading shape \(4, 40\), but scene\.json says T=3"):
        load_scene(path)


def test_bundle_meta_problems(tmp_path):
    _, path = _bundle(tmp_path)
    meta = json.loads((path / "scene.json").read_text())
    del meta["arrays"]["rotations"]
    (path / "scene.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match=r"scene\.json: arrays\.rotations: missing array entry"):
        load_scene(path)
    update = dict(meta, version=99)
    (path / "scene.json").write_text(json.dumps(update))
    with pytest.raises(InputError, match=r"scene\.json: version: unsupported bundle version 99"):
        load_scene(path)
    (path / "scene.json").write_text('{"format": "fourlegs-bundle", "vers')
    with pytest.raises(InputError, match=r"scene\.json: not valid JSON"):
        load_scene(path)


def test_large_latent_file_is_never_read_whole(tmp_path):
    """A 4 GiB (sparse) latent file (64 MiB per timestep); the loader has 512 MiB of data memory to spare."""
    T, N, D = 64, 8192, 2048
    _, path = _bundle(tmp_path, T=T, N=N, sh_degree=0)
    (path / "language").mkdir()
    latents = np.lib.format.open_memmap(path / "language" / "latents.npy", mode="w+", dtype=np.float32,
                                        shape=(T, N, D))
    latents[37, :4] = np.arange(4 * D, dtype=np.float32).reshape(4, D)
    latents.flush()
    del latents
    meta = json.loads((path / "scene.json").read_text())
    update_bundle_meta(path, arrays=dict(meta["arrays"], latents="language/latents.npy"),
                       language={"latent_dim": D})
    script = textwrap.dedent(f"""
        import resource, sys
        import numpy as np, torch
        torch.set_num_threads(1)
        from fourlegs_engine.scene import load_scene
        from fourlegs_engine.commands.scene import format_summary
        data_kb = int(open('/proc/self/status').read().split('VmData:')[1].split()[0])
        limit = data_kb * 1024 + (512 << 20)   # RLIMIT_AS would also count the file mapping itself,
        resource.setrlimit(resource.RLIMIT_DATA, (limit, limit))  # so limit private memory instead
        scene = load_scene({str(path)!r})
        s = scene.summary()
        assert s["latents_bytes_on_disk"] == {T * N * D * 4} and s["language_field"], s
        format_summary(s)
        frame = scene.gaussians.at(37, with_latents=True)
        assert frame.latents.shape == ({N}, {D})
        assert frame.latents[3, 5].item() == 3 * {D} + 5 and frame.latents[4:].abs().sum().item() == 0
        try:
            np.array(scene.gaussians.latents)      # control: reading it whole must fail under the limit
        except MemoryError:
            print("OK")
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and proc.stdout.strip() == "OK", proc.stderr[-3000:]


def test_engine_imports_without_bpy():
    script = textwrap.dedent("""
        import importlib, pkgutil, sys
        class NoBpy:
            def find_spec(self, name, path=None, target=None):
                if name == "bpy" or name.startswith("bpy.") or name.startswith("bpy_"):
                    raise ImportError(f"blocked import of {name}")
                return None
        sys.meta_path.insert(0, NoBpy())
        import fourlegs_engine
        names = [m.name for m in pkgutil.walk_packages(fourlegs_engine.__path__, "fourlegs_engine.")]
        failed = []
        for name in names:
            try:
                importlib.import_module(name)
            except Exception as exc:
                failed.append(f"{name}: {type(exc).__name__}: {exc}")
        assert "bpy" not in sys.modules
        print(len(names), "modules;", "FAILED:" if failed else "ok", *failed, sep="\\n")
        sys.exit(1 if failed else 0)
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert proc.returncode == 0, proc.stdout + proc.stderr[-3000:]
    assert int(proc.stdout.split()[0]) >= 8  # the scene package alone has 9 modules
