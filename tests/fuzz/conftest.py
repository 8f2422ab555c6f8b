"""Fuzz suite settings: ``GARMENTGNN_FUZZ_EXAMPLES`` examples per test (default 25,
derandomized); ``GARMENTGNN_FUZZ_RANDOM=1`` draws new cases each run;
``GARMENTGNN_FUZZ_REPORT=path.json`` writes the outcome counts per target."""
import json
import os

from _fuzz import TALLY


def pytest_sessionfinish():
    path = os.environ.get("GARMENTGNN_FUZZ_REPORT")
    if not path or not TALLY:
        return
    out = {}
    for (target, kind), n in sorted(TALLY.items()):
        out.setdefault(target, {"result": 0, "clear error": 0})[kind] += n
    with open(path, "w") as f:
        json.dump(out, f, indent=1, sort_keys=True)
