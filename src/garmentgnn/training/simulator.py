"""The MGN-style learned simulator as a LightningModule, trained by MeshGraphNets' recipe.

One training step is a batch of ``N`` windows of ``2 + rollout`` consecutive frames of
``N`` sequences (:class:`~garmentgnn.training.GarmentDataModule` with ``chunk=2 +
rollout``, ``stride=1``, ``drop_last=True``: every window of every training sequence),
collated as one PyG ``Batch``:

* the model starts from the simulated garment of the window's first two frames;
* with ``rollout > 1`` it first rolls forward ``rollout - 1`` frames on its own
  predictions without a gradient (the *pushforward* trick: it is trained on the states
  its own rollouts reach, and asked to bring them back to the simulation); before
  optimizer step ``rollout_start`` it trains one step (the window's last three frames);
* the last step's current positions get Gaussian noise of ``noise`` metres, and its
  target is corrected by ``(1 - noise_gamma)`` of that noise (MeshGraphNets: 3 mm,
  gamma 0.1), so the model learns to undo perturbations;
* the loss is the mean squared error of the normalised local-frame acceleration
  (:meth:`MGNStyle.normalized_target`) over the free vertices of windows whose frames are
  all valid ground truth.

The first ``stats_steps`` batches only accumulate the input and target statistics (no
optimizer step; MeshGraphNets: the first 1,000 steps).  Adam, with the learning rate
decayed exponentially per optimizer step, ``lr * decay ** (step / decay_steps)``, to no
less than ``lr_min``.

Validation, test and predict roll a whole sequence out (``eval_chunk`` of the data module:
the sequence length) from ``start``: ``"gt"`` the first two simulated frames, ``"drape"``
the first simulated frame held still (a settled drape: what a user has), ``"lbs"`` the
LBS garment of the first two frames.  Frames given to the model are not scored.
"""
from __future__ import annotations

import copy
from typing import Any, Dict, Optional, Tuple

import torch
from torch import Tensor

from garmentgnn.data.store import read_manifest
from garmentgnn.models.inputs import GarmentInputs
from garmentgnn.models.mgn import MGNStyle, SceneMotion
from garmentgnn.training.base import GarmentModule

__all__ = ["SimulatorModule", "START_STATES"]

#: where an evaluation rollout starts (``start``)
START_STATES = ("gt", "drape", "lbs")


def _positive_int(name: str, v: Any, low: int = 1) -> None:
    if not isinstance(v, int) or isinstance(v, bool) or v < low:
        raise ValueError(f"`{name}`: expected an int >= {low}, got {v!r}")


