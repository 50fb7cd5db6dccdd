"""Shared test configuration.

- Generated artefacts (synthetic scenes) go to ``$FOURLEGS_CACHE`` (scripts/test.sh points it inside
  the checkout); when unset, to a per-session temporary directory so tests never touch ~/.cache.
- Hypothesis runs without per-example deadlines: CI machines are slow and shared.
"""
from __future__ import annotations

import os
import tempfile

from hypothesis import HealthCheck, settings

if not os.environ.get("FOURLEGS_CACHE"):
    os.environ["FOURLEGS_CACHE"] = tempfile.mkdtemp(prefix="fourlegs-test-cache-")

settings.register_profile("ci", deadline=None, max_examples=40,
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
settings.load_profile("ci")
