"""``fourlegs bench device``: the CUDA check, one command, every step under its own time cap.

On a lent GPU machine (``scripts/device_check.sh`` installs the carried wheels, starts the gsplat build in
the background and runs this) the steps are, in order:

``env``           device name, driver, torch / CUDA / numpy versions, nvcc, which packages import
``viclip``        ViCLIP-L/14 (random weights) per precision and batch size, seconds per clip and per
                  camera-timestep, hours for the whole basketball scene beside the CPU row
``raster_torch``  the project's torch rasterizer on the device: RGB and 128-channel features, forward and
                  forward+backward, 300k Gaussians at 640x360 and 1920x1080
``main_job``      the main job's engine half from an empty cache, its frames rendered on the device
``raster_gsplat`` the same cases through gsplat (waits for its build), beside gsplat's published 160 FPS
``cuda_tests``    ``pytest -m cuda``
``fit``           ``fit_capture`` at 640x360 on the carried capture subset, test-camera PSNR against 28.7 dB

Each step runs in a child process (:mod:`.device_steps`) killed at its cap; the report (JSON + Markdown
+ contact sheet, :mod:`.device_report`) is rewritten after every step, so a run stopped from outside
still returns what it measured. ``--size toy`` is the CPU dry run of the same steps at tiny sizes.
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

from fourlegs_engine.errors import InputError

STEP_ORDER = ("env", "viclip", "raster_torch", "main_job", "raster_gsplat", "cuda_tests", "fit")
#: steps that wait for the background gsplat build (bounded by ``--gsplat-wait``) before they start
NEEDS_GSPLAT = frozenset({"raster_gsplat", "cuda_tests", "fit"})
#: a step is not started with less than this many seconds of the budget left
MIN_STEP_S = 8.0
#: seconds kept back from the budget for the final report
REPORT_RESERVE_S = 4.0

TINY_VIT = {"image_size": 32, "patch_size": 16, "num_frames": 8, "vision_width": 64, "vision_layers": 2,
            "vision_heads": 1, "embed_dim": 48, "vocab_size": 1000, "context_length": 32, "text_width": 64,
            "text_layers": 2, "text_heads": 1}
SUBSETS = {"all": [27, 150], "8 cameras": [8, 150], "8 cameras 1 s": [8, 30]}
QUERY = "a ball flying in the air"
TOY_PRESET = """name = "device_toy"
description = "the whole scene through one training camera (needs no language field)"
fps = 24
resolution = [96, 54]

