"""The steps of ``fourlegs bench device``, each run in a process of its own.

``python -m fourlegs_bench.device_steps STEP CONFIG.json RESULT.json`` runs one step. The step writes its
figures to RESULT.json as it measures them (atomically, after every row), so a step that the
orchestrator (:mod:`.device`) stops at its time cap still leaves what it measured; a killed process
is the only way to stop a hung CUDA call. Exit status 0: finished; 1: failed (the one-line reason in
RESULT.json's ``error``); 3: skipped (``skipped``: why).

CONFIG.json holds ``size`` ("toy" | "full"), ``device`` ("cpu" | "cuda"), ``data`` (a capture directory
or null), ``work`` (scratch directory), ``cap_s`` (this step's time cap) and ``plan`` (this step's
sizes, :data:`fourlegs_bench.device.PLANS`).
"""
from __future__ import annotations

import json
import os
import platform
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

REPO = Path(__file__).resolve().parents[1]
#: the repository's CPU figures, shown beside the GPU rows
CPU_FIGURES = {"viclip": REPO / "docs/bench/viclip_real.json", "render": REPO / "docs/bench/render_300k.json",
               "fit": REPO / "docs/bench/fit150_bench.json", "main_job": REPO / "docs/bench/main_job.json"}
#: the paper's mean test-camera PSNR on the Panoptic sequences (Luiten et al., 640x360, GPU)
PAPER_FIT_PSNR = 28.7
#: the cuda-marked tests
CUDA_TEST_FILES = ("tests/test_render_gsplat.py", "tests/test_viclip_encoder.py", "tests/test_bench_viclip_real.py",
                   "tests/test_fit.py")


class StepSkipped(Exception):
    """The step cannot run here (no CUDA, no data, ...); the message says why."""


class StepContext:
    """What a step receives: its configuration, and :meth:`record` to publish figures as it goes."""

    def __init__(self, name: str, config: dict[str, Any], result_path: Path):
        self.name = name
        self.config = config
        self.result_path = result_path
        self.result: dict[str, Any] = {}
        self.started = time.perf_counter()

    @property
    def plan(self) -> dict[str, Any]:
        return self.config["plan"]

    @property
    def device(self):
        import torch
        return torch.device(self.config["device"])

    @property
    def work(self) -> Path:
        path = Path(self.config["work"]) / self.name
        path.mkdir(parents=True, exist_ok=True)
        return path

    @property
    def data(self) -> Path | None:
        return Path(self.config["data"]) if self.config.get("data") else None

    def elapsed(self) -> float:
        return time.perf_counter() - self.started

    def remaining(self) -> float:
        """Seconds left of this step's cap."""
        return float(self.config.get("cap_s", 1e9)) - self.elapsed()

    def record(self, **fields: Any) -> None:
        """Merge ``fields`` into the result and rewrite RESULT.json atomically."""
        from fourlegs_engine.fileio import write_json_atomic

        self.result.update(fields)
        write_json_atomic(self.result_path, self.result)

    def append(self, key: str, row: dict[str, Any]) -> None:
        """Add ``row`` to the list ``key`` of the result and rewrite RESULT.json."""
        self.record(**{key: [*self.result.get(key, []), row]})


def _sync(device) -> None:
    import torch
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _cpu_rows(name: str) -> Any:
    """The repository's CPU figures for ``name`` (None when the file is not in this checkout)."""
    path = CPU_FIGURES[name]
    if not path.is_file():
        return None
    from fourlegs_engine.fileio import read_json
    return read_json(path)


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0][:200] if text else ''}"


def _require_cuda(ctx: StepContext) -> None:
    if ctx.device.type != "cuda":
        raise StepSkipped("no CUDA")


def _gsplat_usable() -> bool:
    from fourlegs_engine.render.backends import gsplat_available
    return gsplat_available()


# ------------------------------------------------------------------------------------------- env
#: import name -> distribution name of what the project (and its tests) import
PACKAGES = {"numpy": "numpy", "torch": "torch", "scipy": "scipy", "tqdm": "tqdm", "matplotlib": "matplotlib",
            "PIL": "pillow", "OpenEXR": "OpenEXR", "safetensors": "safetensors", "plyfile": "plyfile",
            "numba": "numba", "cv2": "opencv-python-headless", "pytest": "pytest", "hypothesis": "hypothesis",
            "pytest_timeout": "pytest-timeout", "regex": "regex", "ninja": "ninja", "jaxtyping": "jaxtyping",
            "rich": "rich", "gsplat": "gsplat"}


