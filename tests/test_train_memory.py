"""benchmarks/train_memory.py: the RSS it reads, its arguments."""
import runpy
import sys
from pathlib import Path

import psutil
import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "train_memory.py"


@pytest.fixture(scope="module")
def script():
    return runpy.run_path(str(SCRIPT), run_name="train_memory_check")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/self/status")
def test_rss_matches_psutil(script):
    """VmRSS of /proc/self/status against psutil's resident set size (the oracle)."""
    ours = script["rss_mb"]()
    theirs = psutil.Process().memory_info().rss / 2 ** 20
    assert abs(ours - theirs) < 0.05 * theirs


@pytest.mark.parametrize("flag", ["--steps", "--every"])
def test_rejects_a_count_below_one(script, flag, tmp_path):
    with pytest.raises(SystemExit, match="must be >= 1"):
        script["main"](["--data", str(tmp_path), flag, "0", "--out", str(tmp_path)])
