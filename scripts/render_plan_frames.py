"""Render chosen frames of a plan through Blender (the bpy module, the 4-LEGS Splats engine and the add-on's
compositor: blur and desaturation included), the subject's relevancy taken from a `fourlegs bench
real-annotations` report, and lay them out as one PNG sheet:

    python scripts/render_plan_frames.py SCENE PLAN.json REPORT.json "the ball in the air" 61,98,230,298 OUT.png

Used for the Blender sheet of docs/benchmarks_shots.md (the plan from `fourlegs bench shots ... --annotations`).
Renders at half the plan's resolution.
"""
from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def main(argv: list[str]) -> int:
    scene_path, plan_path, report_path, phrase, frames, out = argv
    import bpy
    from PIL import Image, ImageDraw

    from fourlegs_addon import importer, operators, registration
    from fourlegs_bench.shots import AnnotatedBallLocalizer
    from fourlegs_engine.scene import load_bundle

    registration.register()
    plan = json.loads(Path(plan_path).read_text())
    scene = load_bundle(scene_path)
    loc = AnnotatedBallLocalizer(scene, json.loads(Path(report_path).read_text()), phrase)
    bl = bpy.context.scene
    bl.fourlegs.renderer = "FOURLEGS"
    obj = importer.import_scene(bl, scene)
    importer.set_relevancy_provider(obj, lambda t: loc.members(t).astype(np.float32))
    operators.generate_highlight(bl, plan)
    bl.render.resolution_percentage = 50
    shots = {f: s for s in plan["shots"] for f in range(s["frame_start"], s["frame_end"] + 1)}
    blur = {int(k): v for k, v in ((plan.get("blur") or {}).get("weights") or {}).items()}
    desat = {int(k): v for k, v in ((plan.get("desaturate") or {}).get("weights") or {}).items()}
    tiles = []
    with tempfile.TemporaryDirectory() as tmp:
        for f in (int(v) for v in frames.split(",")):
            cpu = time.process_time()
            bl.frame_set(f)
            bl.render.filepath = f"{tmp}/frame_{f:04d}.png"
            bpy.ops.render.render(write_still=True)
            label = f"{shots[f]['name']} f{f} t={bl.fourlegs.timestep:.1f}"
            label += f" blur {blur[f]:.2f}" if blur.get(f, 0) > 0 else ""
            label += f" desat {desat[f]:.2f}" if desat.get(f, 0) > 0 else ""
            tiles.append((label, Image.open(bl.render.filepath).convert("RGB")))
            print(f"frame {f}: {time.process_time() - cpu:.1f} CPU s (this process)", flush=True)
    w, h = tiles[0][1].size
    cols = 2
    rows = (len(tiles) + cols - 1) // cols
    sheet = Image.new("RGB", (w * cols, (h + 16) * rows), "white")
    draw = ImageDraw.Draw(sheet)
    for i, (label, im) in enumerate(tiles):
        x, y = (i % cols) * w, (i // cols) * (h + 16)
        sheet.paste(im, (x, y + 16))
        draw.text((x + 4, y + 2), label, fill="black")
    sheet.save(out)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
