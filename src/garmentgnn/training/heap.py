"""Freed memory kept for the next training step on the CPU (glibc's ``malloc``).

A GarTrans step allocates tens of megabytes of large temporaries (attention rows,
per-edge values, their gradients).  glibc serves a block above its mmap threshold (128
KiB, rising to the largest block freed so far) with fresh pages from the kernel and
gives them back when it is freed, so every step faults those pages in again: 10,000 to
15,000 page faults a step at batch 4 (``getrusage``), each a trap and a page of zeros.
:func:`keep_freed_memory` raises the mmap threshold to glibc's largest (32 MiB on 64-bit
systems) and the heap's trim threshold to 1 GiB, so freed blocks stay in the heap and the
next step reuses them: 1,400 to 1,700 faults a step.  The price: the process keeps the
step's peak memory instead of returning it between steps.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import sys

from lightning.pytorch import Callback, LightningModule, Trainer

#: ``mallopt`` parameters (``<malloc.h>``)
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
#: the largest mmap threshold glibc accepts on 64-bit systems, and the trim threshold set
MMAP_THRESHOLD, TRIM_THRESHOLD = 32 * 2 ** 20, 2 ** 30


def keep_freed_memory() -> bool:
    """Make glibc keep freed blocks up to 32 MiB in the heap (``mallopt``): ``True`` when
    set, ``False`` where the C library has no ``mallopt`` (not glibc: nothing changes)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) \
        and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))


class KeepFreedMemory(Callback):
    """:func:`keep_freed_memory` in every process that fits (each DDP replica too)."""

    def setup(self, trainer: Trainer, pl_module: LightningModule, stage: str) -> None:
        if stage == "fit":
            keep_freed_memory()
