"""The main-job step of ``fourlegs bench device`` (:mod:`.device_steps`): the engine half of the job from an
empty cache, its frames rendered on the device."""
from __future__ import annotations

import os
import statistics
import time
from pathlib import Path
from typing import Any

from .device_steps import CPU_FIGURES, REPO, StepContext, cpu_figures, sync


def step_main_job(ctx: StepContext) -> None:
    """The main job's engine half (``prepare_highlight_job``: scene, language field, query, plan) from an
    empty cache, then every frame of the plan rendered through the engine's rasterizer on the device.
    Blender (import, compositor, MP4, .blend) is not part of it."""
    import torch

    from fourlegs_engine.highlight_job import HighlightJobOptions, StageTimer, prepare_highlight_job
    from fourlegs_engine.highlights.plan import HighlightPlan
    from fourlegs_engine.highlights.preview import frame_at, key_camera
    from fourlegs_engine.render import render_frame
    from fourlegs_engine.render.backends import select_backend

    plan, device = ctx.plan, ctx.device
    os.environ["FOURLEGS_CACHE"] = str(ctx.work / "cache")    # from scratch: every stage runs
    preset = plan["preset"]
    if plan.get("preset_toml"):
        preset = ctx.work / f"{plan['preset']}.toml"
        preset.write_text(plan["preset_toml"], encoding="utf-8")
    timer = StageTimer()
    options = HighlightJobOptions(query=plan["query"], output=ctx.work / "job", demo=plan["demo"],
                                  preset=str(preset), resolution=tuple(plan["resolution"]), overwrite=True)
    ctx.record(query=plan["query"], demo=plan["demo"], preset=plan["preset"], resolution=plan["resolution"],
               blender="not run: no bpy on this machine (import, compositor, MP4 encoding and .blend are "
                       "Blender's part of the job)")
    job = prepare_highlight_job(options, timer)
    stage_devices = {name: "cpu (the engine stage has no device option)" for name in timer.timings}
    ctx.record(stages={name: {"wall_s": timer.timings[name], "cpu_s": timer.cpu_timings.get(name),
                              "device": stage_devices[name]} for name in timer.timings})
    loc = job.plan.get("localization") or {}
    ctx.record(answer={"segment": loc.get("segment"), "peak": loc.get("peak"), "best_view": loc.get("best_view"),
                       "found": loc.get("found")})
    hp = HighlightPlan.from_dict(job.plan)
    width = int(plan["resolution"][0])
    frames = list(range(hp.frame_start, hp.frame_end + 1))
    backend = select_backend("auto", device, ("rgb",)).__module__.rsplit(".", 1)[-1].replace("_backend", "")
    keep = {s.frame_start + s.num_frames // 2: s.name for s in hp.shots}
    kept: list[tuple[str, int, Any]] = []
    times = []
    background = torch.zeros(3, device=device)
    name = f"render frames ({device.type})"
    with timer(name), torch.no_grad():
        for frame in frames:
            start = time.perf_counter()
            cam = key_camera(hp.camera_key_at(frame), hp, width)
            g = frame_at(job.scene.gaussians, hp.timestep_at(frame), str(device))
            rgb = render_frame(g, cam, outputs=("rgb",), background=background)["rgb"]
            sync(device)
            times.append(time.perf_counter() - start)
            if frame in keep:
                kept.append((keep[frame], frame, rgb.clamp(0, 1).cpu().numpy()))
            if ctx.remaining() < 3:
                break
    ctx.record(stages={**ctx.result["stages"], name: {"wall_s": timer.timings[name],
                                                     "cpu_s": timer.cpu_timings[name], "device": str(device)}},
               frames={"rendered": len(times), "planned": len(frames), "backend": backend,
                       "seconds_per_frame_median": statistics.median(times) if times else None,
                       "fps": 1.0 / statistics.median(times) if times else None,
                       "gaussians": int(job.scene.gaussians.num_gaussians)},
               total_seconds=timer.total_seconds())
    _frames_strip(kept, ctx.work.parent / "contact_main_job.png", str(device))
    cpu = cpu_figures("main_job")
    if cpu:
        ctx.record(cpu_stages={r["stage"]: r["wall_s"] for r in cpu.get("stages", [])},
                   cpu_total_seconds=cpu.get("report_total_seconds"), cpu_frames=cpu.get("frames"),
                   cpu_source=str(CPU_FIGURES["main_job"].relative_to(REPO)))


def _frames_strip(kept: list[tuple[str, int, Any]], path: Path, device: str) -> None:
    """One frame per shot, side by side (tiles 320 px wide), labelled with the shot and frame."""
    from PIL import Image, ImageDraw

    from fourlegs_engine.fileio import atomic_path

    import numpy as np

    if not kept:
        return
    h, w = kept[0][2].shape[:2]
    tw = min(320, w)
    th = max(1, round(h * tw / w))
    label = 14
    title = f"main job frames rendered by the engine on {device} (no Blender compositing)"
    sheet = Image.new("RGB", (max(tw * len(kept), 6 * len(title) + 8), th + 2 * label), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    draw.text((4, 1), title, fill=(0, 0, 0))
    for k, (shot, frame, img) in enumerate(kept):
        tile = Image.fromarray((np.clip(img, 0, 1) * 255).astype(np.uint8)).resize((tw, th), Image.BOX)
        sheet.paste(tile, (k * tw, 2 * label))
        draw.text((k * tw + 3, label + 1), f"{shot}, frame {frame}", fill=(0, 0, 0))
    with atomic_path(path) as tmp:
        sheet.save(tmp, format="PNG")
