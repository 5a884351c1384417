"""core.freed_memory: a freed big block's pages serve the next one (no page faults), in a process of its own."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys

import pytest

# mallopt is glibc's (other C libraries: keep_freed_memory does nothing, and says so).
pytestmark = pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's allocator only")

_PROBE = """
import json, resource, sys
from monovoc_ros.core.freed_memory import keep_freed_memory
kept = keep_freed_memory() if sys.argv[1] == "keep" else False
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
block = bytearray(57_000_000)  # as a map message's buffers: allocated, touched, freed, once per message
del block
before = faults()
block = bytearray(57_000_000)
print(json.dumps({"kept": kept, "faults": faults() - before}))
"""


def _faults(mode: str, **env: str) -> dict:
    clean = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != "GLIBC_TUNABLES"}
    out = subprocess.run([sys.executable, "-c", _PROBE, mode], env={**clean, **env}, capture_output=True, text=True,
                         timeout=60, check=True)  # fmt: skip
    return json.loads(out.stdout)


def test_a_freed_block_serves_the_next_without_faulting_its_pages_again():
    default, kept = _faults("default"), _faults("keep")
    # Mapped afresh: 57 MB of pages faulted in again (13.9k of 4 KiB; ~30 where huge pages are on for everything).
    assert not default["kept"] and default["faults"] >= 20
    assert kept["kept"] and 10 * kept["faults"] < default["faults"]


def test_a_users_own_allocator_settings_are_left_as_they_are():
    theirs, default = _faults("keep", MALLOC_TRIM_THRESHOLD_="131072"), _faults("default")
    assert not theirs["kept"] and theirs["faults"] > default["faults"] // 2
