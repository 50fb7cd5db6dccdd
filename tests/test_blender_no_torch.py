"""The extension without PyTorch: bundled wheels for both Blender Pythons, a scene imported and played
on the timeline with torch unimportable, the preferences' installer running pip in the background."""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from _blender_helpers import REPO, bl, bpy_addon, child_env, tiny_scene  # noqa: F401

pytestmark = pytest.mark.blender
pytest.importorskip("bpy")

from fourlegs_addon import build  # noqa: E402


def test_pip_download_asks_for_each_python_and_platform(tmp_path):
    cmd = build.pip_download_command(tmp_path, "macos-x64", "3.13", build.requirements("3.13", "macos-x64"))
    assert cmd[cmd.index("--python-version") + 1] == "3.13" and "--only-binary=:all:" in cmd
    assert "macosx_10_14_x86_64" in cmd and "scipy==1.16.3" in cmd and "plyfile>=1.0" in cmd
    # numba's last macOS x86-64 wheels; the other platforms get the release accepting numpy 1.22 - 2.5
    assert "numba==0.62.1" in cmd and "llvmlite==0.45.1" in cmd
    assert "numba==0.68.1" in build.requirements("3.11", "linux-x64")
    assert "manylinux_2_28_x86_64" in build.pip_download_command(tmp_path, "linux-x64", "3.11", ["numba"])
    assert set(build.PYTHON_VERSIONS) == {"3.11", "3.13"}
    assert {"scipy", "plyfile", "tqdm", "safetensors", "numba", "llvmlite"} <= set(build.DEPENDENCIES)


def _complete_wheel_set() -> list[str]:
    """The file names ``fetch_wheels`` downloads (PyPI's, as of numba 0.68.1 / scipy 1.16.3)."""
    names = ["plyfile-1.1.5-py3-none-any.whl", "tqdm-4.70.1-py3-none-any.whl"]
    for plat in ("win_amd64", "manylinux_2_17_x86_64.manylinux2014_x86_64", "macosx_12_0_arm64",
                 "macosx_10_13_x86_64"):
        names.append(f"safetensors-0.8.0-cp310-abi3-{plat}.whl")
        names.append(f"scipy-1.16.3-cp313-cp313-{plat.replace('10_13', '10_14')}.whl")
        names.append(f"scipy-1.13.1-cp311-cp311-{plat.replace('10_13', '10_9')}.whl")
    for cp in ("cp311", "cp313"):
        for plat in ("win_amd64", "manylinux_2_27_x86_64.manylinux_2_28_x86_64", "macosx_12_0_arm64"):
            names += [f"numba-0.68.1-{cp}-{cp}-{plat}.whl", f"llvmlite-0.50.0-{cp}-{cp}-{plat}.whl"]
        names += [f"numba-0.62.1-{cp}-{cp}-macosx_10_15_x86_64.whl",
                  f"llvmlite-0.45.1-{cp}-{cp}-macosx_10_15_x86_64.whl"]
    return names


def test_missing_wheels_names_the_platform_and_python():
    names = _complete_wheel_set()
    assert build.missing_wheels([Path(n) for n in names]) == []
    without = [n for n in names if n != "scipy-1.16.3-cp313-cp313-win_amd64.whl"]
    assert build.missing_wheels([Path(n) for n in without]) == ["scipy (windows-x64, Python 3.13)"]
    without = [n for n in names if not n.startswith("plyfile")]
    assert len(build.missing_wheels([Path(n) for n in without])) == 8  # 4 platforms x 2 Pythons
    without = [n for n in names if not n.startswith("llvmlite-0.45.1")]
    assert build.missing_wheels([Path(n) for n in without]) == ["llvmlite (macos-x64, Python 3.11)",
                                                               "llvmlite (macos-x64, Python 3.13)"]
    # a cp311 wheel does not serve Python 3.13
    cp311_only = [n for n in names if "cp313" not in n]
    assert "scipy (linux-x64, Python 3.13)" in build.missing_wheels([Path(n) for n in cp311_only])
    # one platform's build needs only that platform's wheels
    linux = [n for n in names if "manylinux" in n or n.endswith("none-any.whl")]
    assert build.missing_wheels([Path(n) for n in linux], platforms=["linux-x64"]) == []
    assert [n for n in names if build.serves(n, ["linux-x64"])] == linux


