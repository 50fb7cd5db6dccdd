"""The fit step of ``fourlegs bench device`` (:mod:`.device_steps`): ``fit_capture`` on the device, its
iterations fitted to the step's time by a short calibration fit, then the test-camera evaluation."""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from .device_steps import CPU_FIGURES, PAPER_FIT_PSNR, REPO, StepContext, StepSkipped, cpu_figures, gsplat_usable


class _FitClock:
    """Fit progress callback: wall seconds per finished timestep, published as the fit goes; stops the
    fit (raises :class:`_OutOfTime`) when too little of the step's time is left to evaluate it."""

    def __init__(self, ctx: StepContext, reserve_s: float):
        self.ctx, self.reserve_s = ctx, reserve_s
        self.last = time.perf_counter()
        self.seconds: dict[int, float] = {}
        self.iterations: dict[int, int] = {}

    def __call__(self, ev) -> None:
        if ev.kind == "iteration":
            self.iterations[ev.timestep] = ev.index
            if self.ctx.remaining() < self.reserve_s:
                raise _OutOfTime(f"timestep {ev.timestep}, iteration {ev.index}")
            return
        now = time.perf_counter()
        self.seconds[ev.timestep] = now - self.last
        self.last = now
        psnr = ev.train_psnr if ev.train_psnr == ev.train_psnr else None    # NaN: no iteration ran
        self.ctx.record(fitted_timesteps=len(self.seconds),
                        seconds_per_timestep={str(k): round(v, 3) for k, v in self.seconds.items()},
                        train_psnr={**self.ctx.result.get("train_psnr", {}), str(ev.timestep): psnr})
        if self.ctx.remaining() < self.reserve_s:
            raise _OutOfTime(f"after timestep {ev.timestep}")


class _OutOfTime(Exception):
    pass


class _IterationClock:
    """Fit progress callback of the calibration run: when each timestep's iterations ran. Past
    ``limit_s`` (and three first-timestep iterations, enough for a rate) it stops the run."""

    def __init__(self, limit_s: float):
        self.start = time.perf_counter()
        self.limit_s = limit_s
        self.stamps: dict[int, list[float]] = {}
        self.ends: dict[int, float] = {}

    def __call__(self, ev) -> None:
        now = time.perf_counter()
        if ev.kind != "iteration":
            self.ends[ev.timestep] = now
            return
        self.stamps.setdefault(ev.timestep, []).append(now)
        if now - self.start > self.limit_s and len(self.stamps.get(0, [])) >= 3:
            raise _OutOfTime(f"calibration stopped after {now - self.start:.0f} s")

    def per_iteration(self, t: int) -> float | None:
        s = self.stamps.get(t, [])
        return (s[-1] - s[0]) / (len(s) - 1) if len(s) > 1 else None


def calibrate_fit(capture, opts, scratch: Path, iterations: tuple[int, int], limit_s: float) -> dict[str, Any]:
    """Fit two timesteps with a few iterations and time the parts: the first timestep's set-up
    (frames, initial cloud), one first-timestep iteration, a later timestep's set-up and one of its
    iterations, and the bundle written at the end. Stopped after ``limit_s``, the parts it did not
    reach are guessed from the others (``complete`` is then False)."""
    from dataclasses import replace

    from fourlegs_engine.fit import fit_capture

    clock = _IterationClock(limit_s)
    try:
        fit_capture(capture, scratch, replace(opts, timesteps=(0, 2), first_iterations=iterations[0],
                                              iterations=iterations[1]), overwrite=True, progress=clock)
        complete = True
    except _OutOfTime:
        complete = False
    done = time.perf_counter()
    first_it = clock.per_iteration(0) or 0.0
    setup = clock.stamps.get(0, [done])[0] - clock.start - first_it
    later_it = clock.per_iteration(1)
    t1 = clock.stamps.get(1)
    later_setup = max(0.0, t1[0] - clock.ends[0] - (later_it or 0.0)) if t1 and 0 in clock.ends else None
    return {"setup_s": setup, "first_iteration_s": first_it,
            # not reached: a later iteration costs about a first one; a later set-up reads one timestep's
            # frames (a fifth of the first set-up, which also builds the initial cloud); the bundle a tenth
            "later_iteration_s": later_it if later_it is not None else first_it,
            "later_setup_s": later_setup if later_setup is not None else 0.2 * setup,
            "finish_s": max(0.0, done - clock.ends[1]) if complete and 1 in clock.ends else 0.1 * setup,
            "seconds": done - clock.start, "complete": complete}


