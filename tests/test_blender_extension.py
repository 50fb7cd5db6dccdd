"""The extension: manifest passes Blender's validator, the zip builds, installs offline and enables."""
from __future__ import annotations

import base64
import hashlib
import io
import json
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import pytest

from _blender_helpers import REPO, child_env

pytestmark = pytest.mark.blender
pytest.importorskip("bpy")

from fourlegs_addon import build  # noqa: E402


@pytest.fixture(scope="module")
def probe_wheel(tmp_path_factory) -> Path:
    """A real (tiny, pure-Python) wheel, to prove Blender installs the wheels the manifest declares."""
    path = tmp_path_factory.mktemp("wheels") / "fourlegs_wheel_probe-1.0-py3-none-any.whl"
    files = {"fourlegs_wheel_probe/__init__.py": b"ANSWER = 42\n",
             "fourlegs_wheel_probe-1.0.dist-info/METADATA": b"Metadata-Version: 2.1\nName: fourlegs-wheel-probe\nVersion: 1.0\n",
             "fourlegs_wheel_probe-1.0.dist-info/WHEEL": b"Wheel-Version: 1.0\nGenerator: test\nRoot-Is-Purelib: true\nTag: py3-none-any\n"}
    record = []
    for name, data in files.items():
        digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
        record.append(f"{name},sha256={digest},{len(data)}")
    record.append("fourlegs_wheel_probe-1.0.dist-info/RECORD,,")
    with zipfile.ZipFile(path, "w") as zf:
        for name, data in files.items():
            zf.writestr(name, data)
        zf.writestr("fourlegs_wheel_probe-1.0.dist-info/RECORD", "\n".join(record) + "\n")
    return path


@pytest.fixture(scope="module")
def extension_zip(tmp_path_factory, probe_wheel) -> Path:
    out = tmp_path_factory.mktemp("ext")
    zips = build.build(out, with_wheels=False, extra_wheels=[probe_wheel])
    assert len(zips) == 1
    return zips[0]


def test_manifest_passes_blenders_validator(tmp_path):
    src = build.stage(tmp_path / "src")
    build.validate(src)  # raises BuildError with the validator's message on failure
    manifest = (src / "blender_manifest.toml").read_text()
    assert 'license = ["SPDX:GPL-3.0-or-later"]' in manifest
    assert 'blender_version_min = "5.0.0"' in manifest and 'blender_version_max = "5.4.0"' in manifest
    assert "[permissions]" in manifest and "files =" in manifest


def test_validator_rejects_a_broken_manifest(tmp_path):
    """The validator is really consulted: a tagline ending in a full stop is refused."""
    bad = tmp_path / "blender_manifest.toml"
    text = (REPO / "blender_manifest.toml").read_text()
    bad.write_text(text.replace('tagline = "Text-queried highlight videos of dynamic Gaussian scenes"',
                                'tagline = "Highlights."'))
    src = build.stage(tmp_path / "src", manifest=bad)
    with pytest.raises(build.BuildError, match="tagline"):
        build.validate(src)


def test_zip_contains_addon_engine_presets_and_declared_wheels(extension_zip, probe_wheel):
    import fourlegs_engine

    engine_wheel = f"fourlegs_engine-{fourlegs_engine.__version__}-py3-none-any.whl"
    names = set(zipfile.ZipFile(extension_zip).namelist())
    for required in ("blender_manifest.toml", "__init__.py", "render_engine.py", f"wheels/{engine_wheel}",
                     f"wheels/{probe_wheel.name}"):
        assert required in names, required
    assert not [n for n in names if "__pycache__" in n or n.endswith(".pyc")]
    # only what runs in Blender: no engine sources beside the wheel, no build script, no benchmarks
    assert not [n for n in names if n.startswith(("fourlegs_engine/", "fourlegs_bench/")) or n in ("build.py", "commands.py")]
    manifest = zipfile.ZipFile(extension_zip).read("blender_manifest.toml").decode()
    assert f'"./wheels/{probe_wheel.name}"' in manifest and f'"./wheels/{engine_wheel}"' in manifest
    with zipfile.ZipFile(io.BytesIO(zipfile.ZipFile(extension_zip).read(f"wheels/{engine_wheel}"))) as wheel:
        inside = set(wheel.namelist())
    for required in ("fourlegs_engine/__init__.py", "fourlegs_engine/render/__init__.py", "fourlegs_engine/api.py",
                     "fourlegs_engine/highlights/presets/broadcast.toml"):
        assert required in inside, required
    assert not [n for n in inside if n.startswith(("fourlegs_bench/", "fourlegs_addon/")) or "__pycache__" in n]


