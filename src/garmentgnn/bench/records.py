"""What every bench record kind shares: where it lives in ``OUT/records``, how it is read
back (also while other shards write theirs), the fields of a failed record and the start
of its report section."""
from __future__ import annotations

import json
import time
import traceback
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

from garmentgnn.bench.tables import slug

__all__ = ["NOT_RUN", "STATUSES", "collect", "failure", "json_safe", "load_record",
           "record_path", "section"]

#: a record's ``status``
STATUSES = ("ok", "failed")

#: a report section's text when the preset ran none of its records
NOT_RUN = "Not run in this preset."


def failure(err: BaseException, limit: int = 4) -> Dict[str, str]:
    """``status``, ``message`` and ``traceback`` (``limit`` frames) of a record whose run
    raised ``err``; call it in the ``except`` block (a crash is a result of the bench, not
    an error of it)."""
    return {"status": "failed", "message": f"{type(err).__name__}: {err}",
            "traceback": traceback.format_exc(limit=limit)}


def section(records: Sequence[Dict[str, Any]], kind: str,
            title: str) -> Tuple[List[Dict[str, Any]], List[str]]:
    """The records of ``kind`` and the first lines of their report section: the heading
    ``## title`` and, when there are none, :data:`NOT_RUN`."""
    recs = [r for r in records if r["kind"] == kind]
    lines = [f"## {title}", ""]
    if not recs:
        lines += [NOT_RUN, ""]
    return recs, lines


def record_path(out: Path, kind: str, method: str, case: str, seed: int) -> Path:
    return Path(out) / "records" / f"{kind}--{slug(case)}--{slug(method)}--s{seed}.json"


def load_record(path: Path, kind: str, method: str, case: str, seed: int
                ) -> Optional[Dict[str, Any]]:
    """The record at ``path`` if it is complete and is the one asked for, else ``None``."""
    try:
        rec = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(rec, dict) or rec.get("status") not in STATUSES:
        return None
    if (rec.get("kind"), rec.get("method"), rec.get("case"), rec.get("seed")) != \
            (kind, method, case, seed):
        return None
    return rec


def collect(out: Path, todo, records: Dict[Tuple[str, str, str, int], Dict[str, Any]],
            wait: bool = False, poll_seconds: float = 30.0, who: str = "") -> bool:
    """Add to ``records`` the records of the tasks ``todo`` (``(kind, method, item,
    seed)``) found under ``out``, written by this process or another; with ``wait``, poll
    every ``poll_seconds`` until all are there.  Whether all are."""
    while True:
        missing = []
        for kind, method, item, seed in todo:
            key = (kind, method, item["name"], seed)
            if key not in records:
                rec = load_record(record_path(out, *key), *key)
                if rec is None:
                    missing.append(key)
                else:
                    records[key] = rec
        if not missing or not wait:
            return not missing
        print(f"{who}: waiting for {len(missing)} record(s) of other shards, e.g. "
              f"{missing[0]}", flush=True)
        time.sleep(poll_seconds)


def json_safe(obj: Any) -> Any:
    """Tuples to lists, non-finite floats to ``None``, anything else JSON cannot hold to
    ``str``."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, float):
        return obj if obj == obj and obj not in (float("inf"), float("-inf")) else None
    if isinstance(obj, (str, int, bool)) or obj is None:
        return obj
    return str(obj)
