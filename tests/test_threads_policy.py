"""OpenMP's idle workers sleep at barriers once fourlegs_engine is imported before torch (spinning
workers collapse on a shared machine); an explicit environment wins."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

PROBE = ("import fourlegs_engine, os, torch; from fourlegs_engine.threads import openmp_wait_policy; "
         "print(os.environ.get('OMP_WAIT_POLICY', '-'), openmp_wait_policy())")


@pytest.mark.parametrize("env_extra,expected", [({}, "PASSIVE PASSIVE"), ({"OMP_WAIT_POLICY": "ACTIVE"}, "ACTIVE ACTIVE"),
                                                ({"FOURLEGS_OPENMP_SPIN": "1"}, "- default")])
def test_import_sets_the_wait_policy_unless_the_environment_says_otherwise(env_extra, expected):
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "FOURLEGS_OPENMP_SPIN")}
    env.update(env_extra)
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == expected.split()


def test_the_command_line_and_this_test_session_run_passive():
    """The `fourlegs` entry point imports the package (and so sets the policy) before torch; conftest
    does the same for the tests."""
    assert os.environ.get("OMP_WAIT_POLICY") in ("PASSIVE", "ACTIVE") or os.environ.get("FOURLEGS_OPENMP_SPIN") == "1"
    import fourlegs_engine.commands.main as cli
    src = open(cli.__file__, encoding="utf-8").read()
    assert src.index("from .. import __version__") < (src.index("import torch") if "import torch" in src else len(src))
