"""Shared test configuration.

- Generated artefacts (synthetic scenes) go to ``$FOURLEGS_CACHE`` (scripts/test.sh points it inside
  the checkout); when unset, to a per-session temporary directory so tests never touch ~/.cache.
- Hypothesis runs without per-example deadlines: CI machines are slow and shared.
- ``fourlegs_engine`` is imported before any test module imports torch, so OpenMP workers sleep at
  barriers (``OMP_WAIT_POLICY=PASSIVE``): on a loaded machine spinning workers make every parallel
  torch operation many times slower.
"""
from __future__ import annotations

import os
import tempfile

import fourlegs_engine  # noqa: F401,E402  (first: it sets the OpenMP wait policy before torch loads)
from hypothesis import HealthCheck, settings  # noqa: E402

if not os.environ.get("FOURLEGS_CACHE"):
    os.environ["FOURLEGS_CACHE"] = tempfile.mkdtemp(prefix="fourlegs-test-cache-")

# property tests draw this many examples by default (FOURLEGS_HYPOTHESIS_EXAMPLES=200 for a thorough run); the
# whole suite has to stay within 10 minutes on 2 cores
settings.register_profile("ci", deadline=None, max_examples=int(os.environ.get("FOURLEGS_HYPOTHESIS_EXAMPLES", "25")),
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
settings.load_profile("ci")
