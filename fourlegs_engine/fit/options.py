"""The options of a fit (:class:`FitOptions`) and what its progress callback receives (:class:`FitEvent`)."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import torch

from ..errors import InputError
from .init import INIT_METHODS
from .presets import FIT_PRESETS


@dataclass(frozen=True)
class FitOptions:
    """Knobs of :func:`fit_capture` (defaults: one CPU core at 320×180; docs/benchmarks_fit.md measures them).

    Attributes:
        resolution_scale: images and intrinsics are scaled by this (0.5: 640×360 → 320×180).
        timesteps: (a, b) half-open range of timesteps to fit (None: all).
        cameras: training camera ids to use (None: every training camera).
        first_iterations: optimization steps of the first (static) timestep (the paper's code: 10,000).
        iterations: steps of every later timestep (the paper's code: 2,000); with ``max_iterations`` the
            base count of the residual-driven schedule.
        max_iterations: 0: every later timestep gets ``iterations``; more: each later timestep gets
            ``iterations`` scaled by its forecast's residual on the moving pixels against the median of
            the earlier timesteps', between ``min_iterations`` and this cap (:mod:`.effort`).
        min_iterations: the floor of that schedule (``iterations`` where that is lower).
        max_gaussians: densification never grows the model past this.
        init: how the initial Gaussians are made: "hull" (visual hull + background proxy), "features"
            (triangulated feature matches, needs OpenCV) or "hull+features" (:mod:`.init`).
        init_foreground, init_background: caps on the initial foreground / background points.
        voxel: visual-hull voxel side (m). background_stride: pixel stride of the background proxy samples.
        densify: clone/split/prune during the first timestep.
        clean_plate_samples: timesteps (spread over the fitted range) whose background pixels make each
            training camera's clean plate, the target of the background-only render at the first
            timestep and the source of background points hidden by the people there (0: neither;
            docs/benchmarks_fit.md measures the default with them).
        grad_threshold: densify Gaussians whose mean screen-space gradient (NDC units, as in 3DGS)
            exceeds this.
        knn: neighbours per foreground Gaussian for the priors.
        knn_lambda: neighbour weight exp(−λ d²) (d in metres).
        weights: loss weights (im, seg, rigid, rot, iso, floor, plate).
        lr_means: centre learning rate as a fraction of the scene radius (first timestep).
        lr_means_later: the same for later timesteps (fewer steps than the paper, so larger), for a centre
            moving at the median speed (see ``motion_step_range``).
        motion_step_range: later timesteps move each foreground centre by steps scaled with its speed
            (its displacement between the two previous timesteps) against the median speed, the scale
            clamped to [1 / range, range]: a fast ball takes larger steps than the slower people
            (1, the default since the part steps carry the ball: the same step for all).
        part_extent: above 0, each later timestep starts with steps that move rigid parts of the
            foreground (:mod:`.clusters`: what touches at the first timestep, cut to at most this long, in
            metres) before the steps that move each Gaussian: a part that moved farther than its own size
            (the thrown ball) is pulled over whole instead of tearing (0: off).
        part_fraction: those part steps at the first later timestep (no velocity known yet: every part),
            as a fraction of its steps (added to them).
        free_part_fraction: the same at every later timestep for the free parts only (whole connected
            components such as the ball, which the constant-velocity forecast misses when caught or
            bounced; the cut parts of the people are left to the per-Gaussian steps).
        part_scale: the resolution of the part steps, as a fraction of the fit resolution (images
            area-averaged).
        lr_colors, lr_rotations, lr_opacities, lr_scales, lr_camera: Adam learning rates of the first
            timestep (colours and scales at the paper's code's rates).
        lr_colors_later: above 0, the foreground colours are optimized at every later timestep too, with
            this Adam learning rate, starting from the previous timestep's, and the fitted scene's colours
            vary per timestep (T,N,3), as in the paper's code (its rate, the default: 0.0025); 0: the first
            timestep's colours throughout.
        seed: every random choice derives from it.
        device: "auto" (CUDA when available), "cpu" or "cuda".
    """

    resolution_scale: float = 0.5
    timesteps: tuple[int, int] | None = None
    cameras: tuple[str, ...] | None = None
    first_iterations: int = 600
    iterations: int = 96
    max_iterations: int = 288
    min_iterations: int = 30
    max_gaussians: int = 60_000
    init: str = "hull"
    init_foreground: int = 30_000
    init_background: int = 30_000
    voxel: float = 0.02
    background_stride: int = 6
    densify: bool = True
    clean_plate_samples: int = 8
    grad_threshold: float = 0.0002
    knn: int = 20
    knn_lambda: float = 2000.0
    weights: dict[str, float] = field(default_factory=lambda: {
        "im": 1.0, "seg": 3.0, "rigid": 4.0, "rot": 4.0, "iso": 2.0, "floor": 2.0, "plate": 1.0})
    lr_means: float = 0.00016
    lr_means_later: float = 0.0008
    motion_step_range: float = 1.0
    part_extent: float = 0.4
    part_fraction: float = 0.5
    free_part_fraction: float = 0.25
    part_scale: float = 0.5
    lr_colors: float = 0.0025
    lr_rotations: float = 0.001
    lr_rotations_later: float = 0.004
    lr_opacities: float = 0.05
    lr_scales: float = 0.001
    lr_camera: float = 0.001
    lr_colors_later: float = 0.0025
    seed: int = 0
    device: str = "auto"

    def check(self) -> "FitOptions":
        if not 0 < self.resolution_scale <= 4:
            raise InputError(f"must be in (0, 4], got {self.resolution_scale}", field="resolution_scale")
        if not 0 <= int(self.seed) < 2 ** 32:
            raise InputError(f"must be an integer in 0..{2 ** 32 - 1}, got {self.seed}", field="--seed")
        if int(self.clean_plate_samples) < 0:
            raise InputError(f"must be 0 or more, got {self.clean_plate_samples}", field="clean_plate_samples")
        if int(self.max_iterations) and not int(self.iterations) <= int(self.max_iterations):
            raise InputError(f"needs iterations <= max_iterations, got {self.iterations} and {self.max_iterations}",
                             field="max_iterations")
        for name in ("first_iterations", "iterations", "min_iterations", "max_iterations", "max_gaussians", "init_foreground", "init_background",
                     "knn", "background_stride"):
            if int(getattr(self, name)) < (0 if name.endswith("iterations") else 1):
                raise InputError(f"must be a positive integer, got {getattr(self, name)}", field=name)
        if self.init not in INIT_METHODS:
            raise InputError(f"must be one of {', '.join(INIT_METHODS)}, got {self.init!r}", field="init")
        if self.init != "hull":
            from .features import require_cv2

            require_cv2()
        if not 1.0 <= float(self.motion_step_range) <= 100.0:
            raise InputError(f"must be in [1, 100], got {self.motion_step_range}", field="motion_step_range")
        if not 0.0 <= float(self.part_extent) < float("inf"):
            raise InputError(f"must be 0 or a positive length in metres, got {self.part_extent}", field="part_extent")
        for name in ("part_fraction", "free_part_fraction"):
            if not 0.0 <= float(getattr(self, name)) <= 4.0:
                raise InputError(f"must be in [0, 4], got {getattr(self, name)}", field=name)
        if not 0.0 < float(self.part_scale) <= 1.0:
            raise InputError(f"must be in (0, 1], got {self.part_scale}", field="part_scale")
        if not 0.0 <= float(self.lr_colors_later) < float("inf"):
            raise InputError(f"must be 0 (off) or a positive learning rate, got {self.lr_colors_later}",
                             field="lr_colors_later")
        if self.device not in ("auto", "cpu", "cuda"):
            raise InputError(f"must be auto, cpu or cuda, got {self.device!r}", field="device")
        if self.device == "cuda" and not torch.cuda.is_available():
            raise InputError("CUDA was requested but no CUDA device is available", field="device")
        return self

    def fingerprint(self) -> dict[str, Any]:
        """Everything that changes the result (the device is left out: CPU and CUDA differ anyway)."""
        d = asdict(self)
        d.pop("device")
        # knobs at their "off" value are left out, so fits started before these knobs existed still resume
        if d["max_iterations"] == 0:
            d.pop("max_iterations")
            d.pop("min_iterations")
        if d["init"] == "hull":
            d.pop("init")
        if d["motion_step_range"] == 1.0:
            d.pop("motion_step_range")
        if d["part_extent"] == 0.0:
            for name in ("part_extent", "part_fraction", "free_part_fraction", "part_scale"):
                d.pop(name)
        if d["lr_colors_later"] == 0.0:
            d.pop("lr_colors_later")
        if d["clean_plate_samples"] == 0:
            d.pop("clean_plate_samples")
            d["weights"] = {k: v for k, v in d["weights"].items() if k != "plate"}
        d["timesteps"] = list(d["timesteps"]) if d["timesteps"] is not None else None
        d["cameras"] = list(d["cameras"]) if d["cameras"] is not None else None
        return d


def preset_options(name: str, **overrides: Any) -> FitOptions:
    """The :class:`FitOptions` of preset ``name`` with ``overrides`` on top."""
    if name not in FIT_PRESETS:
        raise InputError(f"must be one of {', '.join(FIT_PRESETS)}, got {name!r}", field="preset")
    return FitOptions(**{**FIT_PRESETS[name], **overrides})


@dataclass
class FitEvent:
    """What a progress callback receives: ``kind`` is "iteration" (one optimization step) or "timestep"
    (a timestep finished, or ``resumed`` from the work directory)."""

    kind: str
    timestep: int
    index: int = 0
    total: int = 0
    loss: float = float("nan")
    train_psnr: float = float("nan")
    resumed: bool = False
