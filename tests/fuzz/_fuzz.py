"""Shared pieces of the fuzz suite: the hypothesis settings, the outcome classifier and
the tally written to ``$GARMENTGNN_FUZZ_REPORT`` (JSON, at exit).

``GARMENTGNN_FUZZ_EXAMPLES`` examples per test (default 25, derandomized);
``GARMENTGNN_FUZZ_RANDOM=1`` draws new cases on each run.  (No ``conftest.py`` here: a
second module named ``conftest`` would shadow ``tests/conftest.py`` for the test files
that import from it.)

Every fuzzed call must end in one of two ways: a result (checked against an oracle by
the test), or a *clear error*: ``ValueError`` / ``TypeError`` / ``FileNotFoundError``
(the project's own errors derive from these) whose message names the argument or the
file and is one short line.  Anything else -- ``IndexError``, ``KeyError``,
``zipfile.BadZipFile``, ``struct.error``, a ``UnicodeDecodeError`` or
``JSONDecodeError`` passed through with a library's message -- fails the test.
"""
from __future__ import annotations

import atexit
import json
import os
from collections import Counter
from typing import Any, Callable, Iterable, Optional

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

#: examples per fuzz test (``GARMENTGNN_FUZZ_EXAMPLES=500 pytest tests/fuzz`` for more)
EXAMPLES = int(os.environ.get("GARMENTGNN_FUZZ_EXAMPLES", "25"))
FUZZ = settings(max_examples=EXAMPLES, deadline=None, database=None,
                derandomize=os.environ.get("GARMENTGNN_FUZZ_RANDOM") != "1",
                suppress_health_check=list(HealthCheck))
#: (target, "result" | "clear error") -> count, over the whole test run
TALLY: Counter = Counter()
CLEAR = (ValueError, TypeError, FileNotFoundError)


def is_clear(msg: str, names: Iterable[str] = ()) -> bool:
    """A clear message: one line of at most 500 characters naming an argument
    (backquoted, ``--flag`` or ``settings.x``) or one of ``names`` (e.g. the path)."""
    first = msg.strip().splitlines()[0] if msg.strip() else ""
    if not first or len(first) > 500:
        return False
    return "`" in first or "--" in first or "settings." in first \
        or any(n and n in first for n in names)


def outcome(target: str, fn: Callable[..., Any], *args, names: Iterable[str] = (),
            **kwargs) -> Optional[Any]:
    """``fn(*args, **kwargs)``; ``None`` after a clear error (tallied), else the result.
    An unclear message fails here; any other exception type propagates (fails)."""
    try:
        out = fn(*args, **kwargs)
    except CLEAR as e:
        assert is_clear(str(e), names), f"{target}: unclear error {type(e).__name__}: {e}"
        TALLY[target, "clear error"] += 1
        return None
    TALLY[target, "result"] += 1
    return out


def mutations(data: bytes) -> st.SearchStrategy:
    """Corrupt versions of ``data``: truncated, a flipped bit, bytes inserted, bytes
    overwritten, emptied, or random bytes."""
    n = len(data)
    pos = st.integers(0, max(n - 1, 0))
    return st.one_of(
        st.builds(lambda k: data[:k], st.integers(0, max(n - 1, 0))),
        st.builds(lambda k, b: data[:k] + bytes([data[k] ^ (1 << b)]) + data[k + 1:],
                  pos, st.integers(0, 7)),
        st.builds(lambda k, ins: data[:k] + ins + data[k:], pos,
                  st.binary(min_size=1, max_size=16)),
        st.builds(lambda k, rep: data[:k] + rep + data[k + len(rep):], pos,
                  st.binary(min_size=1, max_size=16)),
        st.just(b""),
        st.binary(max_size=256),
    )


@atexit.register
def _write_report() -> None:
    path = os.environ.get("GARMENTGNN_FUZZ_REPORT")
    if not path or not TALLY:
        return
    out: dict = {}
    for (target, kind), n in sorted(TALLY.items()):
        out.setdefault(target, {"result": 0, "clear error": 0})[kind] += n
    with open(path, "w") as f:
        json.dump(out, f, indent=1, sort_keys=True)
