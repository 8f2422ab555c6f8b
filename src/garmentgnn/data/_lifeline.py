"""Worker processes that die with their parent.

A pool worker started by :func:`garmentgnn.data.generate.generate` must not outlive
the process that started it: if the parent is killed with ``SIGKILL`` (no chance to
shut the pool down), orphaned workers would go on simulating and writing files.

:func:`watch_parent` (called in the worker initializer) does two things:

* on Linux, ``prctl(PR_SET_PDEATHSIG, SIGKILL)``: the kernel kills the worker the
  moment its parent exits;
* everywhere, a daemon thread polls ``os.getppid()`` and ends the worker with
  ``os._exit`` once the parent is gone (re-parented to init or a subreaper).

The workers stay in the parent's process group, so ``kill -- -PGID`` (or Ctrl-C in a
terminal) reaches the parent and every worker at once.
"""
from __future__ import annotations

import os
import threading
import time

from garmentgnn._process import set_pdeathsig


def watch_parent(parent_pid: int, interval: float = 0.5) -> None:
    """End this process when ``parent_pid`` (the process that started it) is gone."""
    if os.getppid() != parent_pid:  # the parent died before we got here
        os._exit(1)
    set_pdeathsig()

    def poll() -> None:
        while True:
            time.sleep(interval)
            if os.getppid() != parent_pid:
                os._exit(1)

    threading.Thread(target=poll, name="garmentgnn-parent-watch", daemon=True).start()