def test_only_the_pinned_versions_are_bundled():
    """A wheel of another numba (or scipy) left in the cache by an older build is not bundled."""
    assert build.is_bundled("numba-0.68.1-cp313-cp313-win_amd64.whl")
    assert build.is_bundled("numba-0.62.1-cp311-cp311-macosx_10_15_x86_64.whl")
    assert not build.is_bundled("numba-0.61.2-cp311-cp311-win_amd64.whl")
    assert not build.is_bundled("scipy-1.14.0-cp311-cp311-win_amd64.whl")
    assert build.is_bundled("plyfile-9.9-py3-none-any.whl")  # not pinned: any version
    assert not build.is_bundled("torch-2.13.0-cp311-cp311-win_amd64.whl")


def test_a_one_platform_build_declares_only_that_platform(tmp_path):
    src = build.stage(tmp_path / "src", platforms=["linux-x64"])
    build.validate(src)
    manifest = (src / "blender_manifest.toml").read_text()
    assert 'platforms = ["linux-x64"]' in manifest and "windows-x64" not in manifest
    with pytest.raises(build.BuildError, match="unknown platform.*linux-arm64"):
        build.build(tmp_path / "out", platforms=["linux-arm64"])


@pytest.fixture(scope="module")
def probe_wheel_dir(tmp_path_factory) -> Path:
    """A local index (find-links folder) holding one tiny wheel, for the installer to install offline."""
    import base64
    import hashlib
    import zipfile

    folder = tmp_path_factory.mktemp("index")
    path = folder / "fourlegs_install_probe-1.0-py3-none-any.whl"
    files = {"fourlegs_install_probe/__init__.py": b"ANSWER = 7\n",
             "fourlegs_install_probe-1.0.dist-info/METADATA": b"Metadata-Version: 2.1\nName: fourlegs-install-probe\nVersion: 1.0\n",
             "fourlegs_install_probe-1.0.dist-info/WHEEL": b"Wheel-Version: 1.0\nGenerator: test\nRoot-Is-Purelib: true\nTag: py3-none-any\n"}
    record = []
    for name, data in files.items():
        digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
        record.append(f"{name},sha256={digest},{len(data)}")
    record.append("fourlegs_install_probe-1.0.dist-info/RECORD,,")
    with zipfile.ZipFile(path, "w") as zf:
        for name, data in files.items():
            zf.writestr(name, data)
        zf.writestr("fourlegs_install_probe-1.0.dist-info/RECORD", "\n".join(record) + "\n")
    return folder


def test_import_and_playback_without_torch(tmp_path, probe_wheel_dir):
    """torch made unimportable (sys.modules['torch'] = None before Blender starts): the extension installs
    and enables, a PLY scene imports and moves on the timeline, the panel names what is missing, and the
    preferences' installer puts a package into the extension's own site-packages in the background."""
    from fourlegs_engine.scene.ply import write_ply_scene

    scene = tiny_scene(T=3, N=64)
    write_ply_scene(scene, tmp_path / "ply")
    zips = build.build(tmp_path / "ext", with_wheels=False)
    shim = tmp_path / "shim"
    shim.mkdir()
    (shim / "sitecustomize.py").write_text("import sys\nsys.modules['torch'] = None\n")
    script = textwrap.dedent(f"""
        import json, sys, time
        import bpy
        out = {{}}
        try:
            import torch
            out["torch_importable"] = True
        except ImportError:
            out["torch_importable"] = False
        res = bpy.ops.extensions.package_install_files(filepath={str(zips[0])!r}, repo="user_default",
                                                        enable_on_install=True)
        pkg = "bl_ext.user_default.fourlegs_highlights"
        out["install"] = sorted(res)
        mod = sys.modules[pkg]
        r = bpy.ops.fourlegs.import_scene(filepath={str(tmp_path / "ply")!r})
        out["import"] = sorted(r)
        obj = bpy.context.scene.fourlegs.splat_object
        co = lambda: [tuple(v.vector) for v in obj.data.attributes["position"].data]  # mesh or point cloud
        first = co()
        bpy.context.scene.frame_set(3)  # playback: the import keyed frame f to timestep f - 1
        out["moved"] = max(abs(a[0] - b[0]) for a, b in zip(first, co()))
        out["points"] = len(first)
        out["missing_line"] = mod.preferences.missing_line()
        out["torch_loaded"] = sys.modules.get("torch") is not None
        prefs = bpy.context.preferences.addons[pkg].preferences
        out["prefs_variant"] = prefs.torch_variant
        target = mod.torch_install.site_packages(pkg)
        out["target"] = str(target)
        cmd = mod.torch_install.pip_install_command(target, "CPU", "fourlegs-install-probe",
                                                    ["--no-index", "--find-links", {str(probe_wheel_dir)!r}])
        cmd = [c for c in cmd if c not in ("--index-url", "https://download.pytorch.org/whl/cpu")]
        job = mod.torch_install.InstallJob(cmd, target).start()
        seen = set()
        t0 = time.time()
        while not job.done and time.time() - t0 < 120:
            seen.add(job.stage)
            time.sleep(0.05)
        out["job"] = [job.ok, job.progress, job.message]
        mod.torch_install.add_to_sys_path(target)
        import fourlegs_install_probe
        out["probe"] = fourlegs_install_probe.ANSWER
        bad = mod.torch_install.InstallJob(mod.torch_install.pip_install_command(
            target, "CPU", "fourlegs-no-such-package", ["--no-index"]), target).start()
        bad.wait(120)
        out["bad"] = [bad.ok, bad.message]
        print("RESULT" + json.dumps(out))
    """)
    env = child_env(BLENDER_USER_RESOURCES=str(tmp_path / "blender-user"), PYTHONPATH=str(shim))
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300,
                          cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    out = json.loads([l for l in proc.stdout.splitlines() if l.startswith("RESULT")][-1][len("RESULT"):])
    assert out["torch_importable"] is False
    assert out["install"] == ["FINISHED"] and out["import"] == ["FINISHED"] and out["points"] == 64
    assert out["moved"] == pytest.approx(0.2, abs=1e-4)  # tiny_scene moves +0.1 in x per timestep
    assert out["torch_loaded"] is False
    assert out["missing_line"].startswith("torch is missing (querying") and "Preferences" in out["missing_line"]
    assert out["prefs_variant"] == "CPU"
    assert out["target"].startswith(str(tmp_path / "blender-user")) and out["target"].endswith("site-packages")
    assert out["job"][0] is True and out["job"][1] == 1.0 and out["job"][2].startswith("installed into")
    assert out["probe"] == 7
    assert out["bad"][0] is False and out["bad"][1].startswith("pip failed: ERROR")


