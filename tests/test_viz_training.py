"""Training curves at the end of ``garmentgnn train``: the PNG, and the recorded values
against the CSVLogger's own ``metrics.csv``."""
import math

import pytest

from garmentgnn.training.lightning_cli import main as train_main
from garmentgnn.training.plots import (TrainingPlots, plot_training_curves,
                                       read_metrics_csv)
from test_training import root  # noqa: F401  (the module-scoped toy dataset fixture)
from test_training_cli import CONFIGS, fast_args


def test_train_writes_curves_matching_the_csv_logger(root, tmp_path):  # noqa: F811
    args = ["fit", "--config", str(CONFIGS / "gartrans.yaml")] + fast_args(root, tmp_path)
    cli = train_main(args)
    plots = [c for c in cli.trainer.callbacks if isinstance(c, TrainingPlots)]
    assert len(plots) == 1
    png = plots[0].path
    assert png is not None and png.name == "training_curves.png" and png.stat().st_size > 10_000
    assert tmp_path in png.parents  # the run's log folder
    csv_rows = read_metrics_csv(next(tmp_path.rglob("metrics.csv")))
    assert [r["epoch"] for r in csv_rows] == [0]
    hist = plots[0].history
    assert [r["epoch"] for r in hist] == [0]
    for mine, logged in zip(hist, csv_rows):
        keys = {k for k in logged if k.startswith(("train/", "val/"))}
        assert {"train/loss", "val/E_dist"} <= keys and keys <= set(mine)
        for k in keys:
            assert math.isclose(mine[k], logged[k], rel_tol=1e-5, abs_tol=1e-7), k


def test_plot_training_curves_input(tmp_path):
    assert plot_training_curves([{"epoch": 0}], tmp_path / "x.png") is None
    hist = [{"epoch": e, "train/loss": 1.0 / (e + 1), "train/vert": 0.5 / (e + 1),
             "val/E_dist": 3.0 - e, "val/E_len": float("nan") if e == 1 else 2.0}
            for e in range(3)]
    p = plot_training_curves(hist, tmp_path / "sub" / "c.png", title="t")
    assert p.is_file() and p.stat().st_size > 5_000


def test_callback_state_round_trips():
    cb = TrainingPlots()
    cb.history = [{"epoch": 0, "train/loss": 1.0}]
    other = TrainingPlots()
    other.load_state_dict(cb.state_dict())
    assert other.history == cb.history
    assert "TrainingPlots" in repr(other)


if __name__ == "__main__":  # pragma: no cover
    pytest.main([__file__, "-q"])
