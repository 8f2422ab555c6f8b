"""Train for a fixed wall-clock budget: a Lightning callback.

:class:`TimeBudget` stops a fit once the training steps have taken ``seconds`` of wall
time and anneals the learning rate over that budget (a cosine from each parameter
group's initial rate to ``eta_min``: the schedule of a run whose length is a time, not
a number of epochs).  The time spent is kept in checkpoints, so a resumed fit continues
the same budget.  ``garmentgnn bench`` gives every learned method the same budget with
it; Lightning's own ``Trainer(max_time=...)`` stops a fit too but leaves the learning
rate to an epoch-based scheduler, which cannot know how many epochs the time allows.
"""
from __future__ import annotations

import contextlib
import math
import time
from typing import Any, Dict, Iterator, List, Optional

import lightning as L

__all__ = ["TimeBudget"]

#: the clock (a module attribute, so tests can replace it)
_now = time.perf_counter


class TimeBudget(L.Callback):
    """Stop training after ``seconds`` of training steps; cosine learning rate over them.

    Args:
        seconds: the wall-clock budget of the training epochs: from the start of an
            epoch to the end of its last step, data loading included (the time between
            epochs -- validation, checkpoint writing -- is not counted).
        anneal: set each optimizer parameter group's learning rate before every step
            to ``eta_min + (lr0 - eta_min) (1 + cos(pi f)) / 2``, ``f`` the fraction of
            the budget spent and ``lr0`` the group's rate when the fit started (its
            ``initial_lr`` where a scheduler set one).  This overrides an epoch-based
            scheduler's rate.  ``False``: the rate is left alone.
        eta_min: the final learning rate.

    Attributes:
        spent: training seconds used so far (restored from a checkpoint on resume).
        steps: training steps taken so far (restored likewise).
    """

    def __init__(self, seconds: float, anneal: bool = True, eta_min: float = 0.0) -> None:
        if not (isinstance(seconds, (int, float)) and math.isfinite(seconds) and seconds > 0):
            raise ValueError(f"`seconds`: expected a positive, finite number, got {seconds!r}")
        if not (isinstance(eta_min, (int, float)) and eta_min >= 0):
            raise ValueError(f"`eta_min`: expected a learning rate >= 0, got {eta_min!r}")
        self.seconds, self.anneal, self.eta_min = float(seconds), bool(anneal), float(eta_min)
        self.spent, self.steps = 0.0, 0
        self._t0: Optional[float] = None
        self._lr0: List[List[float]] = []

    # -- state kept in checkpoints ------------------------------------------------------
    def state_dict(self) -> Dict[str, Any]:
        return {"seconds": self.seconds, "spent": self.spent, "steps": self.steps}

    def load_state_dict(self, state: Dict[str, Any]) -> None:
        if abs(float(state.get("seconds", self.seconds)) - self.seconds) > 1e-9:
            raise ValueError(f"`seconds`: this fit's budget ({self.seconds} s) differs from "
                             f"the checkpoint's ({state['seconds']} s); resume with the same "
                             "budget or start a new run")
        self.spent, self.steps = float(state["spent"]), int(state["steps"])

    @contextlib.contextmanager
    def paused(self) -> Iterator[None]:
        """Time spent inside the block (e.g. a validation between two steps) does not
        count against the budget."""
        t = _now()
        try:
            yield
        finally:
            if self._t0 is not None:
                self._t0 += _now() - t

    @property
    def fraction(self) -> float:
        """The share of the budget spent, in ``[0, 1]``."""
        return min(1.0, self.spent / self.seconds)

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(seconds={self.seconds:g}, anneal={self.anneal}, "
                f"eta_min={self.eta_min:g}, spent={self.spent:.1f})")

    # -- hooks ----------------------------------------------------------------------------
    def on_train_start(self, trainer, pl_module) -> None:
        self._lr0 = [[float(g.get("initial_lr", g["lr"])) for g in opt.param_groups]
                     for opt in trainer.optimizers]
        if self.spent >= self.seconds:  # a resumed run whose budget is already spent
            trainer.should_stop = True

    def on_train_epoch_start(self, trainer, pl_module) -> None:
        self._t0 = _now()

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        if self.anneal:
            c = 0.5 * (1.0 + math.cos(math.pi * self.fraction))
            for opt, lr0 in zip(trainer.optimizers, self._lr0):
                for g, base in zip(opt.param_groups, lr0):
                    g["lr"] = self.eta_min + (base - self.eta_min) * c

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        now = _now()
        if self._t0 is not None:  # since the epoch began or the last step ended
            self.spent += now - self._t0
        self._t0 = now
        self.steps += 1
        if self.spent >= self.seconds:
            trainer.should_stop = True