[[shots]]
name = "context"
effect = "play"
camera = "cam00"
from = "start"
to = "end"
"""

#: per size: each step's sizes (what :mod:`.device_steps` reads) and its time cap in seconds
PLANS: dict[str, dict[str, dict[str, Any]]] = {
    "full": {
        "env": {"cap_s": 30},
        "viclip": {"cap_s": 75, "size": "l", "dtypes": ["float32", "bfloat16", "float16"],
                   "batches": {"float32": [16], "bfloat16": [16, 64, 256], "float16": [16, 64, 256]},
                   "repeats": 2, "reference_clips": 16, "camera": "1", "timestep": 12, "subsets": SUBSETS},
        "raster_torch": {"cap_s": 60, "n": 300_000, "channels": 128, "resolutions": [[640, 360], [1920, 1080]],
                         "outputs": ["rgb", "features"], "modes": ["forward", "backward"], "repeats": 3},
        "main_job": {"cap_s": 90, "demo": "demo", "resolution": [640, 360], "preset": "broadcast", "query": QUERY},
        "raster_gsplat": {"cap_s": 45, "n": 300_000, "channels": 128, "resolutions": [[640, 360], [1920, 1080]],
                          "outputs": ["rgb", "features"], "modes": ["forward", "backward"], "repeats": 5},
        "cuda_tests": {"cap_s": 90, "per_test_timeout_s": 75},
        "fit": {"cap_s": 170, "timesteps": 25, "resolution_scale": 1.0, "first_iterations": 2000, "iterations": 150,
                "max_gaussians": 150_000, "init_background": 60_000, "min_first_iterations": 300,
                "min_iterations": 30, "calibration_iterations": [60, 30], "evaluation_reserve_s": 40,
                "options": {}},
    },
    "toy": {
        "env": {"cap_s": 60},
        "viclip": {"cap_s": 60, "size": TINY_VIT, "dtypes": ["float32", "bfloat16", "float16"],
                   "batches": {"float32": [2], "bfloat16": [2, 4], "float16": [2]},
                   "repeats": 1, "reference_clips": 2, "camera": "1", "timestep": 1, "subsets": SUBSETS},
        "raster_torch": {"cap_s": 60, "n": 2000, "channels": 8, "resolutions": [[64, 36], [96, 54]],
                         "outputs": ["rgb", "features"], "modes": ["forward", "backward"], "repeats": 1},
        # one play shot through a named camera: the plan needs no language field, so the dry run skips the
        # field's minutes (the device run builds it: the broadcast preset)
        "main_job": {"cap_s": 120, "demo": "tiny", "resolution": [96, 54], "preset": "device_toy", "query": QUERY,
                     "preset_toml": TOY_PRESET},
        "raster_gsplat": {"cap_s": 60, "n": 2000, "channels": 8, "resolutions": [[64, 36]],
                          "outputs": ["rgb", "features"], "modes": ["forward", "backward"], "repeats": 1},
        "cuda_tests": {"cap_s": 120, "per_test_timeout_s": 60},
        "fit": {"cap_s": 120, "timesteps": 2, "resolution_scale": 1.0, "first_iterations": 20, "iterations": 4,
                "max_gaussians": 3000, "init_background": 400, "min_first_iterations": 5, "min_iterations": 2,
                "calibration_iterations": [4, 2], "evaluation_reserve_s": 10,
                "options": {"voxel": 0.05, "init_foreground": 1000}},
    },
}
DEFAULT_BUDGET_S = {"full": 360.0, "toy": 900.0}
DEFAULT_GSPLAT_WAIT_S = {"full": 200.0, "toy": 30.0}


def register_bench(bench_sub: Any) -> None:
    from . import device_data

    p = bench_sub.add_parser(
        "device", help="the CUDA check for a lent GPU machine (scripts/device_check.sh): one report",
        description="Run every CUDA check (environment, ViCLIP, rasterizer, main job, gsplat, cuda tests, fit), "
                    "each in its own process under its own time cap, and write device_report.json / .md and "
                    "device_contact.png into --out after every step. --size toy is the CPU dry run.")
    add_arguments(p)
    p.set_defaults(func=run_device_cli)
    device_data.register_bench(bench_sub)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--size", choices=tuple(PLANS), default="full", help="full (the device) or toy (CPU dry run)")
    p.add_argument("--out", default=None, help="report folder (default: $OUT, else a new temporary folder)")
    p.add_argument("--data", default=None,
                   help="capture subset (default: .device_data for --size full, a tiny synthetic capture for "
                        "--size toy; 'synthetic' forces that one)")
    p.add_argument("--device", choices=("auto", "cuda", "cpu"), default="auto")
    p.add_argument("--steps", default=",".join(STEP_ORDER), help="comma-separated steps (default: all, in order)")
    p.add_argument("--cap", action="append", default=[], metavar="STEP=SECONDS", help="override a step's time cap")
    p.add_argument("--set", action="append", default=[], metavar="STEP.KEY=JSON",
                   help="override one value of a step's plan, e.g. fit.first_iterations=3000 or "
                        "'viclip.batches={\"bfloat16\": [512]}' (see fourlegs_bench/device.py PLANS)")
    p.add_argument("--threads", type=int, default=None,
                   help="CPU threads of every step (OMP_NUM_THREADS; default: the libraries' choice)")
    p.add_argument("--budget", type=float, default=None,
                   help="seconds for everything from --started (default: 360 full, 900 toy)")
    p.add_argument("--started", type=float, default=None, help="epoch seconds the run began (default: now)")
    p.add_argument("--work", default=None, help="scratch folder (default: a new temporary folder)")
    p.add_argument("--gsplat-status", default=None, help="status JSON of the background gsplat build")
    p.add_argument("--gsplat-site", default=None, help="folder holding the gsplat package (added once it is built)")
    p.add_argument("--gsplat-log", default=None, help="the gsplat build's log (its tail is copied to --out)")
    p.add_argument("--gsplat-wait", type=float, default=None,
                   help="seconds after --started that steps needing gsplat wait for its build (default: 200 full)")


def run_device_cli(args: argparse.Namespace) -> int:
    report = run_device_check(args)
    failed = [n for n, s in report["steps"].items() if s["status"].startswith(("failed", "timed out"))]
    return 1 if failed else 0


def _parse_caps(items: list[str]) -> dict[str, float]:
    caps = {}
    for item in items:
        name, _, value = item.partition("=")
        if name not in STEP_ORDER:
            raise InputError(f"unknown step {name!r} (steps: {', '.join(STEP_ORDER)})", field="--cap")
        try:
            caps[name] = float(value)
        except ValueError:
            raise InputError(f"{item!r} is not STEP=SECONDS", field="--cap") from None
        if caps[name] <= 0:
            raise InputError(f"{item!r}: the cap must be positive", field="--cap")
    return caps


def apply_overrides(plans: dict[str, dict[str, Any]], items: list[str]) -> dict[str, dict[str, Any]]:
    """A copy of ``plans`` with each ``STEP.KEY=JSON`` applied (a bare word counts as a string)."""
    plans = {step: dict(plan) for step, plan in plans.items()}
    for item in items:
        target, sep, text = item.partition("=")
        step, _, key = target.partition(".")
        if not sep or step not in plans or not key:
            raise InputError(f"{item!r} is not STEP.KEY=VALUE with a step of {', '.join(STEP_ORDER)}", field="--set")
        if key not in plans[step]:
            raise InputError(f"{step} has no {key!r} (keys: {', '.join(plans[step])})", field="--set")
        try:
            value = json.loads(text)
        except ValueError:
            value = text
        plans[step][key] = value
    return plans


def _parse_steps(text: str) -> list[str]:
    steps = [s.strip() for s in text.split(",") if s.strip()]
    unknown = [s for s in steps if s not in STEP_ORDER]
    if unknown or not steps:
        raise InputError(f"unknown step(s) {unknown} (steps: {', '.join(STEP_ORDER)})", field="--steps")
    return [s for s in STEP_ORDER if s in steps]


def resolve_device(name: str) -> str:
    import torch
    if name == "cuda" and not torch.cuda.is_available():
        raise InputError("CUDA was asked for but no CUDA device is available", field="--device")
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return name


#: steps that read the capture subset
NEEDS_DATA = frozenset({"viclip", "fit"})


def resolve_data(text: str | None, size: str, work: Path) -> tuple[str | None, str]:
    """(capture directory or None, how it was chosen): ``text`` when given; else the carried subset for
    the full run and a tiny synthetic capture for the dry run ("synthetic" forces that one)."""
    from .device_data import DEFAULT_OUT, write_synthetic_capture

    if text not in (None, "synthetic"):
        path = Path(text)
        if not (path / "train_meta.json").is_file():
            raise InputError("is not a capture (no train_meta.json); build it with `fourlegs bench device-data`",
                             file=path, field="--data")
        from fourlegs_engine.fit.dataset import Capture
        Capture(path)  # its metadata as `fourlegs fit` checks it, before the machine's time is spent
        return str(path), f"{path} (given)"
    if text is None and size == "full":
        if (Path(DEFAULT_OUT) / "train_meta.json").is_file():
            return DEFAULT_OUT, f"{DEFAULT_OUT} (the carried subset)"
        return None, f"none: {DEFAULT_OUT} is missing (the steps that need frames say so)"
    return str(write_synthetic_capture(work / "synthetic_capture", overwrite=True)), "a tiny synthetic capture"


class GsplatBuild:
    """The background build's state, read from its status file (written by :mod:`.device_gsplat`)."""

    def __init__(self, status: str | None, site: str | None, log: str | None):
        self.status = Path(status) if status else None
        self.site = site
        self.log = Path(log) if log else None

    def state(self) -> dict[str, Any]:
        if self.status is None:
            return {"state": "not attempted", "reason": "no build was started (no --gsplat-status)"}
        try:
            return json.loads(self.status.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return {"state": "building", "reason": "no status yet"}

    def wait(self, until: float) -> dict[str, Any]:
        """Poll until the build has ended or ``until`` (epoch seconds) has passed."""
        state = self.state()
        while state["state"] == "building" and time.time() < until:
            time.sleep(2.0)
            state = self.state()
        return state


def _child_env(gsplat: dict[str, Any], site: str | None, threads: int | None) -> dict[str, str]:
    env = dict(os.environ)
    if threads:
        env.update(OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads), NUMBA_NUM_THREADS=str(threads))
    if gsplat.get("state") == "ok" and site:
        env["PYTHONPATH"] = os.pathsep.join([site, *filter(None, [env.get("PYTHONPATH")])])
    return env


