"""Freed memory kept for the next training step (glibc ``mallopt``).  Oracle: the
kernel's count of minor page faults (``getrusage``) of a fresh process that allocates,
writes and frees three 8 MiB blocks in a loop, as a training step does."""
import subprocess
import sys

import pytest

SCRIPT = """
import resource, sys
import torch
from garmentgnn.training import keep_freed_memory
from garmentgnn.training.heap import M_MMAP_THRESHOLD
if sys.argv[1] == "keep":
    kept = keep_freed_memory()
else:  # glibc's starting threshold, pinned (its dynamic rise depends on the past)
    import ctypes
    kept = ctypes.CDLL("libc.so.6").mallopt(M_MMAP_THRESHOLD, 128 * 1024)
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
def step():  # three 8 MiB temporaries alive at once, then freed
    blocks = [torch.empty(2 ** 21).fill_(1.0) for _ in range(3)]
    del blocks
for _ in range(3):
    step()
f0 = faults()
for _ in range(20):
    step()
print(kept, faults() - f0)
"""


def _faults(mode: str):
    out = subprocess.run([sys.executable, "-c", SCRIPT, mode], capture_output=True, text=True,
                         check=True).stdout.split()
    return out[0], int(out[1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_freed_blocks_are_reused_without_page_faults():
    """After ``keep_freed_memory`` the loop's blocks come back from the heap: (almost) no
    page faults, where glibc's starting mmap threshold (128 KiB) maps every block fresh
    and returns it on free (thousands)."""
    kept, with_keep = _faults("keep")
    _, default = _faults("default")
    assert kept == "True"
    assert default > 1000
    assert with_keep < default / 10

