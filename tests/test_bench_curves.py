"""Learning curves and the equal-step snapshot of ``garmentgnn bench``
(:mod:`garmentgnn.bench.curves`).

Oracles: a fit stopped by ``max_steps`` at the snapshot's step (the snapshot must hold
exactly its weights); a validation that sleeps a known time (it must not count as
training time, nor against a :class:`TimeBudget`); for the bench flow, a snapshot taken
at the last step must score exactly like the final model."""
import dataclasses
import json
import time

import lightning as L
import pytest
import torch

from garmentgnn.bench import curves, runner, learned, methods, presets
from garmentgnn.training import GarTransModule, TimeBudget
from garmentgnn.training.evaluate import evaluate_split

from conftest import skirt_dataset



# --------------------------------------------------------------------------- plateau
def _pts(errors, every=10):
    return [{"step": i * every, "epoch": i, "seconds": float(i), "E_dist": e}
            for i, e in enumerate(errors)]


def test_plateau_reached_when_the_last_quarter_does_not_improve():
    flat = curves.plateau(_pts([9.0, 6.0, 5.0, 4.0, 3.9, 3.95, 3.92, 3.91, 3.93]))
    assert flat["reached"] and flat["best"] == 3.9 and flat["best_step"] == 40
    assert flat["best_epoch"] == 4 and flat["gain"] == pytest.approx((3.9 - 3.91) / 3.9)
    falling = curves.plateau(_pts([9.0, 8.0, 7.0, 6.0, 5.0, 4.0, 3.0, 2.0, 1.0]))
    # last quarter: steps > 60, best 1.0 against 3.0 before
    assert not falling["reached"] and falling["gain"] == pytest.approx(2.0 / 3.0)
    with pytest.raises(ValueError, match="points"):
        curves.plateau(_pts([3.0, 2.0, 1.0]))


def test_report_plateau_column_says_which_way_the_last_quarter_moved():
    """The plateau column names the direction: a run whose last quarter is worse than its
    earlier best reads "above" (it was once printed as "-2.9% better")."""
    def rec(errors, seed):
        return {"kind": "learned", "status": "ok", "method": "GarTrans (SAT)", "seed": seed,
                "epochs": 1, "steps": 80, "metrics": {"E_dist": 9.5},
                "curve": {"every": 10, "points": _pts(errors), "lbs_E_dist": 1.9},
                "equal_steps": {"step": 500, "reached": False}}
    text = "\n".join(curves.markdown([rec([9.0, 6.0, 5.0, 4.0, 3.9, 3.95, 3.92, 3.91, 4.29], 0),
                                      rec([9.0, 8.0, 7.0, 6.0, 5.0, 4.0, 3.0, 2.0, 1.0], 1)]))
    rows = [line for line in text.splitlines() if line.startswith("| GarTrans (SAT) |")]
    # seed 0: best of the last quarter 3.91 against 3.9 before; seed 1: 1.0 against 3.0
    assert "yes (the last 25%'s best is 0.3% above the best before it)" in rows[0]
    assert "not converged (the last 25%'s best is 66.7% below the best before it)" in rows[1]
    assert "better" not in text


def test_report_gives_the_fit_to_the_training_sequences_against_lbs():
    pts = _pts([6.0, 5.0, 4.8, 4.7])
    for p, e in zip(pts, [4.0, 3.0, 2.5, 2.0]):
        p["train_E_dist"] = e
    rec = {"kind": "learned", "status": "ok", "method": "GarTrans (SAT)", "seed": 0,
           "epochs": 1, "steps": 30, "metrics": {"E_dist": 9.5}, "config": {"batch_size": 16},
           "curve": {"every": 10, "points": pts, "lbs_E_dist": 6.0, "train_lbs_E_dist": 4.0}}
    text = "\n".join(curves.markdown([rec, dict(rec, seed=1, curve=dict(rec["curve"],
                                                                      train_lbs_E_dist=None))]))
    rows = [line for line in text.splitlines() if line.startswith("| GarTrans (SAT) |")]
    assert rows[0].endswith("| 2.000 (0.50x) |") and rows[1].endswith("| 2.000 |")
    assert "last on training sequences (cm, x LBS)" in text
    assert "every 10 optimizer steps of 16 chunks" in text