def _command_output(cmd: list[str]) -> str | None:
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout.strip() or None if out.returncode == 0 else None


def step_env(ctx: StepContext) -> None:
    """Device name, driver, torch / CUDA / numpy versions, nvcc, and which packages import."""
    import importlib.metadata
    import importlib.util

    import numpy as np
    import torch

    info: dict[str, Any] = {
        "python": platform.python_version(), "machine": platform.machine(), "cpu_count": os.cpu_count(),
        "torch": torch.__version__, "torch_cuda": torch.version.cuda, "numpy": np.__version__,
        "cuda_available": torch.cuda.is_available(), "device": str(ctx.device),
    }
    if ctx.device.type == "cuda":
        props = torch.cuda.get_device_properties(ctx.device)
        info.update(device_name=torch.cuda.get_device_name(ctx.device),
                    capability=".".join(map(str, torch.cuda.get_device_capability(ctx.device))),
                    memory_gib=round(props.total_memory / 2**30, 1))
        smi = _command_output(["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"])
        info["nvidia_smi"] = smi
        info["driver"] = smi.split(",")[1].strip() if smi and smi.count(",") >= 2 else None
    else:
        info["device_name"] = platform.processor() or platform.machine()
    nvcc = _command_output(["nvcc", "--version"])
    info["nvcc"] = nvcc.splitlines()[-1] if nvcc else None
    packages, missing = {}, []
    for module, dist in PACKAGES.items():
        if importlib.util.find_spec(module) is None:
            packages[module] = None
            missing.append(module)
            continue
        try:
            packages[module] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            packages[module] = "importable"
    info["packages"] = packages
    info["missing"] = missing
    ctx.record(**info)


