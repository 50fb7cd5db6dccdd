"""Freed memory stays in the process (fourlegs_engine.memory): a frame's buffers reuse the last frame's
instead of arriving as fresh pages, unless FOURLEGS_RETURN_FREED_MEMORY=1."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

PROBE = r"""
import json, resource
import fourlegs_engine
import numpy as np
from fourlegs_engine.memory import freed_memory_kept

def faults_of_a_frame_buffer():
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    block = np.empty(40 << 20, dtype=np.uint8)  # beyond glibc's largest adaptive mmap threshold
    block.fill(1)
    del block
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

faults_of_a_frame_buffer()
print(json.dumps({"kept": freed_memory_kept(), "faults": faults_of_a_frame_buffer()}))
"""


def _probe(return_freed: bool) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "FOURLEGS_RETURN_FREED_MEMORY"}
    if return_freed:
        env["FOURLEGS_RETURN_FREED_MEMORY"] = "1"
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def _glibc() -> bool:
    try:
        return sys.platform.startswith("linux") and (os.confstr("CS_GNU_LIBC_VERSION") or "").startswith("glibc")
    except (ValueError, OSError):
        return False


@pytest.mark.skipif(not _glibc(), reason="the thresholds are glibc's")
def test_a_second_frame_buffer_reuses_freed_memory():
    kept = _probe(return_freed=False)
    returned = _probe(return_freed=True)
    assert kept["kept"] and not returned["kept"]
    assert kept["faults"] < 5, kept
    assert returned["faults"] > 10, returned  # a fresh mapping: every page (or huge page) faulted in again


def test_keep_freed_memory_is_idempotent_and_reports_itself():
    from fourlegs_engine import memory

    first = memory.keep_freed_memory()
    assert memory.keep_freed_memory() == first == memory.freed_memory_kept()
