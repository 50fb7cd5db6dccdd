"""Build the Blender extension zip (no bpy needed): the add-on + the engine and its dependencies as wheels.

Layout of the zip (Blender >= 4.2 extension format; Python dependencies ship as wheels listed in the
manifest, the way Blender documents it)::

    blender_manifest.toml      (the repository's manifest + the ``wheels`` list)
    __init__.py ...            (this add-on package, without what only runs outside Blender:
                                ``build.py`` and the ``fourlegs`` command registration)
    wheels/fourlegs_engine-<version>-py3-none-any.whl
                               (the engine, built here from this project, with the presets in
                                ``fourlegs_engine/highlights/presets/``; the benchmarks stay out)
    wheels/*.whl               (the engine's dependencies Blender installs on enable)

Dependency choice (Blender 4.2 - 5.0 run Python 3.11 and ship numpy 1.x; Blender 5.1 and later run
Python 3.13): wheels for both, per platform; Blender installs the ones matching its Python.

- bundled: ``scipy`` (kNN, morphology in query/highlights; ~35-40 MB per platform and Python; cp311:
  1.13.1, the newest release whose wheels accept Blender's numpy 1.2x; cp313: 1.16.3, which accepts
  numpy 1.25.2 - 2.5, the range of the numpy 2.x that Python 3.13 Blenders ship), ``plyfile`` (PLY scenes; pure
  Python), ``tqdm`` (pure Python) and ``safetensors`` (one abi3 wheel per platform serves both
  Pythons), for windows-x64, linux-x64, macos-arm64 and macos-x64. A wheel whose file name is the same
  for both Pythons (pure-Python or abi3) is shipped once.
- not bundled: ``torch``. A CPU build is 70-250 MB per platform and the PyPI Linux wheel depends on
  ~15 NVIDIA wheels (> 2 GB) that Blender's wheel installer does not resolve. Importing a scene and
  playing it on the timeline do not need torch; the add-on's preferences install it (CPU or CUDA
  build) into the extension's own site-packages (:mod:`fourlegs_addon.torch_install`); a
  platform-specific build can bundle a torch wheel the user provides with ``--extra-wheel``.
- bundled: ``numba`` + ``llvmlite`` (the fused CPU splat/blend kernels of
  :mod:`fourlegs_engine.render.cpu_kernels`, which the render engine, the viewport and the lift take when
  numba imports; 43-64 MB per platform and Python, llvmlite being most of it). numba 0.68.1 (llvmlite
  0.50.0) accepts numpy 1.22 - 2.5, which holds Blender 5.0's numpy 1.26 and the numpy 2.2 - 2.5 the
  Python 3.13 Blenders ship (bpy 5.2 requires numpy >= 2.2, < 3); its Linux wheels are manylinux_2_28,
  the glibc Blender >= 4.2 requires. macos-x64 has no numba wheel after 0.62.1 (llvmlite 0.45.1, numpy
  1.22 - 2.3): that platform gets those; Intel Macs end with Blender 4.5 (Python 3.11, numpy 1.26). Where
  numba refuses Blender's numpy at import (an ImportError), the engine takes its torch path.
- not needed inside Blender: numpy (Blender ships it), matplotlib (the panel draws the s_t curve
  itself), OpenEXR (Blender writes EXR).

Validation and packing use Blender's own tool (``blender_ext.py validate`` / ``build``), found in the
bpy wheel or a Blender install, run under the current Python.
"""
from __future__ import annotations

import base64
import hashlib
import os
import re
import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path
from typing import Iterable, Optional, Sequence

ADDON_DIR = Path(__file__).resolve().parent
REPO_ROOT = ADDON_DIR.parent
MANIFEST_NAME = "blender_manifest.toml"
#: Blender's Python versions (4.2 - 5.0: 3.11; 5.1 and later: 3.13)
PYTHON_VERSIONS = ("3.11", "3.13")

