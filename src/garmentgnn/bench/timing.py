"""Run-time and memory measurement helpers.

What is measured (and what is not):

* **Latency** (:func:`measure`): wall-clock ``time.perf_counter`` around one call of a
  function, after ``warmup`` untimed calls; the median of ``repeats`` timed calls is
  reported (plus min/max).  CPU only here: no device synchronisation is done, so do not
  use it for asynchronous GPU work without adding one.  The torch intra-op thread count
  in effect (``torch.get_num_threads()``) is recorded with every measurement; use
  :func:`num_threads` to fix it.
* **Side by side** (:func:`side_by_side`): several functions timed *interleaved*
  (A B C A B C ...), so slow drifts of the machine (other processes, thermal state)
  affect all of them alike.
* **Throughput** (:func:`batch_sweep`): frames per second at each batch size
  (``batch / median seconds per call``); the best batch is the one with the highest
  rate.  Latency is reported at batch 1.
* **Peak memory** (:func:`peak_memory`): the increase of the process's resident set
  size during one call, ``peak RSS during the call - RSS before it``.  On Linux the
  kernel's peak counter (``VmHWM``) is reset through ``/proc/self/clear_refs`` before
  the call and read after it (exact, no overhead); elsewhere RSS is sampled every
  millisecond by a thread (``psutil``), which can miss spikes shorter than that.  RSS
  counts everything the process touches (torch, numpy/scipy, Python objects, allocator
  caches) but memory freed and re-used inside the call is counted once; memory
  allocated before the call (e.g. model weights) is not counted.  Before the call,
  ``gc.collect()`` and glibc's ``malloc_trim(0)`` return freed heap pages to the OS;
  without that, a call re-using memory an earlier call freed would read as ~0 MB.
  Allocator pools that ``malloc_trim`` cannot release may still hide some use, so
  read the number as a lower bound of the call's extra memory.
"""
from __future__ import annotations

import contextlib
import ctypes
import gc
import os
import statistics
import threading
import time
from typing import Any, Callable, Dict, Iterator, List, Mapping, Sequence

import psutil
import torch

MiB = float(1 << 20)


@contextlib.contextmanager
def num_threads(n: int) -> Iterator[int]:
    """Set ``torch.set_num_threads(n)`` inside the block, restoring the old value."""
    if not isinstance(n, int) or n < 1:
        raise ValueError(f"`n`: expected a positive int, got {n!r}")
    old = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield n
    finally:
        torch.set_num_threads(old)


def _check_counts(warmup: int, repeats: int) -> None:
    if not isinstance(warmup, int) or warmup < 0:
        raise ValueError(f"`warmup`: expected a non-negative int, got {warmup!r}")
    if not isinstance(repeats, int) or repeats < 1:
        raise ValueError(f"`repeats`: expected a positive int, got {repeats!r}")


def _summary(times: List[float], warmup: int) -> Dict[str, Any]:
    return {"median_ms": 1e3 * statistics.median(times), "min_ms": 1e3 * min(times),
            "max_ms": 1e3 * max(times), "repeats": len(times), "warmup": warmup,
            "threads": torch.get_num_threads()}


def measure(fn: Callable[[], Any], warmup: int = 2, repeats: int = 5) -> Dict[str, Any]:
    """Median wall time of ``fn()`` over ``repeats`` calls after ``warmup`` calls."""
    return side_by_side({"fn": fn}, warmup, repeats)["fn"]


def side_by_side(fns: Mapping[str, Callable[[], Any]], warmup: int = 2, repeats: int = 5
                 ) -> Dict[str, Dict[str, Any]]:
    """Time several functions interleaved; ``{name: measure-style summary}``."""
    _check_counts(warmup, repeats)
    if not fns:
        raise ValueError("`fns`: nothing to time")
    with torch.inference_mode():
        for _ in range(warmup):
            for fn in fns.values():
                fn()
        times: Dict[str, List[float]] = {k: [] for k in fns}
        for _ in range(repeats):
            for k, fn in fns.items():
                t0 = time.perf_counter()
                fn()
                times[k].append(time.perf_counter() - t0)
    return {k: _summary(v, warmup) for k, v in times.items()}


