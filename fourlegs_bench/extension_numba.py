"""CPU seconds of one splat render inside Blender with the extension's bundled numba, and without it.

    python -m fourlegs_bench.extension_numba [--scene DIR] [--resolution 1280x720] [--repeats 3] [-o DIR]

Builds the linux-x64 extension zip from the cached wheels (``fourlegs build-extension --fetch-wheels
--platform linux-x64`` downloads them), and for each variant installs it into a fresh Blender user folder
in a child Python (the bpy module): ``numba``, numba and llvmlite imported only from the extension;
``torch path``, numba made unimportable, as an extension without it would be. The child imports the
scene (``--scene``: a bundle directory, default the synthetic ``demo`` scene), renders
one frame from its first camera through the 4-LEGS Splats engine to warm up (numba compiles its kernels
once; they are cached in the extension's folder), then ``--repeats`` frames, each timed in process CPU
seconds (every thread) and wall seconds. Writes ``extension_numba.json`` and ``extension_numba.md`` into
``-o`` (refused if they exist, unless ``--overwrite``).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

#: sitecustomize of each variant's child Python
SITECUSTOMIZE = {
    "numba": textwrap.dedent("""
        import importlib.machinery, os, sys

        class ExtensionOnlyNumba:
            def find_spec(self, name, path=None, target=None):
                if name not in ("numba", "llvmlite"):
                    return None
                user = os.environ["BLENDER_USER_RESOURCES"]
                spec = importlib.machinery.PathFinder.find_spec(name, [p for p in sys.path if p.startswith(user)])
                if spec is None:
                    raise ModuleNotFoundError(f"No module named {name!r} in the extension", name=name)
                return spec

        sys.meta_path.insert(0, ExtensionOnlyNumba())
    """),
    "torch path": "import sys\nsys.modules['numba'] = None\n",
}

CHILD = textwrap.dedent("""
    import json, statistics, sys, time
    import bpy
    zip_path, scene_arg = sys.argv[1], sys.argv[2]
    width, height, repeats = (int(v) for v in sys.argv[3:6])
    res = bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True)
    assert "FINISHED" in res, res
    pkg = sys.modules["bl_ext.user_default.fourlegs_highlights"]
    from fourlegs_engine import api
    from fourlegs_engine.render import cpu_kernels
    if scene_arg.startswith("synthetic:"):
        from fourlegs_engine.demo.synthetic import generate_scene
        scene = generate_scene(scene_arg.split(":", 1)[1])
        pkg.importer.import_scene(bpy.context.scene, scene)
    else:
        scene = api.open_scene(scene_arg)
        pkg.importer.import_scene(bpy.context.scene, scene, source=scene_arg)
    bl_scene = bpy.context.scene
    bl_scene.camera = sorted((o for o in bl_scene.objects if o.type == "CAMERA"), key=lambda o: o.name)[0]
    bl_scene.render.engine = "FOURLEGS_SPLATS"
    bl_scene.render.resolution_x, bl_scene.render.resolution_y = width, height
    bl_scene.render.resolution_percentage = 100
    blends = [0]
    blend = cpu_kernels.blend_tiles
    def counted(*a, **k):
        blends[0] += 1
        return blend(*a, **k)
    cpu_kernels.blend_tiles = counted
    def render():
        c0, w0 = time.process_time(), time.perf_counter()
        result = bpy.ops.render.render()
        assert "FINISHED" in result, result
        return time.process_time() - c0, time.perf_counter() - w0
    warm_cpu, warm_wall = render()
    runs = [render() for _ in range(repeats)]
    print("RESULT" + json.dumps({
        "numba": cpu_kernels.available(), "numba_blends": blends[0], "gaussians": int(scene.num_gaussians),
        "warmup_cpu_s": warm_cpu, "warmup_wall_s": warm_wall,
        "cpu_s": [r[0] for r in runs], "wall_s": [r[1] for r in runs], "python": sys.version.split()[0]}))
""")


def run_variant(variant: str, zip_path: Path, scene_arg: str, width: int, height: int, repeats: int) -> dict:
    with tempfile.TemporaryDirectory(prefix="fourlegs-bench-numba-") as tmp:
        shim = Path(tmp) / "shim"
        shim.mkdir()
        (shim / "sitecustomize.py").write_text(SITECUSTOMIZE[variant])
        env = dict(os.environ, BLENDER_USER_RESOURCES=str(Path(tmp) / "user"), PYTHONPATH=str(shim))
        proc = subprocess.run([sys.executable, "-c", CHILD, str(zip_path), scene_arg, str(width), str(height),
                               str(repeats)], capture_output=True, text=True, env=env, cwd=tmp)
    lines = [l for l in proc.stdout.splitlines() if l.startswith("RESULT")]
    if proc.returncode != 0 or not lines:
        raise SystemExit(f"the {variant} child failed:\n{proc.stdout[-2000:]}{proc.stderr[-2000:]}")
    out = json.loads(lines[-1][len("RESULT"):])
    out["cpu_s_median"], out["wall_s_median"] = statistics.median(out["cpu_s"]), statistics.median(out["wall_s"])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="synthetic:demo",
                    help="scene directory (e.g. a `fourlegs fit` bundle), or synthetic:demo (the default)")
    ap.add_argument("--resolution", default="1280x720")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("-o", "--output", default=str(REPO / "docs" / "bench" / "extension_numba"))
    ap.add_argument("--overwrite", action="store_true")
    args = ap.parse_args()
    from fourlegs_addon import build
    from fourlegs_engine.fileio import write_bytes_atomic, write_json_atomic

    out_dir = Path(args.output)
    targets = [out_dir / "extension_numba.json", out_dir / "extension_numba.md"]
    existing = [str(t) for t in targets if t.exists()]
    if existing and not args.overwrite:
        raise SystemExit(f"{', '.join(existing)}: already exists (pass --overwrite to replace)")
    width, height = (int(v) for v in args.resolution.lower().split("x"))
    scene_arg = args.scene
    with tempfile.TemporaryDirectory(prefix="fourlegs-bench-ext-") as tmp:
        zip_path = build.build(tmp, platforms=["linux-x64"])[0]
        results = {variant: run_variant(variant, zip_path, scene_arg, width, height, args.repeats)
                   for variant in SITECUSTOMIZE}
    report = {"scene": scene_arg, "resolution": [width, height], "repeats": args.repeats,
              "cpu_count": os.cpu_count(), "variants": results,
              "cpu_speedup": results["torch path"]["cpu_s_median"] / results["numba"]["cpu_s_median"],
              "wall_speedup": results["torch path"]["wall_s_median"] / results["numba"]["wall_s_median"]}
    rows = [f"| {v} | {r['numba']} | {r['numba_blends']} | {r['cpu_s_median']:.2f} | {r['wall_s_median']:.2f} | "
            f"{r['warmup_cpu_s']:.2f} |" for v, r in results.items()]
    table = "\n".join([
        f"One {width}x{height} render of `{scene_arg}` ({next(iter(results.values()))['gaussians']} Gaussians) "
        f"through the 4-LEGS Splats engine in the installed extension; median of {args.repeats}.",
        "", "| variant | numba imported | numba blends | CPU s | wall s | first render CPU s |",
        "| --- | --- | --- | --- | --- | --- |", *rows, "",
        f"numba: {report['cpu_speedup']:.2f}x less CPU, {report['wall_speedup']:.2f}x less wall time.", ""])
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json_atomic(targets[0], report)
    write_bytes_atomic(targets[1], table.encode("utf-8"))
    print(table)


if __name__ == "__main__":
    main()
