"""Ray, for the parts of garmentgnn that run on a cluster (``generate --backend ray``,
``bench --backend ray``, ``sweep``): importing it (an optional extra) and joining or
starting a cluster for the length of one run.

Without ``address`` a private local cluster of ``workers`` CPUs is started (and stopped
at the end; ``address="local"`` so that a ``ray start`` cluster on the same host is
never joined by accident); with ``address`` (``HOST:PORT`` of a ``ray start --head``)
the run joins that cluster, after checking that something listens there (Ray itself
retries an unreachable address for a minute).  Nothing of the package is imported here.
"""
from __future__ import annotations

import logging
import os
import socket
from contextlib import contextmanager
from typing import Iterator, Optional

__all__ = ["check_address", "cluster", "import_ray", "import_tune"]

#: the local cluster's object store: the tasks return records, checkpoints and a small
#: dataset, never arrays of a whole run
OBJECT_STORE_BYTES = 256 << 20


def import_ray(flag: str = "--backend ray"):
    """The ``ray`` module; ``RuntimeError`` saying how to install it where it is missing."""
    try:
        import ray  # noqa: PLC0415 (optional: the ray extra)
    except ImportError as e:
        raise RuntimeError(f"{flag} needs Ray: `pip install 'garmentgnn[ray]'` "
                           "(`make install` installs it)") from e
    return ray


def import_tune(flag: str = "sweep"):
    """The ``ray.tune`` module (the ray extra's ``ray[tune]``), as :func:`import_ray`."""
    import_ray(flag)
    try:
        from ray import tune  # noqa: PLC0415 (optional: the ray extra)
    except ImportError as e:
        raise RuntimeError(f"{flag} needs Ray Tune: `pip install 'garmentgnn[ray]'` "
                           "(`make install` installs it)") from e
    return tune


def check_address(address: str, timeout: float = 3.0) -> None:
    """``ValueError`` naming ``address`` when it is not ``HOST:PORT`` or nothing accepts a
    connection there within ``timeout`` seconds."""
    host, _, port = str(address).rpartition(":")
    if not host or not port.isdigit():
        raise ValueError(f"--address: expected HOST:PORT of a `ray start --head` (e.g. "
                         f"10.0.0.1:6379), got {address!r}")
    try:
        with socket.create_connection((host, int(port)), timeout=timeout):
            pass
    except OSError as err:
        raise ValueError(f"--address {address}: no Ray cluster answers there ({err}); start "
                         f"one with `ray start --head --port={port}` on {host}, or leave "
                         "--address out for a local cluster") from None


@contextmanager
def cluster(workers: Optional[int] = 1, address: Optional[str] = None,
            flag: str = "--backend ray") -> Iterator[object]:
    """Ray initialised in this process for the ``with`` block: joined at ``address``, or a
    private local cluster of ``workers`` CPUs (``None``: all of this machine's); shut down
    at its end.  Yields ``ray``."""
    ray = import_ray(flag)
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    if ray.is_initialized():
        raise RuntimeError("Ray is already initialised in this process; call ray.shutdown() "
                           "first, or pass its address as `address`")
    if address:
        check_address(address)
        ray.init(address=address, log_to_driver=False, logging_level=logging.WARNING)
    else:
        ray.init(address="local", num_cpus=None if workers is None else max(1, workers),
                 include_dashboard=False, log_to_driver=False, logging_level=logging.WARNING,
                 object_store_memory=OBJECT_STORE_BYTES, _node_ip_address="127.0.0.1")
    try:
        yield ray
    finally:
        ray.shutdown()
