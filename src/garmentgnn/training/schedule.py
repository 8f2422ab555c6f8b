"""The progressive training schedule of GarTrans (paper §4.1) as a Lightning callback.

* phase 1: supervised terms (vert, edge, norm);
* phase 2, once the relative reduction of the epoch-mean vertex error over the last
  ``window`` epochs falls below ``threshold`` (3% over 50 epochs in the paper):
  collision + gravity on, supervised terms scaled by ``supervised_scale`` (0.05);
* phase 3, once the collision term's relative change over ``window`` epochs falls
  below ``threshold``: the rest-pose branch (rest_fc, rest_attn, nystrom_fc, body_fc)
  is frozen (``freeze_rest``) and stretch + shear are switched on.

``extra_terms`` (not in the paper) switches further terms of :class:`GarTransLoss` --
the curvature term by default -- on from phase ``extra_from`` on.

The monitored values are epoch means accumulated by the callback itself from the
training step outputs (``vert_err``: unscaled mean vertex distance; ``terms``; under
DDP summed over the replicas, so every replica changes phase at the same epoch), and
the phase, the histories and the transition epochs are part of :meth:`state_dict`, so a
run resumed from a checkpoint continues in exactly the same phase.
"""
from __future__ import annotations

from typing import Any, Dict, List, Optional, Sequence

import lightning as L
import torch

from garmentgnn.losses.gartrans_loss import PAPER_WEIGHTS, SUPERVISED

PHASE_TERMS = {
    1: tuple(SUPERVISED),
    2: tuple(SUPERVISED) + ("collision", "gravity"),
    3: tuple(SUPERVISED) + ("collision", "gravity", "stretch", "shear"),
}


class ProgressiveSchedule(L.Callback):
    """The schedule :class:`~garmentgnn.training.GarTransModule` trains with (it owns
    one: its ``schedule`` argument holds these arguments).  The defaults are the
    project's, measured on CPU-sized runs (docs/model.md); the paper's are
    ``window=50, window2=None, threshold2=None, extra_terms=(), extra_from=3``.

    Args:
        window: epochs over which the relative change is measured (the paper: 50; 4 here,
            so that a CPU run on the ``small`` dataset reaches all three phases).
        threshold: relative change below which a phase ends (0.03).
        window2, threshold2: the same for the collision plateau (``None``: as above; 3
            epochs within 10% here: with window 4 / 3% phase 3 began at epoch 28 of 30).
        supervised_scale: scale of the supervised terms from phase 2 on (0.05).
        start_phase: the phase of a fresh run (1).
        max_phase: stop advancing after this phase.
        extra_terms: loss terms beyond the paper's (their weights are the module's
            ``loss_weights``), active from phase ``extra_from`` on; here the curvature term
            from phase 1 (docs/model.md: without it the model lost to LBS on E_curv).
        freeze_rest: freeze the rest-pose branch in phase 3 (the paper); ``False`` keeps
            training it on phase 3's losses too.
    """

    def __init__(self, window: int = 4, threshold: float = 0.03,
                 window2: Optional[int] = 3, threshold2: Optional[float] = 0.1,
                 supervised_scale: float = 0.05, start_phase: int = 1, max_phase: int = 3,
                 extra_terms: Sequence[str] = ("curv",), extra_from: int = 1,
                 freeze_rest: bool = True) -> None:
        if window < 1:
            raise ValueError(f"`window`: expected >= 1, got {window}")
        if start_phase not in PHASE_TERMS:
            raise ValueError(f"`start_phase`: expected 1, 2 or 3, got {start_phase}")
        if extra_from not in PHASE_TERMS:
            raise ValueError(f"`extra_from`: expected 1, 2 or 3, got {extra_from}")
        unknown = set(extra_terms) - set(PAPER_WEIGHTS)
        if unknown:
            raise ValueError(f"`extra_terms`: unknown term(s) {sorted(unknown)}; known: "
                             f"{sorted(PAPER_WEIGHTS)}")
        self.extra_terms, self.extra_from = tuple(extra_terms), extra_from
        self.freeze_rest = freeze_rest
        self.window, self.threshold = window, threshold
        self.window2 = window if window2 is None else window2
        self.threshold2 = threshold if threshold2 is None else threshold2
        self.supervised_scale = supervised_scale
        self.max_phase = max_phase
        self.phase = start_phase
        self.history: List[float] = []  # epoch means of the monitored value of this phase
        self.transitions: Dict[int, int] = {}  # phase -> epoch at whose end it began
        self._sum, self._n = 0.0, 0

    @classmethod
    def of(cls, trainer: Any) -> Optional["ProgressiveSchedule"]:
        """The schedule among ``trainer``'s callbacks (a module's own, from
        ``configure_callbacks``, once a fit has begun); ``None`` without one."""
        return next((c for c in trainer.callbacks if isinstance(c, cls)), None)

    # -- state ------------------------------------------------------------------------
    def state_dict(self) -> Dict[str, Any]:
        return {"phase": self.phase, "history": list(self.history),
                "transitions": {str(k): v for k, v in self.transitions.items()}}

    def load_state_dict(self, state: Dict[str, Any]) -> None:
        self.phase = int(state["phase"])
        self.history = [float(x) for x in state["history"]]
        self.transitions = {int(k): int(v) for k, v in state.get("transitions", {}).items()}

    # -- applying a phase -------------------------------------------------------------
    def apply(self, pl_module) -> None:
        loss = pl_module.loss_fn
        extra = self.extra_terms if self.phase >= self.extra_from else ()
        loss.set_enabled(PHASE_TERMS[self.phase] + extra)
        loss.supervised_scale = 1.0 if self.phase == 1 else self.supervised_scale
        pl_module.set_rest_branch_frozen(self.freeze_rest and self.phase >= 3)

    def on_fit_start(self, trainer, pl_module) -> None:  # after a checkpoint is restored
        self.apply(pl_module)

    # -- monitoring -------------------------------------------------------------------
    def on_train_epoch_start(self, trainer, pl_module) -> None:
        self._sum, self._n = 0.0, 0

    def _monitored(self, outputs) -> Optional[float]:
        if not isinstance(outputs, dict):
            return None
        if self.phase == 1:
            v = outputs.get("vert_err")
        else:
            v = outputs.get("terms", {}).get("collision")
        return None if v is None else float(torch.as_tensor(v).detach())

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        v = self._monitored(outputs)
        if v is not None:
            self._sum += v
            self._n += 1

    @staticmethod
    def relative_change(old: float, new: float) -> float:
        return (old - new) / max(abs(old), 1e-12)

    def on_train_epoch_end(self, trainer, pl_module) -> None:
        # DDP: the mean over every replica's chunks, so all replicas switch phase together
        total = trainer.strategy.reduce(torch.tensor([self._sum, float(self._n)],
                                                     dtype=torch.float64), reduce_op="sum")
        s, n = (float(v) for v in total)
        if n:
            self.history.append(s / n)
        pl_module.log("schedule/phase", float(self.phase))
        if self.phase >= self.max_phase or len(self.history) <= (self.window if self.phase == 1
                                                                  else self.window2):
            return
        if self.phase == 1:
            old = self.history[-1 - self.window]
            plateau = self.relative_change(old, self.history[-1]) < self.threshold
        else:
            old = self.history[-1 - self.window2]
            plateau = abs(self.relative_change(old, self.history[-1])) < self.threshold2
        if plateau:
            self.phase += 1
            self.history = []
            self.transitions[self.phase] = int(trainer.current_epoch)
            self.apply(pl_module)
