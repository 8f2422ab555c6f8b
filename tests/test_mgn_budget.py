"""``benchmarks/mgn_budget.py``: a run's validations read from its CSV log, and the trend
of E_dist / LBS against log10(garment-frames) checked against lines worked out by hand."""
import math
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import mgn_budget  # noqa: E402

HEADER = ("epoch,step,train/loss_epoch,train/loss_step,val/E_curv,val/E_dist,val/E_len,"
          "val/collision\n")


def test_validations_are_read_in_step_order_and_a_resumed_step_keeps_its_last_row(tmp_path):
    log = tmp_path / "metrics.csv"
    log.write_text(HEADER + "0,24,,0.5,,,,\n"
                   "2,2499,,,0.05,6.5,6.7,0.006\n"
                   "5,4999,,,0.04,5.6,5.6,0.006\n"
                   "4,2499,,,0.03,6.4,6.6,0.005\n"  # the step again, from a resumed piece
                   "5,5000,,0.3,,,,\n")
    rows = mgn_budget.read_validations(log)
    assert [r["step"] for r in rows] == [2500, 5000]
    assert rows[0] == {"step": 2500, "E_dist": 6.4, "E_len": 6.6, "E_curv": 0.03,
                       "collision": 0.005}
    log.write_text(HEADER + "0,24,,0.5,,,,\n")
    with pytest.raises(ValueError, match="--log"):
        mgn_budget.read_validations(log)


def test_the_trend_crosses_each_target_where_the_line_does():
    # ratio = 1.5 - 0.2 log10(F): 0.85 at F = 10^3.25, 0.75 at 10^3.75, 0.5 at 10^5;
    # 0.95 at 10^2.75, before the first point (F = 10^3, ratio 0.9)
    pts = [{"frames": f, "ratio": 1.5 - 0.2 * math.log10(f)} for f in (1e3, 2e3, 4e3)]
    fit = mgn_budget.trend(pts, [0.95, 0.85, 0.75, 0.5])
    assert fit["slope_per_decade"] == pytest.approx(-0.2)
    assert fit["intercept"] == pytest.approx(1.5)
    # a target the points already passed is reached at the first of them
    assert fit["frames_to_target"]["0.95"] == 1e3
    assert fit["frames_to_target"]["0.85"] == pytest.approx(10 ** 3.25)
    assert fit["frames_to_target"]["0.75"] == pytest.approx(10 ** 3.75)
    assert fit["frames_to_target"]["0.5"] == pytest.approx(1e5)
    # least squares through points off the line: the slope of the fitted line
    noisy = [{"frames": 10.0, "ratio": 1.0}, {"frames": 100.0, "ratio": 0.8},
             {"frames": 1000.0, "ratio": 0.7}]
    assert mgn_budget.trend(noisy, [0.5])["slope_per_decade"] == pytest.approx(-0.15)


def test_a_flat_or_rising_trend_never_reaches_a_target():
    flat = [{"frames": f, "ratio": 0.83} for f in (1e5, 2e5)]
    rising = [{"frames": 1e5, "ratio": 0.8}, {"frames": 2e5, "ratio": 0.82}]
    assert mgn_budget.trend(flat, [0.75])["frames_to_target"] == {"0.75": None}
    assert mgn_budget.trend(rising, [0.75])["frames_to_target"] == {"0.75": None}
    with pytest.raises(ValueError, match="--last"):
        mgn_budget.trend(flat[:1], [0.75])


def test_bad_input_is_one_error_line_naming_the_flag(tmp_path, capsys):
    log = tmp_path / "metrics.csv"
    log.write_text(HEADER + "0,24,,0.5,,,,\n")
    base = ["--ckpt", str(tmp_path / "none.ckpt"), "--data", str(tmp_path),
            "--out", str(tmp_path / "o")]
    for argv, words in ((["--log", str(log)], ["error: --log", "no val/E_dist row"]),
                        (["--log", str(tmp_path / "none.csv")], ["error: --log", "none.csv"])):
        with pytest.raises(SystemExit) as e:
            mgn_budget.main(argv + base)
        assert all(w in str(e.value.code) for w in words), e.value.code
    log.write_text(HEADER + "2,2499,,,0.05,6.5,6.7,0.006\n")
    with pytest.raises(SystemExit) as e:
        mgn_budget.main(["--log", str(log)] + base)
    assert str(e.value.code).startswith(f"error: --ckpt {tmp_path / 'none.ckpt'}")
    with pytest.raises(SystemExit):
        mgn_budget.main(["--log", str(log), "--last", "1"] + base)
    assert "--last: a trend needs two" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
