"""Files written whole or not at all: the ground floor every writer of the package
(datasets, the bench's records and report, the viewer page, the benchmarks' results)
stands on.

Each file is written to a temporary name in its folder (``.<name>.tmp-<pid>``),
flushed, fsynced and moved into place with :func:`os.replace`, so a reader or a resumed
run never sees a half-written file; :func:`remove_stale_temporaries` deletes what an
interrupted run left.  Nothing of the package is imported here.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Union

PathLike = Union[str, os.PathLike]


def _tmp_name(path: Path) -> Path:
    return path.with_name(f".{path.name}.tmp-{os.getpid()}")


def atomic_write_bytes(path: PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` via a temporary file + ``os.replace``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp_name(path)
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def atomic_write_json(path: PathLike, obj: Any) -> Path:
    """``obj`` as indented JSON with sorted keys (:func:`atomic_write_bytes`)."""
    return atomic_write_bytes(path, (json.dumps(obj, indent=1, sort_keys=True) + "\n").encode())


def remove_stale_temporaries(folder: PathLike) -> int:
    """Delete leftovers ``.<name>.tmp-<pid>`` of an interrupted run; returns how many."""
    n = 0
    folder = Path(folder)
    if folder.is_dir():
        for p in folder.glob(".*.tmp-*"):
            p.unlink(missing_ok=True)
            n += 1
    return n


__all__ = ["PathLike", "atomic_write_bytes", "atomic_write_json", "remove_stale_temporaries"]
