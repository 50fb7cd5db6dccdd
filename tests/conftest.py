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


def pytest_sessionfinish(session, exitstatus):
    session.config.fourlegs_exit_status = int(exitstatus)


def pytest_unconfigure(config):
    """Under bpy 4.x end the test process without C++ static destructors: bpy 4.5 deadlocks in one at
    interpreter exit, which would hang the run after its summary. bpy 5.0 and runs that never
    imported bpy exit normally."""
    import sys

    if "bpy" not in sys.modules:
        return
    from fourlegs_addon import headless

    if headless.bpy_deadlocks_at_exit():
        headless.exit_without_destructors(getattr(config, "fourlegs_exit_status", 0))