#: Blender platform -> pip ``--platform`` tags (newest first; pip takes any matching wheel)
PLATFORM_TAGS = {
    "windows-x64": ["win_amd64"],
    "linux-x64": ["manylinux_2_28_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64"],
    "macos-arm64": ["macosx_12_0_arm64", "macosx_11_0_arm64"],
    "macos-x64": ["macosx_10_15_x86_64", "macosx_10_14_x86_64", "macosx_10_13_x86_64", "macosx_10_12_x86_64",
                  "macosx_10_9_x86_64"],
}
#: bundled dependencies per Python version (requirement specifiers); everything the add-on imports
#: inside Blender except numpy (Blender ships it) and torch (installed from the add-on's preferences)
DEPENDENCIES_BY_PYTHON = {
    "3.11": ("scipy==1.13.1", "plyfile>=1.0", "tqdm>=4.60", "safetensors>=0.4"),
    "3.13": ("scipy==1.16.3", "plyfile>=1.0", "tqdm>=4.60", "safetensors>=0.4"),
}
#: numba and its llvmlite (same pins for both Pythons), per Blender platform; see the module docstring
NUMBA = ("numba==0.68.1", "llvmlite==0.50.0")
NUMBA_BY_PLATFORM = {"macos-x64": ("numba==0.62.1", "llvmlite==0.45.1")}


def requirements(python_version: str, platform: str) -> tuple[str, ...]:
    """The requirement specifiers bundled for one Blender Python version and platform."""
    return DEPENDENCIES_BY_PYTHON[python_version] + NUMBA_BY_PLATFORM.get(platform, NUMBA)


def _distribution(requirement: str) -> str:
    return re.split(r"[=<>!~ ]", requirement)[0].lower().replace("-", "_")


#: the distribution names, as wheel files spell them
DEPENDENCIES = tuple(dict.fromkeys(_distribution(r) for py in PYTHON_VERSIONS for plat in PLATFORM_TAGS
                                   for r in requirements(py, plat)))
#: distribution -> the versions pinned (``==``) for it on some platform and Python; a cached wheel of
#: another version is not bundled
PINNED_VERSIONS = {d: {r.split("==", 1)[1] for py in PYTHON_VERSIONS for plat in PLATFORM_TAGS
                       for r in requirements(py, plat) if "==" in r and _distribution(r) == d}
                   for d in DEPENDENCIES}
#: add-on modules that run only outside Blender (the build itself, the ``fourlegs`` CLI registration)
NOT_IN_BLENDER = ("build.py", "commands.py")


class BuildError(RuntimeError):
    """The extension could not be built (message says why)."""