def choose_fit_schedule(plan: dict[str, Any], timing: dict[str, float], budget_s: float, timesteps: int,
                        safety: float = 1.25) -> dict[str, int]:
    """The plan's (first_iterations, iterations, timesteps), shrunk so the calibrated cost fits ``budget_s``:
    first the iterations (in proportion, down to the plan's minimums), then the timesteps."""
    f, l = safety * timing["first_iteration_s"], safety * timing["later_iteration_s"]
    fixed = safety * (timing["setup_s"] + timing["finish_s"])
    per_later = safety * timing["later_setup_s"]
    F, L, N = int(plan["first_iterations"]), int(plan["iterations"]), timesteps

    def cost(F: int, L: int, N: int) -> float:
        return fixed + F * f + (N - 1) * (per_later + L * l)

    if cost(F, L, N) > budget_s:
        scale = max(0.0, budget_s - fixed - (N - 1) * per_later) / max(F * f + (N - 1) * L * l, 1e-9)
        F = max(int(plan["min_first_iterations"]), int(F * scale))
        L = max(int(plan["min_iterations"]), int(L * scale))
    while N > 1 and cost(F, L, N) > budget_s:
        N -= 1
    if cost(F, L, N) > budget_s:        # even the first timestep alone at the minimum does not fit
        F = max(1, min(F, int(max(0.0, budget_s - fixed) / max(f, 1e-9))))
    return {"first_iterations": F, "iterations": L, "timesteps": N, "estimated_s": round(cost(F, L, N), 1)}