#: sitecustomize for the child Blender: the bundled dependencies import only from the Blender user folder
#: (the extension's site-packages), never from the test's own environment
EXTENSION_ONLY_NUMBA = """
import importlib.machinery, os, sys

class ExtensionOnlyNumba:
    def find_spec(self, name, path=None, target=None):
        if name not in ("numba", "llvmlite", "plyfile", "scipy"):
            return None
        user = os.environ["BLENDER_USER_RESOURCES"]
        spec = importlib.machinery.PathFinder.find_spec(name, [p for p in sys.path if p.startswith(user)])
        if spec is None:
            raise ModuleNotFoundError(f"No module named {name!r} in the extension", name=name)
        return spec

sys.meta_path.insert(0, ExtensionOnlyNumba())
"""


def test_installed_zip_carries_plyfile_numba_and_the_scipy_of_its_python(tmp_path):
    """With the real dependency wheels (``fourlegs build-extension --fetch-wheels`` leaves them in the
    cache): the linux-x64 zip installs offline and Blender installs the wheels of its own Python; the
    bundled numba imports against Blender's numpy and compiles, and where torch is present the render
    engine blends through numba's kernels."""
    from fourlegs_engine.paths import cache_dir

    wheels = [w for w in sorted((cache_dir() / "extension-wheels").glob("*.whl")) if build.is_bundled(w)]
    if build.missing_wheels(wheels, platforms=["linux-x64"]):
        pytest.skip("linux-x64 dependency wheels not downloaded (run: fourlegs build-extension --fetch-wheels "
                    "--platform linux-x64)")
    zips = build.build(tmp_path / "ext", platforms=["linux-x64"])
    assert len(zips) == 1
    import zipfile
    names = zipfile.ZipFile(zips[0]).namelist()
    assert any(n.startswith("wheels/plyfile-") for n in names)
    assert any("cp311-cp311-manylinux" in n for n in names) and any("cp313-cp313-manylinux" in n for n in names)
    assert not [n for n in names if "win_amd64" in n or "macosx" in n]
    assert {n.split("/")[1].split("-")[0] for n in names if n.startswith("wheels/")} >= {"numba", "llvmlite"}
    shim = tmp_path / "shim"
    shim.mkdir()
    (shim / "sitecustomize.py").write_text(EXTENSION_ONLY_NUMBA)
    bundle = tmp_path / "bundle"
    from fourlegs_engine.scene import write_bundle
    from fourlegs_engine.scene.ply import write_ply_scene
    write_bundle(tiny_scene(T=2, N=64), bundle)
    write_ply_scene(tiny_scene(T=3, N=48), tmp_path / "ply")
    script = textwrap.dedent(f"""
        import json, sys, bpy
        import numpy as np
        res = bpy.ops.extensions.package_install_files(filepath={str(zips[0])!r}, repo="user_default",
                                                        enable_on_install=True)
        out = {{"install": sorted(res), "python": "%d.%d" % sys.version_info[:2], "numpy": np.__version__}}
        import numba, llvmlite
        out["numba"] = [numba.__version__, numba.__file__, llvmlite.__file__]
        out["jit_sum"] = float(numba.njit(lambda a: (a * a).sum())(np.arange(5.0)))
        import plyfile, scipy
        out["plyfile"], out["scipy"] = plyfile.__file__, [scipy.__version__, scipy.__file__]
        out["ply_import"] = sorted(bpy.ops.fourlegs.import_scene(filepath={str(tmp_path / "ply")!r}))
        out["ply_points"] = len(bpy.context.scene.fourlegs.splat_object.data.attributes["position"].data)
        try:
            import torch
        except ImportError:
            torch = None
        if torch is not None:
            from fourlegs_engine.render import cpu_kernels, kernel_backend
            calls = []
            blend = kernel_backend.blend_forward  # the fused kernels (RasterOptions' default, v2)
            kernel_backend.blend_forward = lambda *a, **k: calls.append(1) or blend(*a, **k)
            for o in list(bpy.data.objects):  # the PLY scene's objects
                bpy.data.objects.remove(o)
            bpy.ops.fourlegs.import_scene(filepath={str(bundle / "scene.json")!r})
            scene = bpy.context.scene
            scene.render.engine = "FOURLEGS_SPLATS"
            scene.camera = next(o for o in scene.objects if o.type == "CAMERA")
            scene.render.resolution_x, scene.render.resolution_y = 32, 24
            out["render"] = sorted(bpy.ops.render.render())
            out["numba_blends"] = len(calls)
            out["kernels_available"] = cpu_kernels.available()
        print("RESULT" + json.dumps(out))
    """)
    user = tmp_path / "blender-user"
    env = child_env(BLENDER_USER_RESOURCES=str(user), PYTHONPATH=str(shim))
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300,
                          cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    out = json.loads([l for l in proc.stdout.splitlines() if l.startswith("RESULT")][-1][len("RESULT"):])
    assert out["install"] == ["FINISHED"]
    site = next(user.glob("extensions/.local/lib/python*/site-packages"))
    installed = {p.name for p in site.iterdir()}
    scipy_version = {"3.11": "1.13.1", "3.13": "1.16.3"}[out["python"]]
    assert f"scipy-{scipy_version}.dist-info" in installed and "plyfile.py" in installed
    assert len([n for n in installed if n.startswith("scipy-")]) == 1  # only its own Python's scipy
    numba_version, numba_file, llvmlite_file = out["numba"]
    assert numba_version == build.NUMBA[0].split("==")[1]
    assert numba_file.startswith(str(site)) and llvmlite_file.startswith(str(site))
    assert out["jit_sum"] == 30.0
    # a PLY sequence imports through the extension's own plyfile
    assert out["plyfile"].startswith(str(site)) and out["ply_import"] == ["FINISHED"] and out["ply_points"] == 48
    assert out["scipy"][0] == scipy_version and out["scipy"][1].startswith(str(site))
    if "render" in out:  # the Python 3.13 job runs without torch
        assert out["render"] == ["FINISHED"] and out["kernels_available"]
        assert out["numba_blends"] >= 1


