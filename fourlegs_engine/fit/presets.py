"""Named knob sets of a fit (overrides of the :class:`~.options.FitOptions` defaults), importable without
torch so that ``--help`` stays cheap; docs/benchmarks_fit.md measures them."""
from __future__ import annotations

from typing import Any

FIT_PRESETS: dict[str, dict[str, Any]] = {
    "default": {},
    "accurate": {"resolution_scale": 1.0, "first_iterations": 3000, "iterations": 80, "max_iterations": 240,
                 "min_iterations": 27, "max_gaussians": 200_000, "init_background": 60_000,
                 "free_part_fraction": 0.5},
}