# ----------------------------------------------------------------------------------------- viclip
def step_viclip(ctx: StepContext) -> None:
    """ViCLIP at the plan's size, random weights: seconds per clip per (precision, batch size), the worst
    cosine of each precision to float32 on real crop clips, seconds per camera-timestep (the device's own
    decoding and crop pre-processing plus clips x seconds per clip) and the whole-scene hours."""
    import torch

    from fourlegs_engine.language.extract import ExtractConfig
    from fourlegs_engine.language.pyramid import crop_layout, pyramid_ratios
    from fourlegs_engine.language.viclip.model import ViCLIPConfig, ViCLIPModel, l2_normalize, video_clip_flops

    from .viclip import DTYPES, _cast
    from .viclip_real import PAPER_CLIPS_640x360, load_tube, preprocess_camera_timestep, sample_clips

    plan, device = ctx.plan, ctx.device
    config = ViCLIPConfig.preset(plan["size"]) if isinstance(plan["size"], str) else ViCLIPConfig(**plan["size"])
    crop = int(ExtractConfig(crop_size=None).resolved_crop_size("rgb", config))
    reference_clips = int(plan["reference_clips"])
    ctx.record(model=config.size_name, device=str(device), flops_per_clip=video_clip_flops(config)["total"],
               weights="random (seeded): seconds depend only on shapes")

    # real clips and the device's own pre-processing of one camera-timestep
    if ctx.data is not None:
        from fourlegs_engine.fit.dataset import Capture
        capture = Capture(ctx.data)
        cam = capture.camera_indices("train", [str(plan["camera"])])[0]
        t = min(int(plan["timestep"]), capture.num_timesteps - 1)
        layout = crop_layout(capture.width, capture.height, pyramid_ratios())
        keep = [i for _, i in sample_clips(layout, 1, reference_clips)]
        tube, decoded = load_tube(capture, t, cam)
        decode_s = decoded["seconds"] / decoded["frames"]
        start = time.perf_counter()
        kept, produced = preprocess_camera_timestep(tube, layout, crop, keep)
        prep_s = time.perf_counter() - start
        real = torch.stack([kept[i] for i in keep])
        ctx.record(clips_source=f"{ctx.data} camera {plan['camera']} timestep {t}", image_size=[capture.width,
                   capture.height], clips_per_camera_timestep=produced,
                   paper_clips_per_camera_timestep=PAPER_CLIPS_640x360,
                   decode_seconds_per_frame=decode_s, crop_resize_seconds_per_camera_timestep=prep_s)
    else:
        gen = torch.Generator().manual_seed(0)
        real = torch.randn(reference_clips, config.num_frames, 3, crop, crop, generator=gen)
        produced, decode_s, prep_s = PAPER_CLIPS_640x360, None, None
        ctx.record(clips_source="random normal clips (no capture data)", clips_per_camera_timestep=produced,
                   decode_seconds_per_frame=None, crop_resize_seconds_per_camera_timestep=None)

    torch.manual_seed(int(plan.get("seed", 0)))
    with torch.device(device):
        master = ViCLIPModel(config).eval()
    with torch.inference_mode():
        reference = l2_normalize(master.encode_video(real.to(device, torch.float32)).double().cpu())
    subsets = plan["subsets"]
    for dtype_name in plan["dtypes"]:
        dtype = DTYPES[dtype_name]
        try:
            model = master if dtype == torch.float32 else _cast(master, dtype)
            with torch.inference_mode():
                emb = l2_normalize(model.encode_video(real.to(device, dtype)).double().cpu())
        except (RuntimeError, NotImplementedError) as exc:
            ctx.append("rows", {"dtype": dtype_name, "supported": False, "error": _one_line(exc)})
            continue
        cosine = float((emb * reference).sum(-1).min())
        for batch in plan["batches"][dtype_name]:
            if ctx.remaining() < 5:
                ctx.append("rows", {"dtype": dtype_name, "batch_size": batch, "supported": True,
                                    "skipped": "out of the step's time"})
                continue
            clips = real[torch.arange(batch) % real.shape[0]].to(device, dtype)
            if device.type == "cuda":
                torch.cuda.reset_peak_memory_stats(device)
            times = []
            with torch.inference_mode():
                for k in range(1 + int(plan["repeats"])):      # the first call (kernel selection) is not timed
                    _sync(device)
                    start = time.perf_counter()
                    out = model.encode_video(clips)
                    _sync(device)
                    if k:
                        times.append(time.perf_counter() - start)
            per_clip = statistics.median(times) / batch
            row = {"dtype": dtype_name, "batch_size": batch, "supported": True, "seconds_per_clip": per_clip,
                   "clips_per_second": 1.0 / per_clip,
                   "tflop_per_second": ctx.result["flops_per_clip"] / per_clip / 1e12,
                   "min_cosine_to_float32": cosine, "finite": bool(torch.isfinite(out).all()),
                   "peak_gib": (torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else None),
                   "network_seconds_per_camera_timestep": produced * per_clip}
            if prep_s is not None:
                row["seconds_per_camera_timestep"] = decode_s + prep_s + produced * per_clip
            per_ct = row.get("seconds_per_camera_timestep", row["network_seconds_per_camera_timestep"])
            row["extrapolated_hours"] = {name: cams * steps * per_ct / 3600 for name, (cams, steps) in subsets.items()}
            ctx.append("rows", row)
            del clips, out
        del model
    cpu = _cpu_rows("viclip")
    if cpu:
        ctx.record(cpu_rows=[{k: r.get(k) for k in ("dtype", "batch_size", "seconds_per_clip",
                                                    "seconds_per_camera_timestep", "extrapolated_hours")}
                             for r in cpu["rows"] if r.get("supported") and r["dtype"] in ("float32", "bfloat16")],
                   cpu_source=str(CPU_FIGURES["viclip"].relative_to(REPO)))


# ----------------------------------------------------------------------------------------- raster
#: the figure issue #34 cites for gsplat at 1920x1080
GSPLAT_PUBLISHED_FPS_1080P = 160.0