def test_encode_process_writes_every_frame_in_a_child_process(bl, tmp_path):
    """The MP4 encoder Render Video starts (no torch needed): a child process encodes the PNG frames while
    this process keeps running; it reports each frame, and the movie holds every one of them."""
    import time

    import numpy as np

    from fourlegs_addon import encode, video

    frames = []
    for i in range(5):
        image = bl.data.images.new(f"frame{i}", 32, 24)
        image.pixels.foreach_set(np.tile(np.float32([i / 4, 0.5, 1 - i / 4, 1.0]), 32 * 24))
        image.filepath_raw, image.file_format = str(tmp_path / f"frame_{i + 1:04d}.png"), "PNG"
        image.save()
        frames.append(tmp_path / f"frame_{i + 1:04d}.png")
    job = encode.EncodeProcess(frames, tmp_path / "movie", fps=12)
    polls = 0
    t0 = time.perf_counter()
    while job.poll():
        polls += 1
        time.sleep(0.01)
    assert polls > 5 and time.perf_counter() - t0 < 120  # the caller ran while the child encoded
    movie = job.result()
    assert movie.parent == tmp_path / "movie" and movie.suffix == ".mp4" and job.encoded == 5
    assert video.movie_frame_count(movie) == 5
    with pytest.raises(ValueError, match="no frames"):
        encode.EncodeProcess([], tmp_path / "none", fps=12)
