"""The rasterizer next to a competing busy process: does it get its share of the CPU, or collapse?

Each case runs in a fresh process (OpenMP reads its wait policy once, when torch loads): a fit-like
step — the benchmark scene's rgb forward+backward with gradients for every input — timed on ``threads``
torch threads (and as many kernel workers), alone or while one busy process (a Python loop) runs
beside it, under this project's OpenMP policy (``PASSIVE``: idle workers sleep) and under OpenMP's
default (``FOURLEGS_OPENMP_SPIN=1``: idle workers spin at every barrier first).

``python -m fourlegs_bench.render_busy N KERNEL THREADS REPEATS`` is the measured child; it prints one
JSON line.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time

#: the competing process: one core's worth of pure busy work
BUSY_LOOP = "while True:\n    pass\n"
#: (name, extra environment) of the OpenMP policies compared
POLICIES = (("passive", {}), ("openmp-default", {"FOURLEGS_OPENMP_SPIN": "1"}))


def run_child(n: int, kernel: str, threads: int, repeats: int) -> dict:
    """Time the fit-like step in this process: median wall and CPU ms per step after one warm-up."""
    import statistics

    import torch

    from fourlegs_bench.render import _render_fn
    from fourlegs_bench.render_scene import make_bench_scene
    from fourlegs_engine.render import RasterOptions
    from fourlegs_engine.threads import kernel_threads, openmp_wait_policy

    torch.set_num_threads(threads)
    scene = make_bench_scene(n, feature_dim=8)
    step = _render_fn(scene, "rgb", "backward", "torch", options=RasterOptions(kernel=kernel))
    walls, cpus = [], []
    with kernel_threads(threads):
        step()
        for _ in range(repeats):
            w0, c0 = time.perf_counter(), time.process_time()
            step()
            walls.append((time.perf_counter() - w0) * 1e3)
            cpus.append((time.process_time() - c0) * 1e3)
    return {"wall_ms": statistics.median(walls), "cpu_ms": statistics.median(cpus),
            "omp_wait_policy": openmp_wait_policy(), "threads": torch.get_num_threads()}


def busy_records(n: int, kernels: tuple[str, ...], threads: int, repeats: int, progress=None) -> list[dict]:
    """One record per (kernel, policy, competitor or not): wall and CPU ms of the fit-like step."""
    records = []
    for kernel in kernels:
        for policy, env_extra in POLICIES:
            for busy in (False, True):
                competitor = subprocess.Popen([sys.executable, "-c", BUSY_LOOP]) if busy else None
                try:
                    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "FOURLEGS_OPENMP_SPIN")}
                    env.update(env_extra)
                    done = subprocess.run([sys.executable, "-m", "fourlegs_bench.render_busy", str(n), kernel,
                                           str(threads), str(repeats)], env=env, capture_output=True, text=True,
                                          check=True)
                finally:
                    if competitor is not None:
                        competitor.kill()
                        competitor.wait()
                result = json.loads(done.stdout.strip().splitlines()[-1])
                records.append({"part": "busy", "n": n, "output": "rgb", "mode": "backward", "kernel": kernel,
                                "policy": policy, "competitor": busy, "device": "cpu", "backend": "torch",
                                "ms_median": round(result["wall_ms"], 2), "cpu_ms_median": round(result["cpu_ms"], 2),
                                "peak_mb": 0.0, "step_threads": result["threads"],
                                "omp_wait_policy": result["omp_wait_policy"]})
                if progress:
                    progress(records[-1])
    for r in records:
        quiet = next(q for q in records if q["kernel"] == r["kernel"] and q["policy"] == r["policy"]
                     and not q["competitor"])
        r["x_alone"] = round(r["ms_median"] / max(quiet["ms_median"], 1e-9), 2)
    return records


def main(argv: list[str]) -> int:
    import fourlegs_engine  # noqa: F401  (before torch: the OpenMP policy)

    n, kernel, threads, repeats = int(argv[0]), argv[1], int(argv[2]), int(argv[3])
    print(json.dumps(run_child(n, kernel, threads, repeats)))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
