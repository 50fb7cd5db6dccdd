"""Registers the 4D method in ``fourlegs bench grounding`` (imported by ``eval.grounding`` on first use).

The method itself lives in :mod:`fourlegs_engine.eval.method4d` (eval may use every package); this
module only exists because ``eval.grounding.METHOD_MODULES`` names it. It is imported by eval only.
"""
from __future__ import annotations

from ..eval.method4d import register

register()
