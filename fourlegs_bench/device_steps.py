"""The steps of ``fourlegs bench device``, each run in a process of its own (the speed steps live in
:mod:`.device_speed`, the main job in :mod:`.device_main_job`, the fit in :mod:`.device_fit`).

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
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

REPO = Path(__file__).resolve().parents[1]
#: the repository's CPU figures, shown beside the GPU rows
CPU_FIGURES = {"viclip": REPO / "docs/bench/viclip_real.json", "render": REPO / "docs/bench/render.json",
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


def sync(device) -> None:
    import torch
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def cpu_figures(name: str) -> Any:
    """The repository's CPU figures for ``name`` (None when the file is not in this checkout)."""
    path = CPU_FIGURES[name]
    if not path.is_file():
        return None
    from fourlegs_engine.fileio import read_json
    return read_json(path)


def one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0][:200] if text else ''}"


def require_cuda(ctx: StepContext) -> None:
    if ctx.device.type != "cuda":
        raise StepSkipped("no CUDA")


def gsplat_usable() -> bool:
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
    info["ninja"] = _command_output(["ninja", "--version"])      # torch's extension builder runs it by name
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


#: step name -> "module:function" (imported when the step runs: each step process loads only its own)
STEPS: dict[str, str] = {
    "env": "device_steps:step_env", "viclip": "device_speed:step_viclip", "main_job": "device_main_job:step_main_job",
    "raster_torch": "device_speed:step_raster_torch", "raster_gsplat": "device_speed:step_raster_gsplat",
    "cuda_tests": "device_steps:step_cuda_tests", "fit": "device_fit:step_fit",
}


def step_function(name: str) -> Callable[[StepContext], None]:
    import importlib

    module, function = STEPS[name].split(":")
    return getattr(importlib.import_module(f"{__package__}.{module}"), function)


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
        step_function(name)(ctx)
    except StepSkipped as exc:
        ctx.record(skipped=str(exc))
        return 3
    except Exception as exc:                                  # the orchestrator reports it as one line
        import traceback
        traceback.print_exc()
        ctx.record(error=one_line(exc))
        return 1
    return 0


if __name__ == "__main__":
    # run the package's copy of this module, not __main__: the step modules raise its StepSkipped
    from fourlegs_bench.device_steps import main as package_main
    sys.exit(package_main())