def test_report_when_no_method_reached_the_equal_step_snapshot():
    """Every run stopped by its time before the snapshot: the section names them and
    shows no equal-step table (this crashed the report once)."""
    rec = {"kind": "learned", "status": "ok", "method": "GarTrans (SAT)", "seed": 0,
           "epochs": 1, "steps": 40, "metrics": {"E_dist": 9.5},
           "curve": {"every": 20, "points": _pts([2.2, 2.1, 2.05], every=20), "lbs_E_dist": 1.9},
           "equal_steps": {"step": 500, "reached": False}}
    text = "\n".join(curves.markdown([rec]))
    assert "Stopped by the time budget before 500 steps" in text and "GarTrans (SAT)" in text
    assert "E_dist at 500 steps" not in text and "too few points" in text


def test_plot_marks_only_curves_that_leave_the_frame(tmp_path, monkeypatch):
    """The legend says "above the frame" for a curve whose top lies above the plotted
    error axis, and only then: a curve a little above 1.5x LBS still drawn inside the
    axis's margin was once marked so (read off the figure's own axis)."""
    got = {}
    monkeypatch.setattr(curves, "save_figure",
                        lambda fig, path: got.update(fig=fig) or path)

    def rec(method, errors):
        return {"kind": "learned", "status": "ok", "method": method, "seed": 0, "epochs": 1,
                "steps": 40, "metrics": {"E_dist": 9.5},
                "curve": {"every": 10, "points": _pts(errors), "lbs_E_dist": 2.0}}

    b = rec("B", [2.1, 3.02, 2.9])
    for p, e in zip(b["curve"]["points"], [2.0, 1.5, 1.0]):  # its training-sequence curve
        p["train_E_dist"] = e
    curves.plot([rec("A", [2.1, 2.2, 2.1]), b, rec("C", [2.1, 50.0, 70.0])], tmp_path / "c.png")
    fig = got["fig"]
    assert [a.get_xlabel() for a in fig.axes] == ["optimizer steps", "epochs of the training "
                                                  "split", "training wall time (min)"]
    for a in fig.axes:  # B's dashed training curve on every axis
        dashed = [ln for ln in a.get_lines() if ln.get_linestyle() == "--"
                  and list(ln.get_ydata()) == [2.0, 1.5, 1.0]]
        assert len(dashed) == 1
    ax = fig.axes[0]
    top = ax.get_ylim()[1]
    labels = dict(zip(["A", "B", "C"], ax.get_legend_handles_labels()[1]))
    assert "dashed: training sequences" in ax.get_legend_handles_labels()[1]
    assert 3.0 < 3.02 < top < 50.0  # 1.5x LBS plus the margin
    assert labels["A"] == "A" and labels["B"] == "B"
    assert labels["C"] == "C (up to 70 cm, above the frame)"


# --------------------------------------------------------------------------- callback
class _Line(L.LightningModule):
    """Least squares on a fixed random problem: deterministic, a few ms per step."""

    def __init__(self) -> None:
        super().__init__()
        self.lin = torch.nn.Linear(4, 1)

    def training_step(self, batch, batch_idx):
        x, y = batch
        return torch.nn.functional.mse_loss(self.lin(x), y)

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)


def _loader():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(64, 4, generator=g)
    y = x @ torch.tensor([[1.0], [-2.0], [0.5], [3.0]]) + 0.1
    return torch.utils.data.DataLoader(torch.utils.data.TensorDataset(x, y), batch_size=8)


def _fit(callbacks, **kw):
    torch.manual_seed(0)
    module = _Line()
    trainer = L.Trainer(accelerator="cpu", logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False,
                        callbacks=callbacks, **kw)
    trainer.fit(module, _loader())
    return module