def test_manifest_wheels_inserted_before_tables():
    text = 'id = "x"\n\n[permissions]\nfiles = "y"\n'
    out = build.manifest_with_wheels(text, ["a-1.0-py3-none-any.whl"])
    assert out.index("wheels = [") < out.index("[permissions]")
    with pytest.raises(build.BuildError):
        build.manifest_with_wheels(out, ["b-1.0-py3-none-any.whl"])


def test_install_offline_and_enable(extension_zip, tmp_path):
    """Install the built zip into a fresh bpy (own user resources), enable it, use it, disable it."""
    script = textwrap.dedent(f"""
        import json, sys
        import bpy
        res = bpy.ops.extensions.package_install_files(filepath={str(extension_zip)!r}, repo="user_default",
                                                        enable_on_install=True)
        pkg = "bl_ext.user_default.fourlegs_highlights"
        mod = sys.modules[pkg]
        out = {{"install": sorted(res), "enabled": pkg in bpy.context.preferences.addons,
               "scene_prop": hasattr(bpy.types.Scene, "fourlegs"),
               "operators": [hasattr(bpy.ops.fourlegs, n) for n in ("import_scene", "run_query",
                             "generate_highlight", "render_video")]}}
        import fourlegs_wheel_probe
        out["wheel"] = fourlegs_wheel_probe.ANSWER
        import fourlegs_engine
        out["engine_file"] = fourlegs_engine.__file__
        bpy.context.scene.render.engine = "FOURLEGS_SPLATS"  # raises if the engine is not registered
        out["render_engine"] = bpy.context.scene.render.engine
        # the installed add-on works with its bundled engine: import a tiny scene
        sys.path.insert(0, {str(REPO / "tests")!r})
        from _blender_helpers import tiny_scene
        from fourlegs_engine.scene import write_bundle
        write_bundle(tiny_scene(), {str(tmp_path / "bundle")!r})
        bpy.context.scene.fourlegs.source_path = {str(tmp_path / "bundle")!r}
        r = bpy.ops.fourlegs.import_scene(filepath={str(tmp_path / "bundle" / "scene.json")!r})
        obj = bpy.context.scene.fourlegs.splat_object
        out["import"] = sorted(r)
        out["points"] = len(obj.data.vertices)
        out["scene_class_file"] = sys.modules[type(mod.importer.engine_scene_for(obj)).__module__].__file__
        bpy.ops.preferences.addon_disable(module=pkg)
        out["disabled"] = not hasattr(bpy.types.Scene, "fourlegs")
        print("RESULT" + json.dumps(out))
    """)
    env = child_env(BLENDER_USER_RESOURCES=str(tmp_path / "blender-user"))
    # run outside the checkout, so the engine imported is the one the extension's wheel installed
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=240,
                          cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    line = [l for l in proc.stdout.splitlines() if l.startswith("RESULT")][-1]
    out = json.loads(line[len("RESULT"):])
    assert out["install"] == ["FINISHED"] and out["enabled"] and out["scene_prop"]
    user = str(tmp_path / "blender-user")
    assert out["engine_file"].startswith(user), out["engine_file"]  # installed from the engine wheel
    assert all(out["operators"]) and out["render_engine"] == "FOURLEGS_SPLATS"
    assert out["wheel"] == 42
    assert out["import"] == ["FINISHED"] and out["points"] == 64
    assert out["scene_class_file"].startswith(user)
    assert out["disabled"]


def test_missing_dependency_wheels_are_reported(tmp_path):
    (tmp_path / "wheels").mkdir()
    with pytest.raises(build.BuildError, match="--fetch-wheels"):
        build.build(tmp_path / "out", wheels_dir=tmp_path / "wheels")
    assert not list((tmp_path / "out").glob("*.zip"))


def test_manifest_version_matches_the_package():
    import tomllib

    import fourlegs_engine

    manifest = tomllib.loads((REPO / "blender_manifest.toml").read_text())
    assert manifest["version"] == fourlegs_engine.__version__
    assert manifest["blender_version_min"] == "5.0.0" and manifest["type"] == "add-on"
