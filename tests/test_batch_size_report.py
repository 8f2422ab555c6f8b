"""``benchmarks/batch_size.py``: bench runs that differ in batch size compared at equal
epochs (interpolated on the curves, checked against hand-computed values) and at equal
wall time."""
import json
import runpy
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BS = runpy.run_path(str(ROOT / "benchmarks" / "batch_size.py"), run_name="batch_size_test")


def _record(batch, chunks, errs, test, lr=1.0):
    pts = [{"step": c // batch, "epoch": 0, "chunks": c, "seconds": 60.0 * i, "E_dist": e}
           for i, (c, e) in enumerate(zip(chunks, errs))]
    return {"kind": "learned", "method": "M", "seed": 0, "status": "ok",
            "steps": chunks[-1] // batch, "train_seconds": 60.0 * len(chunks),
            "config": {"batch_size": batch, "lr_factor": lr} if batch > 1 else {},
            "curve": {"points": pts, "lbs_E_dist": 5.0}, "metrics": {"E_dist": test[0]},
            "per_sequence": [{"sequence": f"s{i}", "metrics": {"E_dist": v}}
                             for i, v in enumerate(test[1])],
            "dataset": {"content_sha256": "abc", "root": "/nowhere"}}


def test_equal_epochs_are_interpolated_on_each_curve():
    one = _record(1, [0, 100, 200], [5.0, 4.0, 3.0], (3.1, [3.0, 3.2, 3.1]))
    big = _record(16, [0, 160, 320, 480], [5.0, 3.6, 3.0, 2.8], (2.9, [2.9, 3.0, 2.8]), 4.0)
    res = BS["compare"]([("b1", one), ("b16", big)], train_chunks=400)
    assert res["equal_epochs"] == pytest.approx(0.5)  # b1 reached 200 of 400 chunks
    r1, r16 = res["rows"]
    assert r1["val_equal_epochs"] == pytest.approx(3.0) and r1["p"] is None
    # 200 chunks: between 160 (3.6) and 320 (3.0), a quarter of the way
    assert r16["val_equal_epochs"] == pytest.approx(3.6 - 0.25 * 0.6)
    assert r16["val_end"] == 2.8 and r16["epochs"] == pytest.approx(1.2)
    assert (r16["batch_size"], r16["lr_factor"], r1["batch_size"]) == (16, 4.0, 1)
    assert 0 <= r16["p"] <= 1 and r16["minutes"] == pytest.approx(4.0)


def test_a_folder_without_results_is_one_error_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        BS["main"](["--run", f"a={tmp_path}", "--out", str(tmp_path / "x")])
    assert e.value.code == 2 and "LABEL=DIR" in capsys.readouterr().err
    (tmp_path / "results.json").write_text(json.dumps({"records": []}))
    with pytest.raises(SystemExit, match="no finished run"):
        BS["main"](["--run", f"a={tmp_path}", "--out", str(tmp_path / "x")])