def test_curve_points_snapshot_and_excluded_validation_time(tmp_path):
    pause = 0.05

    def evaluate(module):
        assert not module.training and not torch.is_grad_enabled()
        time.sleep(pause)
        return float(module.lin.weight.abs().sum())

    budget = TimeBudget(3600.0, anneal=False)
    curve = curves.LearningCurve(4, evaluate, snapshot_step=5, snapshot_path=tmp_path / "s.pt",
                                 budget=budget)
    t0 = time.perf_counter()
    module = _fit([budget, curve], max_epochs=2)  # 8 batches per epoch: 16 steps
    total = time.perf_counter() - t0
    assert [p["step"] for p in curve.points] == [0, 4, 8, 12, 16]
    assert [p["epoch"] for p in curve.points] == [0, 0, 0, 1, 1]
    assert [p["chunks"] for p in curve.points] == [0, 4, 8, 12, 16]  # a tuple batch: one
    last = float(module.lin.weight.detach().abs().sum())
    assert curve.points[-1]["E_dist"] == pytest.approx(last)
    # 5 validations of >= 50 ms each: counted apart, neither as training nor in the budget
    assert curve.eval_seconds >= 5 * pause
    assert curve.seconds + curve.eval_seconds <= total
    assert budget.spent < total - 5 * pause
    assert curve.seconds == pytest.approx(budget.spent, abs=0.05)
    # the snapshot holds the weights of a fit stopped after 5 steps
    snap = torch.load(tmp_path / "s.pt", weights_only=False)
    ref = _fit([], max_steps=5)
    assert snap["step"] == 5
    for k, v in ref.state_dict().items():
        assert torch.equal(snap["state_dict"][k], v), k
    assert not torch.equal(snap["state_dict"]["lin.weight"], module.lin.weight)


def test_curve_scores_the_training_sequences_beside_validation():
    """``train_evaluate``: each point's ``train_E_dist``, the model in eval mode as for
    validation; ``train_chunks`` kept for the epochs axis."""
    seen = []

    def fit_error(module):
        seen.append(module.training)
        return 2.0 * float(module.lin.bias.detach())

    curve = curves.LearningCurve(4, lambda m: float(m.lin.bias.detach()),
                                 train_evaluate=fit_error, train_chunks=32)
    _fit([curve], max_steps=8)
    assert [p["train_E_dist"] for p in curve.points] == \
        pytest.approx([2.0 * p["E_dist"] for p in curve.points])
    assert seen == [False] * 3 and curve.to_json()["train_chunks"] == 32
    rec = {"curve": curve.to_json()}
    assert curves._epochs(rec) == [0.0, 0.125, 0.25]  # 4 and 8 chunks of 32


def test_curve_state_round_trips_and_a_resumed_fit_adds_no_step_zero_point():
    curve = curves.LearningCurve(4, lambda m: 1.0)
    _fit([curve], max_steps=8)
    again = curves.LearningCurve(4, lambda m: 2.0)
    again.load_state_dict(json.loads(json.dumps(curve.state_dict())))
    assert again.points == curve.points and again.seconds == curve.seconds
    again.on_train_start(None, None)  # a resumed fit: its curve already has step 0
    assert len(again.points) == len(curve.points) == 3


def test_curve_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="every"):
        curves.LearningCurve(0, lambda m: 0.0)
    with pytest.raises(ValueError, match="snapshot_step"):
        curves.LearningCurve(2, lambda m: 0.0, snapshot_step=3)
    with pytest.raises(ValueError, match="snapshot_step"):
        curves.LearningCurve(2, lambda m: 0.0, snapshot_step=0, snapshot_path=tmp_path / "x")
    with pytest.raises(ValueError, match="curve_every"):
        methods.LearnedBudget(curve_every=0)
    with pytest.raises(ValueError, match="equal_steps"):
        methods.LearnedBudget(equal_steps=10)


def test_converge_preset():
    p = presets.preset("converge")
    b = p.learned
    assert p.dataset == "small" and b.minutes and b.curve_every and b.equal_steps
    assert set(b.methods) == set(methods.METHOD_NAMES) and b.seeds == 3


