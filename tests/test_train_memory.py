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


@pytest.mark.parametrize("argv, words", [
    (["--steps", "0"], "argument --steps: expected an integer >= 1, got 0"),
    (["--every", "0"], "argument --every: expected an integer >= 1, got 0"),
    (["--threads", "0"], "argument --threads: expected an integer >= 1, got 0"),
    (["--steps", "10", "--every", "50"], "--every 50: more than --steps 10"),
])
def test_rejects_counts_out_of_range(script, argv, words, tmp_path, capsys,
                                     monkeypatch):
    (tmp_path / "manifest.json").write_text('{"items": []}')  # a dataset folder

    def ran(*args):
        raise AssertionError("trained with these arguments")

    monkeypatch.setitem(script["main"].__globals__, "output_path", ran)
    with pytest.raises(SystemExit) as e:
        script["main"](["--data", str(tmp_path), "--out", str(tmp_path)] + argv)
    assert e.value.code == 2 and words in capsys.readouterr().err.splitlines()[-1]


def test_rejects_a_missing_dataset(script, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        script["main"](["--data", str(tmp_path / "typo"), "--out", str(tmp_path)])
    err = capsys.readouterr().err.splitlines()[-1]
    assert e.value.code == 2 and f"argument --data: {tmp_path / 'typo'}" in err
    assert "garmentgnn generate" in err
