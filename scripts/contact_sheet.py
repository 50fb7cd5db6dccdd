"""Contact sheet of a highlight video: frames read with Blender's FFmpeg, tiled with matplotlib.

    python scripts/contact_sheet.py out/highlight.mp4 out/plan.json docs/images/demo_contact_sheet.png

Takes ``--per-shot`` frames evenly spread over every shot of the plan (captioned with the shot's name
and effect) and writes a PNG grid, one row per shot.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np


def read_frames(video: Path, frames: list[int], width: int) -> dict[int, np.ndarray]:
    """(H,W,3) float RGB of each 1-based ``frames`` of ``video``, scaled to ``width`` pixels wide."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.sequence_editor_create()
    editor = scene.sequence_editor
    strips = editor.strips if hasattr(editor, "strips") else editor.sequences  # bpy >= 4.4 : older
    strip = strips.new_movie("video", str(video), channel=1, frame_start=1)
    scene.render.resolution_x = strip.elements[0].orig_width
    scene.render.resolution_y = strip.elements[0].orig_height
    scene.render.resolution_percentage = max(1, round(100 * width / scene.render.resolution_x))
    scene.render.use_sequencer = True
    scene.render.image_settings.file_format = "PNG"
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for f in frames:
            scene.frame_set(f)
            scene.render.filepath = str(Path(tmp) / f"{f:05d}.png")
            bpy.ops.render.render(write_still=True)
            image = bpy.data.images.load(scene.render.filepath)
            w, h = image.size
            out[f] = np.asarray(image.pixels[:], np.float32).reshape(h, w, 4)[::-1, :, :3]
            bpy.data.images.remove(image)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("video")
    p.add_argument("plan")
    p.add_argument("output")
    p.add_argument("--per-shot", type=int, default=4, help="frames per shot (default 4)")
    p.add_argument("--width", type=int, default=320, help="width of one tile in pixels (default 320)")
    args = p.parse_args(argv)
    plan = json.loads(Path(args.plan).read_text())
    rows = []
    for shot in plan["shots"]:
        picks = np.linspace(shot["frame_start"], shot["frame_end"], args.per_shot + 2)[1:-1].round().astype(int)
        rows.append((f"{shot['name']} ({shot['effect']})", [int(f) - plan["frame_start"] + 1 for f in picks]))
    images = read_frames(Path(args.video).resolve(), sorted({f for _, fs in rows for f in fs}), args.width)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h, w = next(iter(images.values())).shape[:2]
    fig, axes = plt.subplots(len(rows), args.per_shot, figsize=(args.per_shot * w / 100, len(rows) * (h + 24) / 100),
                             dpi=100, squeeze=False)
    for (label, frames), row in zip(rows, axes):
        for f, ax in zip(frames, row):
            ax.imshow(np.clip(images[f], 0, 1))
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"{label}, frame {f}", fontsize=8)
    fig.suptitle(f"\"{plan['query']}\" — preset {plan.get('preset', 'broadcast')}", fontsize=10)
    fig.tight_layout()
    Path(args.output).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.output)
    plt.close(fig)
    print(args.output)
    return 0


if __name__ == "__main__":
    sys.exit(main())
