"""How far the rasterizer is from what the machine could do: the work of a frame and its floor.

* :func:`measure_peak` — one core's fp32 matmul GFLOP/s and exp/s (torch, one thread, CPU seconds);
* :func:`frame_work` — the pixel–Gaussian pairs of a frame: inside the bounding boxes, inside the
  footprints (α ≥ 1/255), evaluated by the v2 kernels, actually blended;
* :func:`floor_ms` — the two floors of a forward pass from those counts: arithmetic
  (``FLOPS_PER_BLENDED_PAIR + 2·C`` per blended pair, ``FLOPS_PER_REJECTED_PAIR`` per pair of the boxes
  that is not blended, at the matmul peak) and exp throughput (one exp per footprint pair at the exp
  peak). A renderer that touches only the blended pairs and needs no exp beats the first; the second is
  the cost of evaluating every footprint pair directly. The measured time divided by each is the gap.
"""
from __future__ import annotations

import time

import torch

#: flops per blended pixel–Gaussian pair besides its channels: the exponent (dx, dy, the quadratic:
#: 10), clamp and test (2), transmittance update and stop test (3), weight (1), a few index operations
#: (8); each blended channel adds a multiply-add (2)
FLOPS_PER_BLENDED_PAIR = 24
#: flops per pair inside a bounding box that is not blended: the exponent and its test
FLOPS_PER_REJECTED_PAIR = 21


def measure_peak(repeats: int = 5, matmul_side: int = 1024, exp_elements: int = 1 << 22) -> dict:
    """One thread's fp32 matmul rate (GFLOP/s) and exp rate (G exp/s), best of ``repeats`` in CPU
    seconds (a busy machine lowers them less than wall time would)."""
    from fourlegs_engine.threads import torch_threads

    with torch_threads(1), torch.no_grad():
        a = torch.randn(matmul_side, matmul_side)
        b = torch.randn(matmul_side, matmul_side)
        x = torch.rand(exp_elements) * -8.0
        out = torch.empty_like(x)
        torch.mm(a, b)
        torch.exp(x, out=out)
        mm_s = exp_s = float("inf")
        for _ in range(repeats):
            c0 = time.process_time()
            torch.mm(a, b)
            mm_s = min(mm_s, time.process_time() - c0)
            c0 = time.process_time()
            torch.exp(x, out=out)
            exp_s = min(exp_s, time.process_time() - c0)
    return {"gflops": 2.0 * matmul_side ** 3 / max(mm_s, 1e-9) / 1e9,
            "gexp_per_s": exp_elements / max(exp_s, 1e-9) / 1e9}


def frame_work(scene, options=None, channels: int = 3) -> dict:
    """The pixel–Gaussian pair counts of one benchmark frame (see
    :func:`fourlegs_engine.render.kernel_backend.count_work`)."""
    from fourlegs_engine.render.kernel_backend import count_work

    return count_work(scene.means, scene.rotations, scene.log_scales, scene.opacity_logits, scene.camera, options,
                      channels=channels)


def floor_ms(work: dict, peak: dict, channels: int) -> tuple[float, float]:
    """(arithmetic floor, exp floor) in ms of a forward pass blending ``channels`` values."""
    blended = work["blended"]
    flops = blended * (FLOPS_PER_BLENDED_PAIR + 2 * channels) + (work["in_boxes"] - blended) * FLOPS_PER_REJECTED_PAIR
    return flops / (peak["gflops"] * 1e9) * 1e3, work["in_footprints"] / (peak["gexp_per_s"] * 1e9) * 1e3