#: seconds between two reports while a step runs (a run stopped from outside keeps the step's rows so far)
PROGRESS_EVERY_S = 15.0


def _read_result(path: Path) -> dict[str, Any]:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}


def run_step(name: str, config: dict[str, Any], work: Path, cap: float, env: dict[str, str],
             progress: Callable[[dict[str, Any]], None] | None = None) -> dict[str, Any]:
    """Run one step in its own process group, killed at ``cap`` seconds. Returns its result dict with
    ``status`` ("ok", "failed: …", "skipped: …", "timed out after N s") and ``seconds``; while it runs,
    ``progress`` receives what it has measured so far (status "running") every :data:`PROGRESS_EVERY_S`."""
    from fourlegs_engine.fileio import write_json_atomic

    config_path, result_path = work / f"{name}.config.json", work / f"{name}.result.json"
    write_json_atomic(config_path, {**config, "cap_s": cap})
    result_path.unlink(missing_ok=True)
    print(f"[device] {name}: start (cap {cap:.0f} s)", flush=True)
    start = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "fourlegs_bench.device_steps", name, str(config_path),
                             str(result_path)], env=env, start_new_session=True)
    code, timed_out = None, False
    while code is None:
        left = cap - (time.perf_counter() - start)
        if left <= 0:
            _kill_group(proc)
            timed_out = True
            break
        try:
            code = proc.wait(timeout=min(PROGRESS_EVERY_S, left))
        except subprocess.TimeoutExpired:
            if progress is not None:
                elapsed = time.perf_counter() - start
                progress({**_read_result(result_path), "status": f"running ({elapsed:.0f} s of its {cap:.0f} s cap)",
                          "seconds": round(elapsed, 2), "cap_s": round(cap, 1)})
    seconds = time.perf_counter() - start
    result = _read_result(result_path)
    if timed_out:
        status = f"timed out after {cap:.0f} s (its cap)"
    elif code == 0:
        status = "ok"
    elif code == 3:
        status = f"skipped: {result.get('skipped', 'no reason given')}"
    else:
        status = f"failed: {result.get('error') or f'exit status {code} (see device_log.txt)'}"
    print(f"[device] {name}: {status} ({seconds:.1f} s)", flush=True)
    return {**result, "status": status, "seconds": round(seconds, 2), "cap_s": round(cap, 1)}


