"""Benchmarks and evaluation of the 4-LEGS engine (``fourlegs bench ...``); never imported by the engine.

- :mod:`.commands` — the argument parsers (registered through the ``fourlegs.commands`` entry point).
- :mod:`.grounding`, :mod:`.method4d`, :mod:`.baseline2d`, :mod:`.ground_truth`, :mod:`.metrics` — the
  spatio-temporal grounding benchmark on synthetic scenes (paper metrics vAP, vIoU, tIoU, ...).
- :mod:`.accuracy_time`, :mod:`.compare` — every query knob's seconds next to its accuracy.
- :mod:`.render`, :mod:`.query_speed`, :mod:`.query_speed_tiled`, :mod:`.distill`, :mod:`.viclip`,
  :mod:`.blender` — speed and accuracy of the rasterizer, the query paths, distillation, ViCLIP and the
  Blender layer.
"""
from .metrics import METRIC_NAMES, grounding_metrics

__all__ = ["METRIC_NAMES", "grounding_metrics"]
