"""``garmentgnn generate --backend ray``: one Ray task per sequence.

The driver (the process that runs :func:`garmentgnn.data.generate.generate`) keeps the
manifest: each task simulates one item with :func:`~garmentgnn.data.worker.run_item`,
writes its sequence file and returns its manifest record, which the driver writes as
soon as it arrives -- exactly as the local process pool does, so a Ray run gives the
same files as a local one, and a killed run resumes from the manifest the same way.

Without ``address`` a private local cluster of ``workers`` CPUs is started (and stopped
at the end); with ``address`` (``HOST:PORT`` of a ``ray start --head``) the run joins
that cluster (:func:`garmentgnn._ray.cluster`).  On several machines, ``out`` must be
storage that every node sees at the same path (docs/dataset.md).  Ray is an optional
dependency (``pip install garmentgnn[ray]``; ``make install`` installs it).
"""
from __future__ import annotations

from typing import Any, Callable, Dict, List, Optional

from garmentgnn._ray import cluster
from garmentgnn.data.worker import init_worker, run_item

_INITIALISED = False


def _task(item: Dict[str, Any], out: str, simulate_fn: Optional[Callable],
          settings_fn: Optional[Callable]) -> Dict[str, Any]:
    """A Ray task: one item, in a worker with one torch thread."""
    global _INITIALISED
    if not _INITIALISED:
        init_worker()
        _INITIALISED = True
    return run_item(item, out, simulate_fn, settings_fn)


def run_on_ray(todo: List[Dict[str, Any]], out: str, finish: Callable[[Dict[str, Any]], None],
               simulate_fn: Optional[Callable] = None, settings_fn: Optional[Callable] = None,
               workers: int = 1, address: Optional[str] = None, max_retries: int = 3) -> None:
    """Simulate ``todo`` as Ray tasks and call ``finish(record)`` for each as it ends.

    ``max_retries``: times Ray reruns a task whose worker process died (a simulation
    that fails is not retried: it comes back as a ``failed`` record)."""
    with cluster(workers, address) as ray:
        remote = ray.remote(num_cpus=1, max_retries=max_retries)(_task)
        pending = [remote.remote(it, out, simulate_fn, settings_fn) for it in todo]
        try:
            while pending:
                ready, pending = ray.wait(pending, num_returns=1)
                for ref in ready:
                    finish(ray.get(ref))
        except BaseException:
            for ref in pending:
                ray.cancel(ref, force=True)
            raise