class SimulatorModule(GarmentModule):
    """An :class:`~garmentgnn.models.MGNStyle` trained by MeshGraphNets' recipe (module
    doc); in YAML (``recipes/mgn.yaml``): ``model: init_args: model: class_path:
    garmentgnn.models.MGNStyle``.

    Args:
        model: the learned simulator to train.
        lr: Adam's learning rate at step 0; ``decay``, ``decay_steps``, ``lr_min``: the
            rate is ``max(lr_min, lr * decay ** (step / decay_steps))``.
        noise: standard deviation (m) of the noise on the input positions (MeshGraphNets:
            3 mm; 1 cm rolled out best of 1, 3 and 10 mm on `learn`, docs/experiments.md).
        noise_gamma: the share of the noise the target keeps (0: the model undoes all of
            it in one step; MeshGraphNets: 0.1).
        rollout: frames a training window rolls forward, the first ``rollout - 1``
            without a gradient (pushforward); the data's ``chunk`` must be
            ``2 + rollout``.  ``rollout_start``: the optimizer step from which it does;
            one-step training (the window's last three frames) before it.  Three frames
            from step 3,500 on brought the `learn` test rollouts from 1.26x to 0.91x LBS
            at step 5,000 (docs/results/mgn_learn, "Pushforward"); ``rollout=1``: one-step
            training throughout (MeshGraphNets' own recipe).
        stats_steps: batches at the start that only accumulate the normalisation
            statistics.
        start: where validation, test and predict rollouts start (module doc).
    """

    #: the method's name in tables (``garmentgnn train test``)
    method = "mgn"

    def __init__(self, model: MGNStyle, lr: float = 1e-3, decay: float = 0.1,
                 decay_steps: int = 6250, lr_min: float = 1e-6, noise: float = 0.01,
                 noise_gamma: float = 0.1, rollout: int = 3, rollout_start: int = 3500,
                 stats_steps: int = 100, start: str = "gt") -> None:
        super().__init__()
        if not isinstance(model, MGNStyle):
            raise TypeError(f"`model`: expected an MGNStyle, got {type(model).__name__}; "
                            f"SimulatorModule(MGNStyle())")
        if not (lr > 0 and lr_min > 0 and 0 < decay <= 1):
            raise ValueError(f"`lr`, `lr_min`, `decay`: expected lr > 0, lr_min > 0 and "
                             f"0 < decay <= 1, got {lr!r}, {lr_min!r}, {decay!r}")
        _positive_int("decay_steps", decay_steps)
        _positive_int("rollout", rollout)
        _positive_int("rollout_start", rollout_start, 0)
        _positive_int("stats_steps", stats_steps, 0)
        if not (isinstance(noise, (int, float)) and noise >= 0):
            raise ValueError(f"`noise`: expected metres >= 0, got {noise!r}")
        if not (isinstance(noise_gamma, (int, float)) and 0 <= noise_gamma <= 1):
            raise ValueError(f"`noise_gamma`: expected a value in [0, 1], got {noise_gamma!r}")
        if start not in START_STATES:
            raise ValueError(f"`start`: expected one of {START_STATES}, got {start!r}")
        if stats_steps > model.target_norm.max_updates:
            raise ValueError(f"`stats_steps`: {stats_steps} batches of statistics, but the "
                             f"model keeps updating them for only "
                             f"{model.target_norm.max_updates} (its `norm_updates`); give at "
                             f"most that")
        self.save_hyperparameters(ignore=["model"])
        self.hand_model(model)

    # -- set-up checks ----------------------------------------------------------------
    def setup(self, stage: str) -> None:
        super().setup(stage)
        try:
            dm = self.trainer.datamodule
        except RuntimeError:
            dm = None
        if dm is None or getattr(dm, "hparams", None) is None:
            return
        hp = dm.hparams
        if stage == "fit":
            need = 2 + self.hparams.rollout
            if hp.chunk != need:
                raise ValueError(f"--data.chunk: the MGN-style model trains on windows of "
                                 f"2 + rollout = {need} frames, got {hp.chunk}; give "
                                 f"--data.chunk {need} (with --data.stride 1 "
                                 f"--data.drop_last true)")
        rates = {float((r.get("settings") or {}).get("fps", 0)) or None
                 for r in read_manifest(dm.root)["items"]}
        rates.discard(None)
        other = sorted(f for f in rates if abs(f - self.model.fps) > 1e-6 * self.model.fps)
        if other:
            raise ValueError(f"--data.root: {dm.root} is simulated at {other[0]:g} fps, the "
                             f"model learned its accelerations at {self.model.fps:g} fps; "
                             f"resample the motion to {self.model.fps:g} fps or train a "
                             f"model at {other[0]:g} fps (--model.model.fps)")

    # -- training -----------------------------------------------------------------------
    def window_loss(self, batch: GarmentInputs) -> Tuple[Tensor, Dict[str, Tensor]]:
        """The loss of a batch of training windows (module doc) and its parts."""
        hp = self.hparams
        gt = batch.get("gt")
        if gt is None:
            raise ValueError("`batch`: the MGN-style model trains on simulated frames "
                             "(`gt`), the batch has none")
        T = gt.shape[0]
        if T != 2 + hp.rollout:
            raise ValueError(f"`batch`: expected windows of 2 + rollout = {2 + hp.rollout} "
                             f"frames, got {T} (--data.chunk {2 + hp.rollout})")
        if self.global_step < hp.rollout_start:  # one step: the last three frames
            batch = batch.select(torch.arange(T - 3, T))
            gt, T = batch.gt, 3
        model = self.model
        motion = model.scene_motion(batch)
        x_prev, x_curr = gt[0], gt[1]
        with torch.no_grad():  # pushforward: the states its own rollout reaches
            for t in range(2, T - 1):
                x_prev, x_curr = x_curr, model.step(batch, motion, t, x_prev, x_curr)
        t = T - 1
        free = ~motion.pinned
        n = hp.noise * torch.randn_like(x_curr) * free.unsqueeze(1) if hp.noise else 0.0
        x_noisy = x_curr + n
        target = gt[t] + (1.0 - hp.noise_gamma) * n
        out = model(batch, motion, t, x_prev, x_noisy)
        want = model.normalized_target(target - 2 * x_noisy + x_prev, motion, t)
        valid = batch.get("valid")
        keep = free
        if valid is not None:  # windows whose every frame is valid ground truth
            ok = valid.reshape(batch.num_chunks, T).all(1)
            keep = keep & ok[motion.vertex_chunk]
        err = ((out - want) ** 2).sum(1)
        w = keep.to(err.dtype)
        loss = (err * w).sum() / w.sum().clamp_min(1.0)
        with torch.no_grad():
            a = model.acceleration(out.detach(), motion, t)
            pos_err = ((2 * x_noisy + a - x_prev - target).norm(dim=1) * w).sum() \
                / w.sum().clamp_min(1.0)
        return loss, {"one_step_m": pos_err}

    def collecting_statistics(self) -> bool:
        """Whether this batch only accumulates the normalisation statistics."""
        return self.training and int(self.model.target_norm.updates) < self.hparams.stats_steps

    def training_step(self, batch: GarmentInputs, batch_idx: int) -> Optional[Tensor]:
        if self.collecting_statistics():
            with torch.no_grad():
                self.window_loss(batch)
            return None  # no optimizer step (Lightning skips it)
        loss, extra = self.window_loss(batch)
        self.log_training_step(loss, {}, batch.num_chunks, extra)
        return loss

    def configure_optimizers(self):
        hp = self.hparams
        opt = torch.optim.Adam(self.parameters(), lr=hp.lr)
        floor = hp.lr_min / hp.lr

        def factor(step: int) -> float:
            return max(floor, hp.decay ** (step / hp.decay_steps))

        sched = torch.optim.lr_scheduler.LambdaLR(opt, factor)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    # -- rollouts -------------------------------------------------------------------------
    def start_states(self, batch: GarmentInputs, motion: SceneMotion,
                     start: Optional[str] = None) -> Tuple[Tensor, Tensor]:
        """The garment ``[V, 3]`` at frames 0 and 1 that a rollout of ``batch`` starts
        from (``start``, default the module's)."""
        start = start or self.hparams.start
        gt = batch.get("gt")
        if start != "lbs" and gt is None:
            raise ValueError(f"`start`: {start!r} starts from the simulated garment, which "
                             f"these inputs lack; start from 'lbs'")
        if start == "gt":
            return gt[0], gt[1]
        if start == "drape":
            return gt[0], gt[0]
        return motion.lbs[0], motion.lbs[1]

    def rollout(self, batch: GarmentInputs, start: Optional[str] = None) -> Tensor:
        """The garment ``[T, V, 3]`` of ``batch``'s frames, rolled out from ``start``."""
        if batch.num_frames < 3:
            raise ValueError(f"`batch`: a rollout needs at least 3 frames (two to start "
                             f"from), got {batch.num_frames}")
        motion = self.model.scene_motion(batch)
        x0, x1 = self.start_states(batch, motion, start)
        return self.model.rollout(batch, x0, x1, motion)

    def predict_garment(self, batch: GarmentInputs) -> Tensor:
        return self.rollout(batch)

    def _scored(self, batch: GarmentInputs) -> GarmentInputs:
        """``batch`` with the frames a rollout is given (from the ground truth) left out
        of its valid frames."""
        if self.hparams.start == "lbs" or "valid" not in batch:
            return batch
        out = copy.copy(batch)
        valid = batch.valid.clone()
        valid[..., :2] = False
        out.valid = valid
        return out

    def validation_step(self, batch: GarmentInputs, batch_idx: int) -> Dict[str, float]:
        return super().validation_step(self._scored(batch), batch_idx)

    def test_step(self, batch: GarmentInputs, batch_idx: int) -> Dict[str, float]:
        return super().test_step(self._scored(batch), batch_idx)
