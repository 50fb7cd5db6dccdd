"""The report of ``fourlegs bench device``: JSON, Markdown (a "GPU" section ready for docs/benchmarks.md)
and a contact sheet, all written into the report folder after every step.

The folder receives at most six files, each written atomically: ``device_report.json``,
``device_report.md``, ``device_contact.png``, ``cuda_tests.txt``, ``gsplat_build.txt`` (and the
``device_log.txt`` that ``scripts/device_check.sh`` tees its output to).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Optional

REPORT_FILES = ("device_report.json", "device_report.md", "device_contact.png", "cuda_tests.txt",
                "gsplat_build.txt")
#: the longest tail of a log copied into the report folder
LOG_TAIL_BYTES = 1 << 20
STEP_TITLES = {"env": "Environment", "viclip": "ViCLIP", "raster_torch": "Rasterizer, torch backend",
               "main_job": "Main job", "raster_gsplat": "Rasterizer, gsplat backend", "cuda_tests": "Tests marked cuda",
               "fit": "Fit (fourlegs fit)"}


def publish(report: dict[str, Any], out: Path, work: Path, gsplat_log: Optional[Path]) -> None:
    """(Re)write every report file from ``report`` and the steps' artefacts in ``work``."""
    from fourlegs_engine.fileio import write_bytes_atomic, write_json_atomic

    write_json_atomic(out / "device_report.json", _finite(report))
    write_bytes_atomic(out / "device_report.md", markdown(report).encode("utf-8"))
    for source, name in ((work / "cuda_tests" / "cuda_tests.txt", "cuda_tests.txt"), (gsplat_log, "gsplat_build.txt")):
        if source is not None and Path(source).is_file():
            write_bytes_atomic(out / name, _tail(Path(source)))
    strips = [work / "contact_fit.png", work / "contact_main_job.png"]
    if any(p.is_file() for p in strips):
        contact_sheet([p for p in strips if p.is_file()], out / "device_contact.png")


def _tail(path: Path) -> bytes:
    data = path.read_bytes()
    return data if len(data) <= LOG_TAIL_BYTES else b"[... cut ...]\n" + data[-LOG_TAIL_BYTES:]


def _finite(value: Any) -> Any:
    """NaN / Inf become None so the JSON stays standard."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    return value


def contact_sheet(strips: list[Path], path: Path) -> None:
    """Stack the steps' image strips (fit: ground truth over render; main job: frames) into one PNG."""
    from PIL import Image

    from fourlegs_engine.fileio import atomic_path

    images = []
    for p in strips:
        with Image.open(p) as im:
            images.append(im.convert("RGB"))
    width = max(im.width for im in images)
    sheet = Image.new("RGB", (width, sum(im.height for im in images) + 8 * (len(images) - 1)), (255, 255, 255))
    y = 0
    for im in images:
        sheet.paste(im, (0, y))
        y += im.height + 8
    with atomic_path(path) as tmp:
        sheet.save(tmp, format="PNG")