def batch_sweep(make_fn: Callable[[int], Callable[[], Any]], batches: Sequence[int],
                warmup: int = 2, repeats: int = 5) -> Dict[str, Any]:
    """Latency at batch 1 and throughput over ``batches``.

    Args:
        make_fn: ``make_fn(b)`` returns a function predicting ``b`` frames per call
            (inputs prepared outside the timed call).
        batches: batch sizes to try; must include 1.

    Returns:
        ``{"latency_ms", "throughput_fps", "best_batch", "threads", "sweep": [{batch,
        median_ms, fps}, ...]}``.
    """
    batches = sorted(set(int(b) for b in batches))
    if not batches or batches[0] != 1:
        raise ValueError(f"`batches`: must contain 1 and only positive sizes, got {batches}")
    sweep = []
    for b in batches:
        m = measure(make_fn(b), warmup, repeats)
        sweep.append({"batch": b, "median_ms": m["median_ms"], "fps": b * 1e3 / m["median_ms"]})
    best = max(sweep, key=lambda r: r["fps"])
    return {"latency_ms": sweep[0]["median_ms"], "throughput_fps": best["fps"],
            "best_batch": best["batch"], "threads": torch.get_num_threads(), "sweep": sweep,
            "repeats": repeats, "warmup": warmup}


# --------------------------------------------------------------------------- memory
def status_kb(field: str) -> int:
    """A ``kB`` field of ``/proc/self/status`` (``VmRSS``, ``VmHWM``; Linux)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    raise OSError(f"{field} not in /proc/self/status")


def _hwm_resettable() -> bool:
    try:
        status_kb("VmHWM")
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _release_free_memory() -> bool:
    """``gc.collect()`` and glibc ``malloc_trim(0)``: hand freed heap pages back to the
    OS so that re-using them inside the measured call shows up in RSS.  ``False`` where
    there is no glibc."""
    gc.collect()
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.malloc_trim(0)
        return True
    except (OSError, AttributeError):
        return False


def peak_memory(fn: Callable[[], Any]) -> Dict[str, Any]:
    """Run ``fn()`` once; returns ``{"result", "peak_mb", "method"}`` (see module doc)."""
    trimmed = _release_free_memory()
    if _hwm_resettable():
        before = status_kb("VmRSS")
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")  # VmHWM := current RSS
        result = fn()
        peak = status_kb("VmHWM")
        return {"result": result, "peak_mb": max(0, peak - before) * 1024 / MiB,
                "method": "linux VmHWM delta" + (" after malloc_trim" if trimmed else "")}

    proc = psutil.Process(os.getpid())
    before = proc.memory_info().rss
    peak = [before]
    stop = threading.Event()

    def sample() -> None:
        while not stop.is_set():
            peak[0] = max(peak[0], proc.memory_info().rss)
            time.sleep(1e-3)

    th = threading.Thread(target=sample, daemon=True)
    th.start()
    try:
        result = fn()
    finally:
        stop.set()
        th.join()
    peak[0] = max(peak[0], proc.memory_info().rss)
    return {"result": result, "peak_mb": max(0, peak[0] - before) / MiB,
            "method": "psutil RSS sampled at 1 kHz, delta" + (" after malloc_trim" if trimmed
                                                                  else "")}


def synchronised(fn: Callable[[], Any], device: str) -> Callable[[], Any]:
    """``fn`` followed by a wait for the device's queued work (a no-op on the CPU)."""
    if device == "cpu":
        return fn

    def call():
        out = fn()
        torch.cuda.synchronize()
        return out
    return call


def device_peak_memory(fn: Callable[[], Any], device: str) -> Dict[str, Any]:
    """:func:`peak_memory` on the CPU; on a GPU the allocator's peak during one call of
    ``fn`` over what was allocated before it."""
    if device == "cpu":
        return peak_memory(fn)
    torch.cuda.synchronize()
    torch.cuda.reset_peak_memory_stats()
    before = torch.cuda.memory_allocated()
    synchronised(fn, device)()
    return {"peak_mb": (torch.cuda.max_memory_allocated() - before) / 2 ** 20}