def find_blender_ext() -> Path:
    """Blender's extension tool ``blender_ext.py`` (from the bpy module, else ``$BLENDER_EXT``)."""
    env = os.environ.get("BLENDER_EXT")
    if env and Path(env).is_file():
        return Path(env)
    import importlib.util

    spec = importlib.util.find_spec("bpy")
    roots = [Path(p) for p in (spec.submodule_search_locations or [])] if spec else []
    for root in roots:
        for cand in sorted(root.glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"), reverse=True):
            return cand
    raise BuildError("Blender's blender_ext.py was not found: install the bpy module (pip install bpy) or "
                     "set BLENDER_EXT to <blender>/<version>/scripts/addons_core/bl_pkg/cli/blender_ext.py")


def run_blender_ext(args: Sequence[str]) -> str:
    """Run ``blender_ext.py ARGS`` under this Python; raise :class:`BuildError` with its output on failure."""
    proc = subprocess.run([sys.executable, str(find_blender_ext()), *args], capture_output=True, text=True)
    if proc.returncode != 0:
        raise BuildError(f"blender_ext {args[0]} failed:\n{proc.stdout}{proc.stderr}".rstrip())
    return proc.stdout


def validate(source_dir: str | Path) -> str:
    """Validate an extension directory (manifest + files) with Blender's validator."""
    return run_blender_ext(["validate", str(source_dir)])


def pip_download_command(dest: str | Path, platform: str, python_version: str,
                         requirements: Iterable[str]) -> list[str]:
    """The ``pip download`` command fetching binary wheels of ``requirements`` for one Blender platform
    and Python version (no dependency resolution: the list is complete)."""
    cmd = [sys.executable, "-m", "pip", "download", "--quiet", "--only-binary=:all:", "--no-deps",
           "--python-version", python_version, "--implementation", "cp", "-d", str(dest)]
    for tag in PLATFORM_TAGS[platform]:
        cmd += ["--platform", tag]
    return cmd + list(requirements)


def fetch_wheels(dest: str | Path, platforms: Iterable[str] = tuple(PLATFORM_TAGS),
                 python_versions: Iterable[str] = PYTHON_VERSIONS) -> list[Path]:
    """Download the binary wheels of :func:`requirements` for each Blender platform and Python version
    with pip (PyPI). Wheels named alike for several targets (pure-Python, abi3) are downloaded once, and
    none already in ``dest`` again."""
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    for python_version in python_versions:
        for platform in platforms:
            cmd = pip_download_command(dest, platform, python_version, requirements(python_version, platform))
            proc = subprocess.run(cmd, capture_output=True, text=True)
            if proc.returncode != 0:
                raise BuildError(f"pip could not download wheels for {platform}, Python {python_version}:\n"
                                 f"{proc.stderr.strip()}")
    return sorted(dest.glob("*.whl"))


def _wheel_tags(wheel: str | Path) -> Optional[tuple[str, set[tuple[str, str, str]]]]:
    """(distribution, {(python, abi, platform) tags}) of a wheel file name; None when it is not one."""
    parts = Path(wheel).name[:-len(".whl")].split("-")
    if len(parts) not in (5, 6):
        return None
    py, abi, plat = (set(p.split(".")) for p in parts[-3:])
    return parts[0].lower(), {(a, b, c) for a in py for b in abi for c in plat}


def _accepted_tags(python_version: str, platform: str) -> set[tuple[str, str, str]]:
    """The wheel tags Blender's Python ``python_version`` installs on ``platform``."""
    major, minor = python_version.split(".")
    cp = f"cp{major}{minor}"
    accepted = {("py3", "none", "any"), (f"py{major}{minor}", "none", "any")}
    for ptag in PLATFORM_TAGS[platform]:
        accepted |= {(cp, cp, ptag)} | {(f"cp3{m}", "abi3", ptag) for m in range(2, int(minor) + 1)}
    return accepted


def serves(wheel: str | Path, platforms: Iterable[str], python_versions: Iterable[str] = PYTHON_VERSIONS) -> bool:
    """Whether a wheel installs on one of ``platforms`` under one of ``python_versions``."""
    parsed = _wheel_tags(wheel)
    return parsed is not None and any(parsed[1] & _accepted_tags(py, plat)
                                      for py in python_versions for plat in platforms)


def missing_wheels(wheels: Iterable[Path], platforms: Iterable[str] = tuple(PLATFORM_TAGS),
                   python_versions: Iterable[str] = PYTHON_VERSIONS) -> list[str]:
    """``"name (platform, Python x.y)"`` for every dependency without a wheel installable there."""
    parsed = [t for t in map(_wheel_tags, wheels) if t is not None]
    out = []
    for python_version in python_versions:
        for platform in platforms:
            accepted = _accepted_tags(python_version, platform)
            for dep in dict.fromkeys(map(_distribution, requirements(python_version, platform))):
                if not any(name == dep and tags & accepted for name, tags in parsed):
                    out.append(f"{dep} ({platform}, Python {python_version})")
    return out


def is_bundled(wheel: str | Path) -> bool:
    """Whether a wheel file is one of the dependencies, in a pinned version where its version is pinned."""
    name, version = Path(wheel).name.split("-")[:2]
    dist = name.lower()
    return dist in DEPENDENCIES and (not PINNED_VERSIONS[dist] or version in PINNED_VERSIONS[dist])


def manifest_with_wheels(text: str, wheel_names: Sequence[str]) -> str:
    """Insert ``wheels = [...]`` among the manifest's top-level keys (before its first table)."""
    if re.search(r"^wheels\s*=", text, flags=re.M):
        raise BuildError(f"{MANIFEST_NAME} already lists wheels; they are added by the build")
    if not wheel_names:
        return text
    block = "wheels = [\n" + "".join(f'  "./wheels/{name}",\n' for name in wheel_names) + "]\n\n"
    match = re.search(r"^\[", text, flags=re.M)
    at = match.start() if match else len(text)
    return text[:at] + block + text[at:]


def engine_wheel(dest_dir: str | Path) -> Path:
    """Write a wheel of this project's engine (``fourlegs_engine`` with its presets) into ``dest_dir``.

    A pure-Python ``py3-none-any`` wheel of the installed engine sources: the package, the repository's
    ``presets/*.toml`` as package data in ``fourlegs_engine/highlights/presets/``, and the dist-info
    (METADATA, WHEEL, RECORD with sha256 digests) the wheel format requires.
    """
    import fourlegs_engine

    version = fourlegs_engine.__version__
    source = Path(fourlegs_engine.__file__).resolve().parent
    files: dict[str, bytes] = {}
    for path in sorted(source.rglob("*")):
        rel = path.relative_to(source)
        if path.is_dir() or any(part == "__pycache__" or part.startswith(".") for part in rel.parts) \
                or path.suffix in (".pyc", ".pyo"):
            continue
        files[f"fourlegs_engine/{rel.as_posix()}"] = path.read_bytes()
    for preset in sorted((REPO_ROOT / "presets").glob("*.toml")):
        files[f"fourlegs_engine/highlights/presets/{preset.name}"] = preset.read_bytes()
    info = f"fourlegs_engine-{version}.dist-info"
    files[f"{info}/METADATA"] = (f"Metadata-Version: 2.1\nName: fourlegs-engine\nVersion: {version}\n"
                                 "Summary: 4-LEGS highlights engine (bundled with the Blender extension)\n"
                                 "License: GPL-3.0-or-later\n").encode()
    files[f"{info}/WHEEL"] = b"Wheel-Version: 1.0\nGenerator: fourlegs_addon.build\nRoot-Is-Purelib: true\nTag: py3-none-any\n"
    record = []
    for name, data in files.items():
        digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
        record.append(f"{name},sha256={digest},{len(data)}")
    record.append(f"{info}/RECORD,,")
    files[f"{info}/RECORD"] = ("\n".join(record) + "\n").encode()
    dest_dir = Path(dest_dir)
    dest_dir.mkdir(parents=True, exist_ok=True)
    wheel = dest_dir / f"fourlegs_engine-{version}-py3-none-any.whl"
    with zipfile.ZipFile(wheel, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, data in files.items():
            zf.writestr(zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0)), data, zipfile.ZIP_DEFLATED)
    return wheel


