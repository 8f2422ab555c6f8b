"""What every bench record kind shares: the fields of a failed record and the start of
its report section."""
from __future__ import annotations

import traceback
from typing import Any, Dict, List, Sequence, Tuple

__all__ = ["NOT_RUN", "failure", "section"]

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
