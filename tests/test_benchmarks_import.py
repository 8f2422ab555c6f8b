"""Every script in ``benchmarks/`` and ``benchmarks/experiments/`` imports against the
current package (its module level runs; ``main`` does not): a renamed or removed function
breaks this test, not a user's benchmark run weeks later."""
import json
import runpy
import subprocess
import sys
from pathlib import Path

import pytest

_BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
SCRIPTS = sorted([*_BENCHMARKS.glob("*.py"), *(_BENCHMARKS / "experiments").glob("*.py")])


@pytest.mark.parametrize("path", SCRIPTS, ids=[p.name for p in SCRIPTS])
def test_benchmark_script_imports(path):
    ns = runpy.run_path(str(path), run_name="benchmark_import_check")
    assert callable(ns.get("main")), f"{path.name} has no main()"


def test_layer_benchmark_runs_and_matches_a_baseline_of_the_same_source(tmp_path):
    """``benchmarks/layers.py`` end to end on a 6 x 6 mesh, every layer, with this very
    source as ``--baseline``: the same weights through the same code give the same
    outputs (max abs diff exactly 0), and every row has a time."""
    root = Path(__file__).resolve().parents[1]
    layers = ["sat", "gt", "gt_edge", "structure_aware", "gat"]
    subprocess.run([sys.executable, str(root / "benchmarks" / "layers.py"), "--nx", "6",
                    "--reps", "1", "--warmup", "0", "--threads", "1", "--edge-dims", "4",
                    "--layers", *layers, "--baseline", str(root / "src"), "--out",
                    str(tmp_path)], check=True, capture_output=True, timeout=300)
    rows = json.loads((tmp_path / "layers.json").read_text())["rows"]
    names = {r["layer"] for r in rows}
    assert names >= set(layers) | {f"{n}@base" for n in layers} | {"TransformerConv"}
    assert all(r["fwd_ms"] > 0 and r["fwd_bwd_ms"] > 0 for r in rows)
    diffs = [r["max_abs_diff"] for r in rows if r["layer"].endswith("@base")]
    assert len(diffs) == sum(r["layer"] in layers for r in rows)  # one per layer row
    assert diffs and all(d == 0.0 for d in diffs)


def test_resolution_datasets_hold_the_same_sequences_at_each_resolution():
    """``benchmarks/resolution.py``: at every resolution the same 8 (garment, body,
    motion) items, all in the test split, paired across resolutions by their parts."""
    ns = runpy.run_path(str(_BENCHMARKS / "resolution.py"), run_name="check")
    parts = {}
    for r in ns["RESOLUTIONS"]:
        items = ns["spec"](r).items()
        assert len(items) == 8 and {i["split"] for i in items} == {"test"}
        assert {i["garment"]["resolution"] for i in items} == {r}
        parts[r] = sorted(ns["_parts"](i["id"]) for i in items)
        assert len(set(parts[r])) == 8
    assert len({tuple(p) for p in parts.values()}) == 1
