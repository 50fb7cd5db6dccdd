"""Named extraction plans: the cost knobs of feature extraction in scene-independent terms.

Cheap to import (no torch): the command line lists the plan names and the benchmarks count clips
without loading the network code. :mod:`.budget` prices a plan on a scene and device.

Named plans (:data:`PLANS`): ``"full"`` is the paper's extraction (every training camera and timestep,
the 5-level pyramid with half-crop overlap). ``"default"`` is the measured cheap plan
(``docs/benchmarks_language_cost.md``). ``"auto"`` is ``"default"`` for network encoders (ViCLIP) and
``"full"`` for the encoders whose features cost next to nothing (simulated, annotation masks).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from ..errors import InputError

if TYPE_CHECKING:
    from ..scene.scene import Scene
    from .extract import ExtractOptions

#: neighbouring crops overlap by half their side (paper)
PAPER_CROP_STRIDE = 0.5
#: how timesteps off the stride's grid are filled: their crop features ("interpolate" between the two encoded
#: neighbours, "reuse" the nearer one), or their lifted field ("latents": every Gaussian gets the
#: interpolation of its own latents at the two encoded neighbours, so the fill moves with the Gaussians)
FILL_MODES = ("interpolate", "reuse", "latents")
#: the fill modes whose in-between timesteps have no teacher features (the lift fills them)
LATENT_FILLS = ("latents",)
#: which crops an early exit copies from the previous encoded timestep instead of encoding
EARLY_EXITS = ("none", "foreground", "difference")


@dataclass(frozen=True)
class ExtractPlan:
    """Scene-independent cost knobs of feature extraction.

    Attributes:
        name: "full", "default" or "custom".
        cameras: encode this many training cameras, chosen for coverage (None: all).
        timestep_stride: encode every n-th timestep and the last; fill the others (``fill``).
        timestep_seconds: encode timesteps this many seconds apart instead (None: use ``timestep_stride``):
            the stride is the most whole timesteps within it at the scene's frame rate, at least 1
            (:meth:`stride_at`), so a plan keeps the same spacing in time on a 30 fps and an 8 fps capture.
        fill: "interpolate" | "reuse" (crop features) | "latents" (the lifted field; :data:`FILL_MODES`).
        levels: indices of the pyramid scales kept (None: all), e.g. (1, 2, 3, 4) drops the smallest.
        crop_stride: distance between neighbouring crops, as a fraction of the crop side (0.5: paper).
        early_exit: "none" | "foreground" | "difference".
    """

    name: str = "custom"
    cameras: int | None = None
    timestep_stride: int = 1
    timestep_seconds: float | None = None
    fill: str = "interpolate"
    levels: tuple[int, ...] | None = None
    crop_stride: float = PAPER_CROP_STRIDE
    early_exit: str = "none"

    def with_(self, **changes: Any) -> "ExtractPlan":
        """This plan with some knobs changed (named "custom" unless ``name`` is given)."""
        changes = {k: v for k, v in changes.items() if v is not None}
        if not changes:
            return self
        if "timestep_stride" in changes and "timestep_seconds" not in changes:
            changes["timestep_seconds"] = None     # a stride in timesteps given now replaces one in seconds
        return replace(self, **{"name": "custom", **changes})

    def stride_at(self, fps: float) -> int:
        """The timestep stride on a scene of ``fps`` timesteps per second."""
        if self.timestep_seconds is None:
            return int(self.timestep_stride)
        seconds, rate = float(self.timestep_seconds), float(fps)
        if not (math.isfinite(seconds) and seconds > 0):
            raise InputError(f"must be a positive number of seconds, got {self.timestep_seconds!r}",
                             field="--timestep-seconds")
        if not (math.isfinite(rate) and rate > 0):
            raise InputError(f"the scene's frame rate must be positive, got {fps!r}", field="fps")
        return max(1, int(math.floor(seconds * rate + 1e-6)))

    def extract_config(self, scene: "Scene", base: "ExtractOptions | None" = None) -> "ExtractOptions":
        """The plan on ``scene``: ``base`` (ratios, crop size, batch, split) with the knobs applied."""
        from .extract import ExtractOptions
        from .skipping import coverage_cameras

        base = base or ExtractOptions()
        ratios = tuple(base.ratios)
        if self.levels is not None:
            bad = [i for i in self.levels if not 0 <= int(i) < len(ratios)]
            if bad or not self.levels:
                raise InputError(f"levels {list(self.levels)} must be distinct indices of the {len(ratios)} "
                                 f"pyramid scales 0..{len(ratios) - 1}", field="--levels")
            ratios = tuple(ratios[int(i)] for i in sorted(set(self.levels)))
        cameras = None
        count = scene.cameras.num_cameras(base.split)
        if self.cameras is not None:
            if not 1 <= int(self.cameras):
                raise InputError(f"must be >= 1, got {self.cameras}", field="--camera-subset")
            if int(self.cameras) < count:
                cams = scene.cameras.cameras(0, base.split)
                cameras = tuple(coverage_cameras(np.stack([c.center for c in cams]),
                                                 np.stack([c.forward for c in cams]), int(self.cameras)))
        return replace(base, ratios=ratios, cameras=cameras, crop_stride=float(self.crop_stride),
                       timestep_stride=self.stride_at(scene.fps), fill=self.fill,
                       early_exit=self.early_exit).check(count)

    def describe(self, fps: float | None = None) -> str:
        """One line naming every knob (with ``fps``, a spacing in seconds also as its stride there)."""
        if self.timestep_seconds is None:
            skips, spacing = self.timestep_stride > 1, f"timestep stride {self.timestep_stride}"
        else:
            skips = fps is None or self.stride_at(fps) > 1
            spacing = f"timesteps {self.timestep_seconds:g} s apart" + (
                f" (stride {self.stride_at(fps)} at {fps:g} fps)" if fps else "")
        parts = [f"cameras {'all' if self.cameras is None else self.cameras}",
                 spacing + (f" ({self.fill})" if skips else ""),
                 f"levels {'all' if self.levels is None else ','.join(str(i) for i in self.levels)}",
                 f"crop stride {self.crop_stride:g}", f"early exit {self.early_exit}"]
        return f"plan {self.name}: " + ", ".join(parts)


PLANS: dict[str, ExtractPlan] = {
    "full": ExtractPlan("full"),
    # timesteps 0.2 s apart (every 6th at 30 fps; their 8-frame tubes overlap by 2 frames), crops 0.65 of their
    # side apart, unchanged crops copied: docs/benchmarks_language_cost.md
    "default": ExtractPlan("default", timestep_seconds=0.2, fill="interpolate", crop_stride=0.65,
                           early_exit="foreground"),
}
PLAN_NAMES = ("auto", *PLANS)


def resolve_plan(plan: str | ExtractPlan | None, encoder: Any) -> ExtractPlan:
    """A plan by name; "auto"/None: "default" for network (RGB) encoders, "full" for label encoders."""
    if isinstance(plan, ExtractPlan):
        return plan
    name = plan or "auto"
    if name == "auto":
        name = "default" if getattr(encoder, "input_kind", "rgb") == "rgb" else "full"
    if name not in PLANS:
        raise InputError(f"unknown plan {name!r} (choose from {', '.join(PLAN_NAMES)})", field="--plan")
    return PLANS[name]


def plan_clips(plan: ExtractPlan, num_cameras: int, num_timesteps: int, width: int, height: int, *,
               exit_share: float = 0.0, ratios: Sequence[float] | None = None, fps: float = 30.0) -> dict[str, float]:
    """The plan's clips on a rig of ``num_cameras`` identical ``width`` x ``height`` cameras over
    ``num_timesteps`` at ``fps`` (no scene needed; e.g. the Panoptic capture: 27 x 150 at 640 x 360, 30 fps).

    Returns ``{"full", "planned", "expected", "reduction"}``: the paper's clips, the plan's before early
    exits, after them (``exit_share`` of the crops of every encoded timestep but the first copied), and
    full / expected."""
    from .pyramid import crop_layout, pyramid_ratios
    from .skipping import encoded_timesteps

    ratios = tuple(ratios) if ratios is not None else pyramid_ratios()
    kept = ratios if plan.levels is None else tuple(ratios[int(i)] for i in sorted(set(plan.levels)))
    full = crop_layout(width, height, ratios).num_crops * num_cameras * num_timesteps
    cams = num_cameras if plan.cameras is None else min(int(plan.cameras), num_cameras)
    steps = len(encoded_timesteps(num_timesteps, plan.stride_at(fps)))
    per_step = crop_layout(width, height, kept, plan.crop_stride).num_crops * cams
    share = float(exit_share) if plan.early_exit != "none" else 0.0
    expected = per_step * (min(steps, 1) + max(steps - 1, 0) * (1.0 - share))
    return {"full": float(full), "planned": float(per_step * steps), "expected": float(expected),
            "reduction": float(full / max(expected, 1e-9))}