def _kill_group(proc: subprocess.Popen) -> None:
    """SIGTERM the step's process group, SIGKILL it if it lingers (a hung CUDA call ignores SIGTERM)."""
    for sig, grace in ((signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(timeout=grace)
            return
        except subprocess.TimeoutExpired:
            continue


def _command_line() -> str:
    argv = sys.argv[1:]
    if argv[:2] == ["bench", "device"]:
        argv = argv[2:]
    return "fourlegs bench device " + " ".join(shlex.quote(a) for a in argv)


def run_device_check(args: argparse.Namespace) -> dict[str, Any]:
    """Run the selected steps in order and write the report after each; returns the report."""
    from .device_report import publish

    started = args.started if args.started is not None else time.time()
    budget = args.budget if args.budget is not None else DEFAULT_BUDGET_S[args.size]
    deadline = started + budget
    steps = _parse_steps(args.steps)
    caps = _parse_caps(args.cap)
    plans = apply_overrides(PLANS[args.size], args.set)
    work = Path(args.work or tempfile.mkdtemp(prefix="fourlegs-device-work-"))
    work.mkdir(parents=True, exist_ok=True)
    device = resolve_device(args.device)
    data, data_note = (resolve_data(args.data, args.size, work) if NEEDS_DATA & set(steps)
                       else (None, "not needed by the selected steps"))
    out = Path(args.out or os.environ.get("OUT") or tempfile.mkdtemp(prefix="fourlegs-device-"))
    out.mkdir(parents=True, exist_ok=True)  # once the inputs are known to be usable
    gsplat = GsplatBuild(args.gsplat_status, args.gsplat_site, args.gsplat_log)
    wait_until = started + (args.gsplat_wait if args.gsplat_wait is not None else DEFAULT_GSPLAT_WAIT_S[args.size])
    report: dict[str, Any] = {
        "format": "fourlegs-device-report", "version": 1, "command": _command_line(),
        "size": args.size, "device": device, "data": data, "data_note": data_note, "budget_s": budget,
        "started": time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(started)),
        "gsplat_build": gsplat.state(), "steps": {},
    }
    print(f"[device] {args.size} run on {device}, data: {data_note}; report in {out}", flush=True)
    publish(report, out, work, gsplat.log)
    for name in steps:
        left = deadline - time.time() - REPORT_RESERVE_S
        cap = min(float(caps.get(name, plans[name]["cap_s"])), left)
        if left < MIN_STEP_S:
            report["steps"][name] = {"status": f"skipped: the run's {budget:.0f} s budget is spent "
                                               f"({max(0.0, left):.0f} s left)"}
            publish(report, out, work, gsplat.log)
            continue
        state = gsplat.state()
        if name in NEEDS_GSPLAT and state["state"] == "building" and device == "cuda":
            print(f"[device] {name}: waiting for the gsplat build", flush=True)
            state = gsplat.wait(min(wait_until, deadline - MIN_STEP_S - REPORT_RESERVE_S))
            cap = min(cap, deadline - time.time() - REPORT_RESERVE_S)
        report["gsplat_build"] = state
        config = {"size": args.size, "device": device, "data": data, "work": str(work), "plan": plans[name]}
        def progress(partial: dict[str, Any], name: str = name) -> None:
            report["steps"][name] = partial
            report["gsplat_build"] = gsplat.state()
            publish(report, out, work, gsplat.log)

        result = run_step(name, config, work, max(cap, 1.0), _child_env(state, gsplat.site, args.threads), progress)
        result["gsplat_at_start"] = state["state"]
        report["steps"][name] = result
        report["gsplat_build"] = gsplat.state()
        publish(report, out, work, gsplat.log)
    report["finished"] = time.strftime("%Y-%m-%d %H:%M:%S")
    report["wall_seconds"] = round(time.time() - started, 1)
    publish(report, out, work, gsplat.log)
    print(f"[device] done in {report['wall_seconds']:.0f} s: {out}", flush=True)
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fourlegs_bench.device", description=__doc__.splitlines()[0])
    add_arguments(parser)
    args = parser.parse_args(argv)
    try:
        return run_device_cli(args)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
