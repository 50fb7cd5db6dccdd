"""gsplat for ``fourlegs bench device``: its CUDA code is compiled on first import, timed here.

gsplat's PyPI wheel (``py3-none-any``) holds the CUDA sources; importing ``gsplat.cuda._backend``
compiles them with torch's JIT extension builder (ninja + nvcc) into ``$TORCH_EXTENSIONS_DIR``, for the
visible GPU's architecture only, which takes minutes the first time and is reused afterwards.

``python -m fourlegs_bench.device_gsplat build --site DIR --status FILE --log FILE --cap S`` (started in
the background by ``scripts/device_check.sh``) runs that import in a child process with DIR on its
path, under a time cap, then renders a few Gaussians through ``gsplat.rasterization`` to prove the
kernels run. FILE always holds the state: ``building`` while it runs, then ``ok``, ``failed``,
``timed out`` or ``skipped``, with the seconds and a one-line reason; the orchestrator (:mod:`.device`)
puts DIR on the steps' path only once the state is ``ok``.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any


def _write_status(path: Path, status: dict[str, Any]) -> None:
    from fourlegs_engine.fileio import write_json_atomic
    write_json_atomic(path, status)


def _last_error_line(log: Path) -> str:
    try:
        lines = [ln.strip() for ln in log.read_text(encoding="utf-8", errors="replace").splitlines() if ln.strip()]
    except OSError:
        return "no log"
    errors = [ln for ln in lines if "error" in ln.lower()]
    return (errors[-1] if errors else lines[-1] if lines else "no output")[:300]


class _Stopped(Exception):
    """SIGTERM while the compiler runs (the check is over): the compiler is stopped too."""


def _raise_stopped(signum, frame) -> None:
    raise _Stopped()


def _kill_group(proc: subprocess.Popen) -> None:
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(proc.pid, sig)
            proc.wait(timeout=5)
            return
        except ProcessLookupError:
            return
        except subprocess.TimeoutExpired:
            continue


def build(site: Path, status_path: Path, log: Path, cap: float) -> dict[str, Any]:
    """Compile gsplat's extension in a child process (killed at ``cap`` seconds); returns the final status."""
    start = time.time()
    status: dict[str, Any] = {"state": "building", "started": start, "cap_s": cap, "site": str(site)}
    _write_status(status_path, status)
    if not (site / "gsplat").is_dir():
        status.update(state="skipped", reason=f"no gsplat package in {site} (no gsplat wheel in .whl/)")
        _write_status(status_path, status)
        return status
    result = status_path.with_name(status_path.stem + ".compile.json")
    result.unlink(missing_ok=True)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), *filter(None, [os.environ.get("PYTHONPATH")])])}
    with open(log, "a", encoding="utf-8") as f:
        f.write(f"[gsplat] compiling (cap {cap:.0f} s, MAX_JOBS={env.get('MAX_JOBS', 'gsplat default')}, "
                f"TORCH_EXTENSIONS_DIR={env.get('TORCH_EXTENSIONS_DIR', 'default')})\n")
        f.flush()
        proc = subprocess.Popen([sys.executable, "-m", "fourlegs_bench.device_gsplat", "compile", str(result)],
                                stdout=f, stderr=subprocess.STDOUT, env=env, start_new_session=True)
        stopped = False
        previous = signal.signal(signal.SIGTERM, _raise_stopped)
        try:
            code = proc.wait(timeout=cap)
        except (subprocess.TimeoutExpired, _Stopped) as exc:
            stopped = isinstance(exc, _Stopped)
            _kill_group(proc)
            code = None
        finally:
            signal.signal(signal.SIGTERM, previous)
    seconds = time.time() - start
    try:
        details = json.loads(result.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        details = {}
    status.update(details, seconds=round(seconds, 1))
    if stopped:
        status.update(state="failed", reason="stopped before it finished (the run ended first)")
    elif code is None:
        status.update(state="timed out", reason=f"the build did not finish within its {cap:.0f} s cap")
    elif code == 0:
        status.update(state="ok")
    elif code == 3:
        status.update(state="skipped", reason=details.get("reason", "no CUDA"))
    else:
        status.update(state="failed", reason=details.get("reason") or _last_error_line(log))
    _write_status(status_path, status)
    return status


def compile_and_check(result: Path) -> int:
    """In the child: import (and so compile) gsplat's extension, then render through it."""
    import torch

    from fourlegs_engine.fileio import write_json_atomic

    if not torch.cuda.is_available():
        write_json_atomic(result, {"reason": "no CUDA device"})
        return 3
    from torch.utils.cpp_extension import _get_build_directory

    build_dir = Path(_get_build_directory("gsplat_cuda", verbose=False))
    details: dict[str, Any] = {"build_dir": str(build_dir), "cached": (build_dir / "gsplat_cuda.so").is_file(),
                               "arch": os.environ.get("TORCH_CUDA_ARCH_LIST") or "{}.{} (the visible GPU)".format(
                                   *torch.cuda.get_device_capability())}
    start = time.perf_counter()
    from gsplat.cuda._backend import _C
    details["compile_seconds"] = round(time.perf_counter() - start, 1)
    import gsplat
    details["version"] = gsplat.__version__
    if _C is None:
        write_json_atomic(result, {**details, "reason": "gsplat found no CUDA toolkit (nvcc) and disabled itself"})
        return 1
    gen = torch.Generator(device="cuda").manual_seed(0)
    n = 100
    means = torch.randn(n, 3, device="cuda", generator=gen) * 0.3 + torch.tensor([0.0, 0.0, 3.0], device="cuda")
    quats = torch.nn.functional.normalize(torch.randn(n, 4, device="cuda", generator=gen), dim=-1)
    scales = torch.full((n, 3), 0.05, device="cuda")
    opac = torch.full((n,), 0.8, device="cuda")
    colors = torch.rand(n, 3, device="cuda", generator=gen)
    K = torch.tensor([[[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]]], device="cuda")
    render, alpha, _ = gsplat.rasterization(means, quats, scales, opac, colors, torch.eye(4, device="cuda")[None], K,
                                            64, 48)
    torch.cuda.synchronize()
    covered = float((alpha > 0.01).float().mean())
    details["smoke_test"] = {"finite": bool(torch.isfinite(render).all()), "covered_fraction": round(covered, 3)}
    if not details["smoke_test"]["finite"] or covered == 0.0:
        write_json_atomic(result, {**details, "reason": f"the smoke render is wrong: {details['smoke_test']}"})
        return 1
    write_json_atomic(result, details)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fourlegs_bench.device_gsplat", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    b = sub.add_parser("build", help="compile in a child process under a time cap, keeping FILE up to date")
    b.add_argument("--site", required=True, help="folder the gsplat wheel was installed into")
    b.add_argument("--status", required=True, help="status JSON to keep up to date")
    b.add_argument("--log", required=True, help="the compiler's output")
    b.add_argument("--cap", type=float, default=240.0, help="seconds before the build is killed (default 240)")
    c = sub.add_parser("compile", help="(the child) import gsplat's extension and render through it")
    c.add_argument("result", help="JSON of the details")
    args = parser.parse_args(argv)
    if args.command == "compile":
        return compile_and_check(Path(args.result))
    status = build(Path(args.site), Path(args.status), Path(args.log), args.cap)
    print(f"[gsplat] {status['state']} after {status.get('seconds', 0):.0f} s"
          + (f": {status['reason']}" if status.get("reason") else ""), flush=True)
    return 0 if status["state"] in ("ok", "skipped") else 1


if __name__ == "__main__":
    sys.exit(main())