def test_learn_preset():
    """Every method, batched, on the `learn` dataset: its curve points and epochs count
    chunks, so they are whole steps of its batch."""
    b = presets.preset("learn").learned
    assert presets.preset("learn").dataset == "learn" and b.batch_size > 1
    assert set(b.methods) == set(methods.METHOD_NAMES) and b.seeds == 3
    assert b.curve_every % b.batch_size == 0 and b.epoch_chunks % b.batch_size == 0
    assert b.val_sequences and b.train_sequences and b.test_sequences and b.equal_steps


# --------------------------------------------------------------------------- the bench
@pytest.fixture(scope="module")
def data_with_val(tmp_path_factory):
    return skirt_dataset(tmp_path_factory.mktemp("data"), ["walk", "run", "arm_swing", "jump"], 4,
                         held_out={"test": ["arm_swing"], "val": ["jump"]}, name="mini")


@pytest.mark.slow
@pytest.mark.parametrize("batch", [1, 2])
def test_bench_records_curves_and_scores_the_equal_step_snapshot(data_with_val, tmp_path, batch):
    full, da = next(iter(methods.GARTRANS)), methods.DA
    p = presets.preset("tiny")
    steps = 4 // batch
    p = dataclasses.replace(
        p, cases=(), budgets=(), stability_cases=(), scaling_item=None, leaveout=False,
        precision_methods=(), long_item=None,
        # 2 train sequences of 4 frames: one chunk each, 2 // batch steps per epoch; a point
        # every `batch` chunks is a point every step
        learned=dataclasses.replace(p.learned, methods=(full, da, methods.LBS), epochs=2,
                                    stability_cases=(), curve_every=batch, equal_steps=steps,
                                    batch_size=batch, train_sequences=2))
    summary = runner.run(p, tmp_path, data=data_with_val, progress=False)
    recs = {r["method"]: r for r in json.loads((tmp_path / "results.json").read_text())["records"]
            if r["kind"] == learned.KIND}
    assert summary.failed == 0
    for m in (full, da):
        r = recs[m]
        assert r["steps"] == steps and r["device"] == "cpu"
        assert [q["step"] for q in r["curve"]["points"]] == list(range(steps + 1))
        assert [q["chunks"] for q in r["curve"]["points"]] == list(range(0, 5, batch))
        # the snapshot after the last step is the final model
        assert r["equal_steps"]["reached"] and r["equal_steps"]["step"] == steps
        assert r["equal_steps"]["metrics"]["E_dist"] == pytest.approx(r["metrics"]["E_dist"])
    assert "curve" not in recs[methods.LBS]
    # the last point and the LBS line scored by evaluate_split (its own loop) on `val`
    module = GarTransModule.load_from_checkpoint(recs[full]["checkpoint"], map_location="cpu")
    ref = evaluate_split(module, data_with_val, "val", modes=("gartrans", "lbs"), history=3,
                         nystrom_dim=16, num_landmarks=64)
    assert recs[full]["curve"]["points"][-1]["E_dist"] == pytest.approx(
        ref["gartrans"]["E_dist"], rel=1e-4)
    assert recs[full]["curve"]["lbs_E_dist"] == pytest.approx(ref["lbs"]["E_dist"], rel=1e-4)
    fit = evaluate_split(module, data_with_val, "train", modes=("gartrans",), history=3,
                         nystrom_dim=16, num_landmarks=64)
    assert recs[full]["curve"]["points"][-1]["train_E_dist"] == pytest.approx(
        fit["gartrans"]["E_dist"], rel=1e-4)
    assert recs[full]["curve"]["train_chunks"] == 2
    lbs_fit = evaluate_split(module, data_with_val, "train", modes=("lbs",), history=3,
                             nystrom_dim=16, num_landmarks=64)
    assert recs[full]["curve"]["train_lbs_E_dist"] == pytest.approx(lbs_fit["lbs"]["E_dist"],
                                                                    rel=1e-4)
    text = (tmp_path / "report.md").read_text()
    assert "## Learning curves (validation split) and equal steps" in text
    assert f"E_dist at {steps} steps (cm)" in text and (tmp_path / "learning_curves.png").exists()