def check_platforms(platforms: Sequence[str]) -> None:
    """BuildError unless ``platforms`` is a non-empty list of Blender platforms this build knows."""
    unknown = sorted(set(platforms) - set(PLATFORM_TAGS))
    if unknown or not platforms:
        raise BuildError(f"unknown platform(s) {', '.join(unknown) or 'none given'} (one or more of "
                         f"{', '.join(PLATFORM_TAGS)})")


def manifest_for_platforms(text: str, platforms: Sequence[str]) -> str:
    """The manifest with its ``platforms = [...]`` list replaced by ``platforms``."""
    check_platforms(platforms)
    line = "platforms = [" + ", ".join(f'"{p}"' for p in platforms) + "]"
    out, count = re.subn(r"^platforms\s*=\s*\[[^\]]*\]", line, text, flags=re.M)
    if count != 1:
        raise BuildError(f"{MANIFEST_NAME} has no single `platforms = [...]` list to restrict")
    return out


def wheel_problem(wheel: Path) -> Optional[str]:
    """Why ``wheel`` is not a wheel Blender can install (None when it is): a zip whose members read back
    intact (CRC), holding a ``*.dist-info/WHEEL`` and ``*.dist-info/METADATA``."""
    try:
        with zipfile.ZipFile(wheel) as zf:
            names = zf.namelist()
            broken = zf.testzip()
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as exc:
        return f"not a zip archive: {exc}"
    if broken is not None:
        return f"member {broken} is damaged"
    for required in ("WHEEL", "METADATA"):
        if not any(n.count("/") == 1 and n.split("/")[0].endswith(".dist-info") and n.endswith("/" + required)
                   for n in names):
            return f"no *.dist-info/{required}"
    return None


