"""Every script in ``benchmarks/`` imports against the current package (its module level
runs; ``main`` does not): a renamed or removed function breaks this test, not a user's
benchmark run weeks later."""
import runpy
from pathlib import Path

import pytest

SCRIPTS = sorted((Path(__file__).resolve().parents[1] / "benchmarks").glob("*.py"))


@pytest.mark.parametrize("path", SCRIPTS, ids=[p.name for p in SCRIPTS])
def test_benchmark_script_imports(path):
    ns = runpy.run_path(str(path), run_name="benchmark_import_check")
    assert callable(ns.get("main")), f"{path.name} has no main()"