def _raster_step(ctx: StepContext, backend: str) -> None:
    """The rasterizer at the plan's N: RGB and C-channel features, forward and forward+backward, per
    resolution; median ms per frame and frames per second."""
    import torch

    from .render import _render_fn
    from .render_scene import make_bench_scene

    plan, device = ctx.plan, ctx.device
    if backend == "gsplat":
        _require_cuda(ctx)
        if not _gsplat_usable():
            raise StepSkipped("gsplat is not usable (see the gsplat build); the torch backend's rows stand alone")
    ctx.record(backend=backend, device=str(device), n=plan["n"], channels=plan["channels"],
               gsplat_published_fps_1080p=GSPLAT_PUBLISHED_FPS_1080P)
    for width, height in plan["resolutions"]:
        scene = make_bench_scene(plan["n"], feature_dim=plan["channels"], seed=0, device=device, width=width,
                                 height=height)
        for output in plan["outputs"]:
            for mode in plan["modes"]:
                if ctx.remaining() < 3:
                    ctx.append("rows", {"width": width, "height": height, "output": output, "mode": mode,
                                        "skipped": "out of the step's time"})
                    continue
                fn = _render_fn(scene, output, mode, backend)
                if device.type == "cuda":
                    torch.cuda.reset_peak_memory_stats(device)
                _sync(device)
                start = time.perf_counter()
                fn()                                      # warm-up: allocation, kernel selection
                _sync(device)
                warm = time.perf_counter() - start
                # slow cases get fewer timed runs so one slow configuration cannot eat the step
                repeats = int(plan["repeats"]) if warm < 1.0 else (1 if warm < 5.0 else 0)
                times = []
                for _ in range(repeats):
                    start = time.perf_counter()
                    fn()
                    _sync(device)
                    times.append(time.perf_counter() - start)
                ms = 1000 * (statistics.median(times) if times else warm)
                ctx.append("rows", {"width": width, "height": height, "output": output, "mode": mode,
                                    "ms_median": ms, "fps": 1000.0 / ms, "timed_runs": len(times),
                                    "warmup_ms": 1000 * warm,
                                    "peak_mb": (torch.cuda.max_memory_allocated(device) / 2**20
                                                if device.type == "cuda" else None)})
        del scene
    cpu = _cpu_rows("render")
    if cpu:
        ctx.record(cpu_rows=[{k: r.get(k) for k in ("n", "output", "mode", "ms_median", "width", "height")}
                             for r in cpu if r.get("part") == "speed"],
                   cpu_source=str(CPU_FIGURES["render"].relative_to(REPO)))


def step_raster_torch(ctx: StepContext) -> None:
    _raster_step(ctx, "torch")


def step_raster_gsplat(ctx: StepContext) -> None:
    _raster_step(ctx, "gsplat")


# ------------------------------------------------------------------------------------- cuda tests
_SUMMARY = re.compile(r"(\d+) (passed|failed|skipped|errors?|deselected|xfailed|xpassed)")
_DURATION = re.compile(r"\bin [\d.]+s\b")
_OUTCOME = re.compile(r"^(PASSED|FAILED|ERROR|SKIPPED|XFAIL|XPASS)\s+(?:\[\d+\]\s+)?(\S+?):?(?:\s+-\s+|\s+|$)(.*)$")


def parse_pytest_output(text: str) -> dict[str, Any]:
    """Counts from pytest's closing line and each test's outcome from its ``-rA`` summary."""
    counts: dict[str, int] = {}
    closing = [line for line in text.splitlines() if _SUMMARY.search(line) and _DURATION.search(line)]
    if closing:
        for number, word in _SUMMARY.findall(closing[-1]):
            counts["errors" if word.startswith("error") else word] = int(number)
    outcomes = []
    for line in text.splitlines():
        m = _OUTCOME.match(line.strip())
        if m:
            outcomes.append({"outcome": m.group(1), "test": m.group(2), "detail": m.group(3).strip(" -")[:200]})
    return {"counts": counts, "tests": outcomes}


def step_cuda_tests(ctx: StepContext) -> None:
    """``pytest -m cuda`` on the cuda-marked test files; the full output goes to ``cuda_tests.txt``."""
    log = ctx.work / "cuda_tests.txt"
    cmd = [sys.executable, "-m", "pytest", "-m", "cuda", "-rA", "-p", "no:cacheprovider",
           f"--timeout={int(ctx.plan['per_test_timeout_s'])}", *CUDA_TEST_FILES]
    env = {**os.environ, "FOURLEGS_CACHE": str(ctx.work / "cache")}
    ctx.record(command=" ".join(cmd[2:]), log=str(log))
    start = time.perf_counter()
    with open(log, "w", encoding="utf-8") as f:
        f.write(f"$ python {' '.join(cmd[1:])}\n")
        f.flush()
        proc = subprocess.run(cmd, cwd=REPO, env=env, stdout=f, stderr=subprocess.STDOUT,
                              timeout=max(10.0, ctx.remaining() - 5))
    parsed = parse_pytest_output(log.read_text(encoding="utf-8", errors="replace"))
    ctx.record(returncode=proc.returncode, seconds=time.perf_counter() - start, **parsed)
    if proc.returncode not in (0, 5):
        failed = [t["test"] for t in parsed["tests"] if t["outcome"] in ("FAILED", "ERROR")]
        raise RuntimeError(f"pytest exit status {proc.returncode}: {', '.join(failed) or 'see cuda_tests.txt'}")