def step_fit(ctx: StepContext) -> None:
    """``fit_capture`` on the device at the plan's resolution, its iterations shrunk to the step's time
    after a short calibration fit, then the project's test-camera evaluation (PSNR / SSIM per timestep
    and camera) against the paper's 28.7 dB."""
    from dataclasses import replace

    import numpy as np

    from fourlegs_engine.fit import Capture, FitOptions, fit_capture
    from fourlegs_engine.fit.evaluate import evaluate_test_views
    from fourlegs_engine.scene.bundle import load_bundle

    if ctx.data is None:
        raise StepSkipped("no capture data (build .device_data with `fourlegs bench device-data`)")
    plan = ctx.plan
    capture = Capture(ctx.data)
    steps = min(int(plan["timesteps"]), capture.num_timesteps)
    backend = "gsplat" if ctx.device.type == "cuda" and gsplat_usable() else "torch"
    opts = FitOptions(resolution_scale=float(plan["resolution_scale"]), timesteps=(0, steps),
                      first_iterations=int(plan["first_iterations"]), iterations=int(plan["iterations"]),
                      max_gaussians=int(plan["max_gaussians"]), init_background=int(plan["init_background"]),
                      max_iterations=0, device=ctx.device.type, **plan.get("options", {}))
    ctx.record(data=str(ctx.data), backend=backend, device=str(ctx.device), paper_psnr=PAPER_FIT_PSNR,
               resolution=[round(capture.width * opts.resolution_scale), round(capture.height * opts.resolution_scale)],
               planned={"first_iterations": opts.first_iterations, "iterations": opts.iterations, "timesteps": steps})
    reserve = float(plan["evaluation_reserve_s"])
    timing = calibrate_fit(capture, opts, ctx.work / "calibration", tuple(plan["calibration_iterations"]),
                           limit_s=0.3 * (ctx.remaining() - reserve))
    schedule = choose_fit_schedule(plan, timing, ctx.remaining() - reserve, steps)
    ctx.record(calibration={k: round(v, 4) if isinstance(v, float) else v for k, v in timing.items()},
               schedule=schedule)
    steps = schedule["timesteps"]
    opts = replace(opts, timesteps=(0, steps), first_iterations=schedule["first_iterations"],
                   iterations=schedule["iterations"])
    ctx.record(timesteps=[0, steps], options=opts.fingerprint())
    clock = _FitClock(ctx, reserve_s=reserve * 0.5)
    scene_dir = ctx.work / "scene"
    start = time.perf_counter()
    try:
        fit_capture(capture, scene_dir, opts, overwrite=True, progress=clock)
    except _OutOfTime as exc:
        ctx.record(fit_stopped=str(exc))
        raise RuntimeError(f"the fit did not finish within the step's time ({exc}); "
                           f"{len(clock.seconds)} timesteps fitted, see seconds_per_timestep") from None
    fit_s = time.perf_counter() - start
    later = [v for k, v in clock.seconds.items() if k != 0]
    ctx.record(fit_seconds=fit_s, first_timestep_seconds=clock.seconds.get(0),
               later_seconds_per_timestep=float(np.mean(later)) if later else None)
    start = time.perf_counter()
    metrics = evaluate_test_views(scene_dir, capture, resolution_scale=opts.resolution_scale,
                                  keep_images_at=tuple(sorted({0, steps - 1})))
    ctx.record(evaluation_seconds=time.perf_counter() - start, test_cameras=metrics.cameras,
               num_gaussians=int(load_bundle(scene_dir).gaussians.num_gaussians),
               psnr_mean=metrics.mean_psnr, ssim_mean=metrics.mean_ssim,
               psnr_first_timestep=float(metrics.psnr[0].mean()), psnr_last_timestep=float(metrics.psnr[-1].mean()),
               psnr_per_timestep=metrics.psnr.mean(1).round(3).tolist(),
               psnr_per_camera=dict(zip(metrics.cameras, metrics.psnr.mean(0).round(3).tolist())))
    _fit_strip(metrics, ctx.work.parent / "contact_fit.png", backend, str(ctx.device))
    cpu = cpu_figures("fit")
    if cpu:
        r = cpu["records"][0]
        ctx.record(cpu_row={k: r.get(k) for k in ("resolution", "num_gaussians", "first_timestep_wall_s",
                                                  "later_timestep_wall_s", "psnr_mean", "psnr_first_timestep")},
                   cpu_source=str(CPU_FIGURES["fit"].relative_to(REPO)))


def _fit_strip(metrics, path: Path, backend: str, device: str) -> None:
    """Ground truth above the render, one column per test camera and kept timestep (tiles 320 px wide)."""
    from PIL import Image, ImageDraw

    from fourlegs_engine.fileio import atomic_path

    import numpy as np

    keys = sorted(metrics.renders)
    if not keys:
        return
    h, w = metrics.renders[keys[0]].shape[:2]
    tw = min(320, w)
    th = max(1, round(h * tw / w))
    label = 14
    title = f"fit on {device} ({backend} backend): ground truth (top), render (bottom), test cameras"
    sheet = Image.new("RGB", (max(tw * len(keys), 6 * len(title) + 8), 2 * (th + label) + label), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    draw.text((4, 1), title, fill=(0, 0, 0))
    for k, (t, cam) in enumerate(keys):
        i, j = metrics.timesteps.index(t), metrics.cameras.index(cam)
        for row, img in enumerate((metrics.targets[(t, cam)], metrics.renders[(t, cam)])):
            tile = Image.fromarray((np.clip(img, 0, 1) * 255).astype(np.uint8)).resize((tw, th), Image.BOX)
            y = label + row * (th + label)
            sheet.paste(tile, (k * tw, y + label))
            text = f"cam {cam} t={t} " + ("GT" if row == 0 else f"{metrics.psnr[i, j]:.1f} dB")
            draw.text((k * tw + 3, y + 1), text, fill=(0, 0, 0))
    with atomic_path(path) as tmp:
        sheet.save(tmp, format="PNG")
