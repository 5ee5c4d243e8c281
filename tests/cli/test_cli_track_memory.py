"""cblrs track keeps the blocks numpy frees for reuse (glibc's malloc): no page faults again."""

from __future__ import annotations

import platform
import subprocess
import sys

import pytest

# In a fresh process: a 16 MiB array made, freed and made again; the minor page faults of the
# second one. glibc maps the first from the system and unmaps it when freed (blocks of 128 KiB
# or more), so the second faults its pages in again (some 500 here: numpy asks for huge pages),
# unless cblrs track's setting keeps such blocks in the heap.
_SECOND_ALLOCATION_FAULTS = """
import resource, sys
import numpy as np
if sys.argv[1] == "set":
    from cblrs.cli.track import _reuse_freed_memory
    _reuse_freed_memory()
block = np.ones(1 << 21)
del block
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
block = np.ones(1 << 21)
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def second_allocation_faults(setting: str) -> int:
    done = subprocess.run([sys.executable, "-c", _SECOND_ALLOCATION_FAULTS, setting],
                          capture_output=True, text=True, check=True, timeout=120)
    return int(done.stdout)


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's malloc only")
def test_freed_blocks_are_reused_without_page_faults() -> None:
    default = second_allocation_faults("default")
    assert default >= 100
    assert second_allocation_faults("set") < default / 10