# -------------------------------------------------------------------------------------------- fit
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
            if ev.index % 50 == 0 and self.ctx.remaining() < self.reserve_s:
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
    """Fit progress callback of the calibration run: when each timestep's iterations ran."""

    def __init__(self):
        self.start = time.perf_counter()
        self.stamps: dict[int, list[float]] = {}
        self.ends: dict[int, float] = {}

    def __call__(self, ev) -> None:
        if ev.kind == "iteration":
            self.stamps.setdefault(ev.timestep, []).append(time.perf_counter())
        else:
            self.ends[ev.timestep] = time.perf_counter()

    def per_iteration(self, t: int) -> float:
        s = self.stamps.get(t, [])
        return (s[-1] - s[0]) / (len(s) - 1) if len(s) > 1 else 0.0


def calibrate_fit(capture, opts, scratch: Path, iterations: tuple[int, int]) -> dict[str, float]:
    """Fit two timesteps with a few iterations and time the parts: the first timestep's set-up
    (frames, initial cloud), one first-timestep iteration, a later timestep's set-up and one of its
    iterations, and the bundle written at the end."""
    from dataclasses import replace

    from fourlegs_engine.fit import fit_capture

    clock = _IterationClock()
    fit_capture(capture, scratch, replace(opts, timesteps=(0, 2), first_iterations=iterations[0],
                                          iterations=iterations[1]), overwrite=True, progress=clock)
    done = time.perf_counter()
    t0, t1 = clock.stamps.get(0, [clock.start]), clock.stamps.get(1, [clock.ends.get(0, clock.start)])
    first_it, later_it = clock.per_iteration(0), clock.per_iteration(1)
    return {"setup_s": t0[0] - clock.start - first_it, "first_iteration_s": first_it,
            "later_setup_s": max(0.0, t1[0] - clock.ends.get(0, t1[0]) - later_it), "later_iteration_s": later_it,
            "finish_s": max(0.0, done - clock.ends.get(1, done)), "seconds": done - clock.start}


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
    backend = "gsplat" if ctx.device.type == "cuda" and _gsplat_usable() else "torch"
    opts = FitOptions(resolution_scale=float(plan["resolution_scale"]), timesteps=(0, steps),
                      first_iterations=int(plan["first_iterations"]), iterations=int(plan["iterations"]),
                      max_gaussians=int(plan["max_gaussians"]), init_background=int(plan["init_background"]),
                      device=ctx.device.type, **plan.get("options", {}))
    ctx.record(data=str(ctx.data), backend=backend, device=str(ctx.device), paper_psnr=PAPER_FIT_PSNR,
               resolution=[round(capture.width * opts.resolution_scale), round(capture.height * opts.resolution_scale)],
               planned={"first_iterations": opts.first_iterations, "iterations": opts.iterations, "timesteps": steps})
    reserve = float(plan["evaluation_reserve_s"])
    timing = calibrate_fit(capture, opts, ctx.work / "calibration", tuple(plan["calibration_iterations"]))
    schedule = choose_fit_schedule(plan, timing, ctx.remaining() - reserve, steps)
    ctx.record(calibration={k: round(v, 4) for k, v in timing.items()}, schedule=schedule)
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
    cpu = _cpu_rows("fit")
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


# --------------------------------------------------------------------------------------- main job
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
            _sync(device)
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
    cpu = _cpu_rows("main_job")
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


STEPS: dict[str, Callable[[StepContext], None]] = {
    "env": step_env, "viclip": step_viclip, "main_job": step_main_job, "raster_torch": step_raster_torch,
    "raster_gsplat": step_raster_gsplat, "cuda_tests": step_cuda_tests, "fit": step_fit,
}


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 3 or args[0] not in STEPS:
        print(f"usage: python -m fourlegs_bench.device_steps {{{','.join(STEPS)}}} CONFIG.json RESULT.json",
              file=sys.stderr)
        return 2
    name, config_path, result_path = args[0], Path(args[1]), Path(args[2])
    config = json.loads(config_path.read_text(encoding="utf-8"))
    ctx = StepContext(name, config, result_path)
    ctx.record()
    try:
        STEPS[name](ctx)
    except StepSkipped as exc:
        ctx.record(skipped=str(exc))
        return 3
    except Exception as exc:                                  # the orchestrator reports it as one line
        import traceback
        traceback.print_exc()
        ctx.record(error=_one_line(exc))
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