def stage(dest: str | Path, wheels: Iterable[str | Path] = (), manifest: Optional[Path] = None,
          platforms: Optional[Sequence[str]] = None) -> Path:
    """Assemble the extension's source directory at ``dest`` (must not exist): the add-on, the engine
    wheel and ``wheels``, with the manifest listing every wheel (and only ``platforms``, when given)."""
    dest = Path(dest)
    manifest = manifest or REPO_ROOT / MANIFEST_NAME
    if not manifest.is_file():
        raise BuildError(f"{manifest}: missing; build the extension from a source checkout of the project")
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.pyo", ".*", "*.part*", *NOT_IN_BLENDER)
    shutil.copytree(ADDON_DIR, dest, ignore=ignore)
    (dest / "wheels").mkdir()
    names = [engine_wheel(dest / "wheels").name]
    for wheel in sorted({Path(w).resolve() for w in wheels}, key=lambda p: p.name):
        if wheel.suffix != ".whl" or not wheel.is_file():
            raise BuildError(f"{wheel}: not a wheel file")
        problem = wheel_problem(wheel)
        if problem is not None:
            raise BuildError(f"{wheel}: not a usable wheel ({problem})")
        shutil.copy2(wheel, dest / "wheels" / wheel.name)
        names.append(wheel.name)
    text = manifest.read_text(encoding="utf-8")
    if platforms is not None:
        text = manifest_for_platforms(text, platforms)
    (dest / MANIFEST_NAME).write_text(manifest_with_wheels(text, names), encoding="utf-8")
    return dest


def build(output_dir: str | Path, *, wheels_dir: Optional[str | Path] = None, fetch: bool = False,
          extra_wheels: Iterable[str | Path] = (), with_wheels: bool = True, split_platforms: bool = False,
          platforms: Optional[Sequence[str]] = None, overwrite: bool = False) -> list[Path]:
    """Build the extension zip(s) into ``output_dir``; returns their paths.

    Args:
        wheels_dir: where dependency wheels are looked for (and downloaded to with ``fetch``); default
            ``<cache>/extension-wheels``.
        fetch: download missing dependency wheels from PyPI first.
        extra_wheels: additional wheels to bundle (e.g. a platform's torch CPU wheel).
        with_wheels: False builds without dependency wheels (the user's Blender Python must provide
            them), e.g. for offline tests.
        split_platforms: one zip per platform, each with only its own wheels.
        platforms: build for these Blender platforms only (default: every one of :data:`PLATFORM_TAGS`);
            only their wheels are needed and bundled.
    """
    from fourlegs_engine.paths import cache_dir

    if platforms is not None:
        check_platforms(platforms)
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    wheels: list[Path] = []
    if with_wheels:
        wdir = Path(wheels_dir) if wheels_dir else cache_dir() / "extension-wheels"
        targets = tuple(platforms) if platforms is not None else tuple(PLATFORM_TAGS)
        if fetch:
            fetch_wheels(wdir, platforms=targets)
        wheels = sorted(wdir.glob("*.whl")) if wdir.is_dir() else []
        wheels = [w for w in wheels if is_bundled(w) and serves(w, targets)]
        missing = missing_wheels(wheels, platforms=targets)
        if missing:
            raise BuildError(f"dependency wheels missing in {wdir}: {', '.join(missing)} (pass --fetch-wheels "
                             "to download them from PyPI, or --no-wheels to build without them)")
    wheels += [Path(w) for w in extra_wheels]
    with tempfile.TemporaryDirectory(prefix="fourlegs-ext-") as tmp:
        src = stage(Path(tmp) / "src", wheels, platforms=platforms)
        validate(src)
        out_tmp = Path(tmp) / "out"
        out_tmp.mkdir()
        args = ["build", "--source-dir", str(src), "--output-dir", str(out_tmp)]
        if split_platforms:
            args.append("--split-platforms")
        run_blender_ext(args)
        results = []
        for zip_path in sorted(out_tmp.glob("*.zip")):
            target = output_dir / zip_path.name
            if target.exists() and not overwrite:
                raise BuildError(f"{target}: already exists (pass --overwrite to replace it)")
            shutil.move(str(zip_path), target)
            results.append(target)
    if not results:
        raise BuildError("blender_ext build produced no zip")
    return results
