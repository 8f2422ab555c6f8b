"""Training curves at the end of ``garmentgnn train``: the PNG, the recorded values
against the CSVLogger's own ``metrics.csv``, and the TensorBoard log read back with
TensorBoard's own reader."""
import math
from pathlib import Path

import pytest
from lightning.pytorch.loggers import TensorBoardLogger
from matplotlib.figure import Figure

from garmentgnn.training.lightning_cli import main as train_main
from garmentgnn.training.plots import (TrainingPlots, plot_training_curves,
                                       read_metrics_csv)

from test_training import root  # noqa: F401  (the module-scoped toy dataset fixture)
from test_training_cli import RECIPES, fast_args


def _tensorboard_scalars(folder):
    """{tag: [(step, value)]} of the event files in ``folder``, read by TensorBoard."""
    # optional: tensorboard comes with the viz extra
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator  # noqa: PLC0415
    acc = EventAccumulator(str(folder), size_guidance={"scalars": 0})
    acc.Reload()
    return {tag: [(e.step, e.value) for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}


def test_train_writes_curves_matching_the_csv_logger(root, tmp_path):  # noqa: F811
    pytest.importorskip("tensorboard", reason="make install installs tensorboard")
    args = ["fit", "--config", str(RECIPES / "gartrans.yaml")] + fast_args(root, tmp_path)
    args[args.index("--trainer.max_epochs") + 1] = "2"
    cli = train_main(args)
    plots = [c for c in cli.trainer.callbacks if isinstance(c, TrainingPlots)]
    assert len(plots) == 1
    png = plots[0].path
    assert png is not None and png.name == "training_curves.png" and png.stat().st_size > 10_000
    assert tmp_path in png.parents  # the run's log folder
    csv_rows = read_metrics_csv(next(tmp_path.rglob("metrics.csv")))
    assert [r["epoch"] for r in csv_rows] == [0, 1]
    hist = plots[0].history
    assert [r["epoch"] for r in hist] == [0, 1]
    for mine, logged in zip(hist, csv_rows):
        keys = {k for k in logged if k.startswith(("train/", "val/"))}
        assert {"train/loss", "val/E_dist"} <= keys and keys <= set(mine)
        for k in keys:
            assert math.isclose(mine[k], logged[k], rel_tol=1e-5, abs_tol=1e-7), k

    # TensorBoard: the same per-epoch values, in the CSV log's run folder
    tb = [lg for lg in cli.trainer.loggers if isinstance(lg, TensorBoardLogger)]
    assert len(tb) == 1 and png.parent / "tensorboard" == Path(tb[0].log_dir)
    assert list(Path(tb[0].log_dir).glob("events.out.tfevents.*"))
    scalars = _tensorboard_scalars(tb[0].log_dir)
    # per epoch: the tag's last value before the next epoch's ("epoch" is logged at each step)
    epoch_at = sorted(scalars["epoch"])
    terms = {k for k in hist[0] if k.startswith("train/") and k != "train/loss"}
    assert terms, hist[0]  # the loss terms, not only the total
    val = {k for k in hist[0] if k.startswith("val/")}
    assert {"val/E_dist", "val/E_len"} <= val
    for k in {"train/loss"} | terms | val:
        tag = k + "_epoch" if k + "_epoch" in scalars else k
        got = {int(dict(epoch_at).get(step, -1)): v for step, v in scalars[tag]}
        assert sorted(got) == [0, 1], (k, scalars[tag], epoch_at)
        for row in hist:
            assert math.isclose(got[row["epoch"]], row[k], rel_tol=1e-5, abs_tol=1e-7), k


def test_plot_training_curves_input(tmp_path):
    assert plot_training_curves([{"epoch": 0}], tmp_path / "x.png") is None
    hist = [{"epoch": e, "train/loss": 1.0 / (e + 1), "train/vert": 0.5 / (e + 1),
             "val/E_dist": 3.0 - e, "val/E_len": float("nan") if e == 1 else 2.0}
            for e in range(3)]
    p = plot_training_curves(hist, tmp_path / "sub" / "c.png", title="t")
    assert p.is_file() and p.stat().st_size > 5_000


@pytest.mark.parametrize("epochs", [2, 3, 7])
def test_short_run_epoch_ticks_are_integers(tmp_path, monkeypatch, epochs):
    """A run of a few epochs: every epoch tick shown is a whole number (matplotlib's
    default locator puts 0.25 steps between two epochs)."""
    saved = []
    orig = Figure.savefig
    monkeypatch.setattr(Figure, "savefig", lambda fig, *a, **k: (saved.append(fig),
                                                                  orig(fig, *a, **k)))
    hist = [{"epoch": e, "train/loss": 1.0 / (e + 1), "val/E_dist": 3.0 - 0.1 * e}
            for e in range(epochs)]
    plot_training_curves(hist, tmp_path / "c.png")
    axes = [ax for ax in saved[0].axes if ax.get_visible()]
    assert len(axes) == 2
    for ax in axes:
        lo, hi = ax.get_xlim()
        ticks = [t for t in ax.get_xticks() if lo <= t <= hi]
        assert len(ticks) >= 2 and all(float(t).is_integer() for t in ticks), ticks


def test_callback_state_round_trips():
    cb = TrainingPlots()
    cb.history = [{"epoch": 0, "train/loss": 1.0}]
    other = TrainingPlots()
    other.load_state_dict(cb.state_dict())
    assert other.history == cb.history
    assert "TrainingPlots" in repr(other)


if __name__ == "__main__":  # pragma: no cover
    pytest.main([__file__, "-q"])
