"""TimeBudget: a wall-clock training budget with the learning rate annealed over it.

Oracles: a fake clock (the callback's ``_now`` replaced by a counter that advances a fixed
amount per call) makes the spent time exact, so the stopping step and every learning
rate follow from the cosine formula written out here."""
import math

import lightning as L
import pytest
import torch

from garmentgnn.training import budget as budget_mod
from garmentgnn.training import TimeBudget


class Tiny(L.LightningModule):
    def __init__(self, lr=0.1):
        super().__init__()
        self.w = torch.nn.Parameter(torch.ones(3))
        self.lrs = []

    def training_step(self, batch, idx):
        self.lrs.append(self.trainer.optimizers[0].param_groups[0]["lr"])
        return ((self.w - batch) ** 2).sum()

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)

    def train_dataloader(self):
        return torch.utils.data.DataLoader(torch.zeros(100, 3), batch_size=None)


class Clock:
    """Each call advances one second."""

    def __init__(self):
        self.t = 0.0

    def __call__(self):
        self.t += 1.0
        return self.t


def fit(module, cb, tmp_path, max_epochs=1, ckpt=None):
    trainer = L.Trainer(max_epochs=max_epochs, logger=False, enable_progress_bar=False,
                        enable_model_summary=False, callbacks=[cb],
                        default_root_dir=tmp_path, enable_checkpointing=False)
    trainer.fit(module, ckpt_path=ckpt)
    return trainer


def test_stops_at_the_budget_and_anneals_the_learning_rate(tmp_path, monkeypatch):
    monkeypatch.setattr(budget_mod, "_now", Clock())
    cb = TimeBudget(10.0, eta_min=0.01)
    m = Tiny()
    fit(m, cb, tmp_path)
    # the epoch start reads the clock once, each step end once: 1 s per step
    assert cb.steps == 10 and cb.spent == pytest.approx(10.0)
    want = [0.01 + (0.1 - 0.01) * 0.5 * (1 + math.cos(math.pi * k / 10)) for k in range(10)]
    assert m.lrs == pytest.approx(want)


def test_resume_continues_the_same_budget(tmp_path, monkeypatch):
    monkeypatch.setattr(budget_mod, "_now", Clock())
    cb = TimeBudget(10.0)
    cb.load_state_dict({"seconds": 10.0, "spent": 7.0, "steps": 7})
    m = Tiny()
    fit(m, cb, tmp_path)
    assert cb.steps == 10 and len(m.lrs) == 3
    assert m.lrs[0] == pytest.approx(0.1 * 0.5 * (1 + math.cos(math.pi * 0.7)))
    spent = TimeBudget(10.0)
    spent.load_state_dict({"seconds": 10.0, "spent": 10.0, "steps": 10})
    m2 = Tiny()
    fit(m2, spent, tmp_path)
    assert m2.lrs == [] and spent.steps == 10  # a spent budget trains no more
    with pytest.raises(ValueError, match="`seconds`.*differs"):
        TimeBudget(5.0).load_state_dict({"seconds": 10.0, "spent": 1.0, "steps": 1})


def test_state_survives_a_checkpoint(tmp_path):
    cb = TimeBudget(1e9)
    trainer = fit(Tiny(), cb, tmp_path)
    path = tmp_path / "a.ckpt"
    trainer.save_checkpoint(path)
    cb2 = TimeBudget(1e9)
    fit(Tiny(), cb2, tmp_path, max_epochs=2, ckpt=str(path))
    assert cb2.steps == 200 and cb2.spent > cb.spent > 0


@pytest.mark.parametrize("kw", [{"seconds": 0}, {"seconds": float("inf")}, {"seconds": "5"},
                                {"seconds": 1, "eta_min": -1}])
def test_bad_arguments(kw):
    named = next(k for k in kw if k != "seconds" or len(kw) == 1)
    with pytest.raises(ValueError, match=f"`{named}`"):
        TimeBudget(**kw)