# ----------------------------------------------------------------------------------------- markdown
def _f(value: Any, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    if isinstance(value, int):
        return f"{value:,}"
    if abs(value) >= 10 ** digits:
        return f"{value:,.0f}"
    return f"{value:.{digits}g}"


def _device_line(report: dict[str, Any]) -> str:
    env = report["steps"].get("env", {})
    if not env.get("python"):
        return f"Device: {report['device']} (the env step did not run)."
    name = env.get("device_name") or report["device"]
    parts = [f"**{name}**" + (f" ({env['memory_gib']} GiB, compute capability {env['capability']})"
                              if env.get("memory_gib") else ""),
             f"driver {env.get('driver') or '–'}", f"torch {env.get('torch')} (CUDA {env.get('torch_cuda') or '–'})",
             f"nvcc: {env.get('nvcc') or 'not found'}", f"ninja {env.get('ninja') or 'not found'}",
             f"numpy {env.get('numpy')}", f"Python {env.get('python')}",
             f"{env.get('cpu_count')} CPU cores"]
    line = "Device: " + ", ".join(parts) + "."
    if env.get("missing"):
        line += f" Not importable there: {', '.join(env['missing'])}."
    return line


def _gsplat_line(build: dict[str, Any]) -> str:
    state = build.get("state", "not attempted")
    text = f"gsplat build: **{state}**"
    if build.get("seconds") is not None:
        text += f" in {build['seconds']:.0f} s"
        if build.get("cached"):
            text += " (reused a build from an earlier run)"
    if build.get("version"):
        text += f", gsplat {build['version']}"
    if build.get("arch"):
        text += f", TORCH_CUDA_ARCH_LIST={build['arch']}"
    if build.get("reason"):
        text += f" — {build['reason']}"
    if state != "ok":
        text += "; the steps that use gsplat fell back to the project's torch backend"
    return text + "."


def markdown(report: dict[str, Any]) -> str:
    steps = report["steps"]
    env = steps.get("env", {})
    title = env.get("device_name") or report["device"]
    heading = f"## GPU ({title})" if report["device"] == "cuda" else f"## Device check dry run ({title}, no GPU)"
    lines = [heading, "",
             f"`{report['command']}` — {report['size']} run, started {report['started']}"
             + (f", {report['wall_seconds']:.0f} s in all" if report.get("wall_seconds") is not None else
                " (still running or stopped)") + f", budget {report['budget_s']:.0f} s.", "",
             _device_line(report), "", _gsplat_line(report.get("gsplat_build", {})), "",
             f"Capture data: {report.get('data_note')}.", "",
             "| step | status | seconds (cap) |", "|---|---|---:|"]
    for name, result in steps.items():
        lines.append(f"| {STEP_TITLES.get(name, name)} | {result['status']} | "
                     f"{_f(result.get('seconds'))} ({_f(result.get('cap_s'))}) |")
    lines.append("")
    for name, writer in (("viclip", _viclip_md), ("raster_torch", _raster_md), ("raster_gsplat", _raster_md),
                         ("main_job", _main_job_md), ("cuda_tests", _tests_md), ("fit", _fit_md)):
        if name in steps:
            lines += [f"### {STEP_TITLES[name]}", ""]
            result = steps[name]
            if result["status"] != "ok":
                lines += [f"Status: {result['status']}.", ""]
            try:
                lines += writer(result)
            except (KeyError, TypeError, ValueError, ZeroDivisionError) as exc:
                lines += [f"(partial result, not tabulated: {type(exc).__name__} {exc})", ""]
    return "\n".join(lines) + "\n"


def _viclip_md(r: dict[str, Any]) -> list[str]:
    rows = r.get("rows") or []
    if not rows:
        return []
    out = [f"ViCLIP {r.get('model')} on {r.get('device')}, {r.get('weights')}; one clip = "
           f"{_f((r.get('flops_per_clip') or 0) / 1e12)} TFLOP. Clips: {r.get('clips_source')}; "
           f"{r.get('clips_per_camera_timestep')} clips per camera-timestep (paper: "
           f"{r.get('paper_clips_per_camera_timestep')}).", ""]
    if r.get("crop_resize_seconds_per_camera_timestep") is not None:
        out += [f"Pre-processing on this machine's CPU: JPEG decode {_f(r['decode_seconds_per_frame'])} s per frame, "
                f"crop + resize + normalize of all clips {_f(r['crop_resize_seconds_per_camera_timestep'])} s per "
                "camera-timestep (extraction's own code, one process).", ""]
    out += ["| precision | batch | s / clip | clips / s | TFLOP/s | min cos to fp32 | peak GiB | s / camera-timestep "
            "(network only) | hours, 27 cams × 150 t |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for row in rows:
        if not row.get("supported", True) or row.get("skipped"):
            out.append(f"| {row['dtype']} | {row.get('batch_size', '')} | {row.get('error') or row.get('skipped')} "
                       "| | | | | | |")
            continue
        out.append(f"| {row['dtype']} | {row['batch_size']} | {_f(row['seconds_per_clip'])} | "
                   f"{_f(row['clips_per_second'])} | {_f(row['tflop_per_second'])} | "
                   f"{row['min_cosine_to_float32']:.6f} | {_f(row.get('peak_gib'))} | "
                   f"{_f(row.get('seconds_per_camera_timestep'))} ({_f(row['network_seconds_per_camera_timestep'])}) | "
                   f"{_f(row['extrapolated_hours'].get('all'))} |")
    for row in r.get("cpu_rows") or []:
        out.append(f"| CPU (2-core VM, {r.get('cpu_source')}): {row['dtype']} | {row['batch_size']} | "
                   f"{_f(row['seconds_per_clip'])} | | | | | {_f(row['seconds_per_camera_timestep'])} | "
                   f"{_f((row.get('extrapolated_hours') or {}).get('all'))} |")
    return out + [""]


def _raster_md(r: dict[str, Any]) -> list[str]:
    rows = r.get("rows") or []
    if not rows:
        return []
    out = [f"{r.get('backend')} backend on {r.get('device')}: {_f(r.get('n'))} Gaussians of the benchmark scene, "
           f"features = {r.get('channels')} channels, backward = forward + backward (rgb: colours and geometry; "
           "features: the features).", "",
           "| resolution | output | mode | ms / frame (median) | FPS | timed runs | peak MB |",
           "|---|---|---|---:|---:|---:|---:|"]
    for row in rows:
        res = f"{row['width']}×{row['height']}"
        if row.get("skipped"):
            out.append(f"| {res} | {row['output']} | {row['mode']} | {row['skipped']} | | | |")
            continue
        out.append(f"| {res} | {row['output']} | {row['mode']} | {_f(row['ms_median'])} | {_f(row['fps'])} | "
                   f"{row['timed_runs']} | {_f(row.get('peak_mb'))} |")
    for row in r.get("cpu_rows") or []:
        out.append(f"| CPU, {row['width']}×{row['height']} ({r.get('cpu_source')}) | {row['output']} | "
                   f"{row['mode']} | {_f(row['ms_median'])} | {_f(1000 / row['ms_median'])} | | |")
    hd = [row for row in rows if row.get("height") == 1080 and row.get("output") == "rgb"
          and row.get("mode") == "forward" and row.get("fps")]
    if hd:
        out += ["", f"RGB forward at 1920×1080: **{_f(hd[0]['fps'])} FPS**, against gsplat's published "
                    f"{_f(r.get('gsplat_published_fps_1080p'))} FPS at 1080p (as cited in issue #34; other scenes "
                    "and Gaussian counts)."]
    return out + [""]


def _main_job_md(r: dict[str, Any]) -> list[str]:
    out = [f"`fourlegs highlight --demo {r.get('query')!r} --preset {r.get('preset')}` at "
           f"{'x'.join(map(str, r.get('resolution') or []))}, demo scene {r.get('demo')!r}, from an empty cache. "
           f"**Blender was {r.get('blender', 'not run')}**; the frames are the engine's rasterizer output.", ""]
    stages = r.get("stages") or {}
    cpu = r.get("cpu_stages") or {}
    if stages:
        out += ["| stage | ran on | wall s | CPU s | 2-core VM wall s (docs) |", "|---|---|---:|---:|---:|"]
        for name, s in stages.items():
            out.append(f"| {name} | {s['device']} | {_f(s['wall_s'])} | {_f(s.get('cpu_s'))} | {_f(cpu.get(name))} |")
        out.append("")
    frames = r.get("frames")
    if frames:
        out += [f"Frames: {frames['rendered']} of {frames['planned']} rendered through the {frames['backend']} backend "
                f"({_f(frames['gaussians'])} Gaussians): {_f(frames['seconds_per_frame_median'])} s per frame, "
                f"{_f(frames['fps'])} FPS. The VM's figure ({r.get('cpu_source')}): {r.get('cpu_frames')} frames "
                f"through Blender in {_f(cpu.get('render'))} s.", ""]
    if r.get("answer"):
        a = r["answer"]
        out += [f"Answer: segment {a.get('segment')}, peak {a.get('peak')}, best view {a.get('best_view')}.", ""]
    return out


def _tests_md(r: dict[str, Any]) -> list[str]:
    counts = r.get("counts") or {}
    summary = ", ".join(f"{v} {k}" for k, v in counts.items()) or "no summary"
    out = [f"`{r.get('command', 'pytest -m cuda')}`: {summary} (full output: cuda_tests.txt).", ""]
    tests = r.get("tests") or []
    if tests:
        out += ["| test | outcome | detail |", "|---|---|---|"]
        out += [f"| {t['test']} | {t['outcome']} | {t['detail'].replace('|', '/')} |" for t in tests]
        out.append("")
    return out


def _fit_md(r: dict[str, Any]) -> list[str]:
    out = []
    if r.get("planned"):
        sched = r.get("schedule") or {}
        cal = r.get("calibration") or {}
        out += [f"{r.get('data')} at {'x'.join(map(str, r.get('resolution') or []))} on {r.get('device')} "
                f"({r.get('backend')} backend). Planned {r['planned']['first_iterations']} first-timestep iterations, "
                f"{r['planned']['iterations']} per later timestep, {r['planned']['timesteps']} timesteps; run: "
                f"{sched.get('first_iterations')}, {sched.get('iterations')}, {sched.get('timesteps')} (fitted to the "
                f"step's time by a calibration fit: {_f(cal.get('first_iteration_s'))} s per first-timestep "
                f"iteration, {_f(cal.get('later_iteration_s'))} s per later iteration, set-up "
                f"{_f(cal.get('setup_s'))} s).", ""]
    if r.get("fit_seconds") is not None:
        out += [f"Fit {_f(r['fit_seconds'])} s: first timestep {_f(r.get('first_timestep_seconds'))} s, later "
                f"{_f(r.get('later_seconds_per_timestep'))} s per timestep.", ""]
    elif r.get("seconds_per_timestep"):
        out += [f"Seconds per fitted timestep so far: {r['seconds_per_timestep']}.", ""]
    if r.get("psnr_mean") is not None:
        cams = ", ".join(f"{k}: {_f(v)}" for k, v in (r.get("psnr_per_camera") or {}).items())
        out += ["| test cameras | mean PSNR / SSIM | first timestep PSNR | last timestep PSNR | paper |",
                "|---|---:|---:|---:|---:|",
                f"| {', '.join(r.get('test_cameras') or [])} | **{_f(r['psnr_mean'], 4)} dB** / {_f(r['ssim_mean'])} | "
                f"{_f(r['psnr_first_timestep'], 4)} dB | {_f(r['psnr_last_timestep'], 4)} dB | "
                f"{r.get('paper_psnr')} dB |",
                "", f"PSNR per test camera: {cams}. Gaussians: {_f(r.get('num_gaussians'))}.", ""]
    row = r.get("cpu_row")
    if row:
        out += [f"CPU figure ({r.get('cpu_source')}, 2-core VM): {row.get('resolution')}, first timestep "
                f"{_f(row.get('first_timestep_wall_s'))} s, later {_f(row.get('later_timestep_wall_s'))} s per "
                f"timestep, mean PSNR {_f(row.get('psnr_mean'), 4)} dB.", ""]
    return out
