"""The MGN-style learned simulator as a LightningModule, trained by MeshGraphNets' recipe.

One training step is a batch of ``N`` windows of ``2 + R`` consecutive frames of ``N``
sequences (:class:`~garmentgnn.training.GarmentDataModule` with ``chunk=2 + R``,
``stride=1``, ``drop_last=True``: every window of every training sequence; ``R`` the
longest rollout of the schedule), collated as one PyG ``Batch``:

* **the rollout length** ``r`` of a step follows the schedule: ``rollout_schedule``, a
  list of ``[from_step, frames]`` (HOOD: ``1 + step // 5000``; e.g. ``[[0, 1], [2000, 2],
  [4000, 5]]``), or by default one frame before optimizer step ``rollout_start`` and
  ``rollout`` frames from it on; the step reads the window's last ``2 + r`` frames and
  starts from the simulated garment at their first two (a share ``lbs_start`` of the
  windows from the LBS garment there: the start ``predict`` uses);
* **how it rolls** (``rollout_mode``): ``"pushforward"`` rolls ``r - 1`` frames on its own
  predictions without a gradient and trains the last (Brandstetter et al.'s pushforward
  trick: trained on the states its rollouts reach, and asked to bring them back to the
  simulation); ``"random"`` rolls a random ``N`` in ``0 .. r - 1`` frames (the rest of
  the window unused); ``"per_frame"`` trains every one of the ``r`` frames with an
  optimizer step after each and the state detached between them (HOOD, ContourCraft);
* each trained frame's current positions get Gaussian noise of ``noise`` metres, and its
  target position is shifted by ``(1 - noise_gamma)`` of that noise (MeshGraphNets: 3 mm,
  gamma 0.1): the model learns to remove ``noise_gamma`` of a perturbation in one step;
* the loss is :meth:`MGNStyle.loss <garmentgnn.models.MGNStyle.loss>` over the free
  vertices of windows whose frames are all valid ground truth; gradients are clipped to
  the norm ``clip`` before every optimizer step (the module optimises by hand:
  ``per_frame`` takes several optimizer steps a batch, and ``--trainer.max_steps``
  counts optimizer steps).

The first ``stats_steps`` batches only accumulate the input and target statistics (no
optimizer step; MeshGraphNets: the first 1,000 steps).  Adam, with the learning rate
decayed exponentially per optimizer step, ``lr * decay ** (step / decay_steps)``, to no
less than ``lr_min``.

Validation, test and predict roll a whole sequence out (``eval_chunk`` of the data module:
the sequence length) from ``start``: ``"gt"`` the first two simulated frames, ``"drape"``
the first simulated frame held still (a settled drape: what a user has), ``"lbs"`` the
LBS garment of the first two frames, ``"preroll"`` the LBS garment of the first frame
held still, then ``preroll_frames`` steps of the model with the body held at its first
pose before the motion starts (Blender's own pre-roll: the model settles the garment
and takes up the body's motion; no ground truth); :meth:`RolloutModule.rollout` also
starts from a garment of frames 0 and 1 given as a tensor (another method's prediction).
Frames given to the model are not scored (the first two, for every start but ``"lbs"``).
An exponential moving average of the weights (Lightning's ``EMAWeightAveraging``
callback, in ``recipes/mgn.yaml``) is what validation, test and the checkpoints see.
"""
from __future__ import annotations

import copy
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple, Union

import torch
from lightning.pytorch.utilities import rank_zero_warn
from torch import Tensor

from garmentgnn.data.store import read_manifest
from garmentgnn.models.inputs import GarmentInputs
from garmentgnn.models.mgn import MGNStyle, SceneMotion
from garmentgnn.training.base import GarmentModule, NonFiniteLossError
from garmentgnn.training.budget import TimeBudget

__all__ = ["ROLLOUT_MODES", "RolloutModule", "START_STATES"]

#: where an evaluation rollout starts (``start``)
START_STATES = ("gt", "drape", "lbs", "preroll")
#: how a training step rolls out (``rollout_mode``, module doc)
ROLLOUT_MODES = ("pushforward", "random", "per_frame")


def _positive_int(name: str, v: Any, low: int = 1) -> None:
    if not isinstance(v, int) or isinstance(v, bool) or v < low:
        raise ValueError(f"`{name}`: expected an int >= {low}, got {v!r}")


def check_schedule(schedule: Sequence[Sequence[int]]) -> List[Tuple[int, int]]:
    """``rollout_schedule`` as ``[(from_step, frames), ...]``, or a ``ValueError``."""
    fix = "give [[from_step, frames], ...] with ascending steps from 0, e.g. [[0, 1], [2000, 5]]"
    try:
        pairs = [(s, r) for s, r in schedule]
    except (TypeError, ValueError):
        raise ValueError(f"`rollout_schedule`: expected pairs, got {schedule!r}; {fix}") from None
    ok = (pairs and pairs[0][0] == 0
          and all(isinstance(v, int) and not isinstance(v, bool) for p in pairs for v in p)
          and all(r >= 1 for _, r in pairs)
          and all(a[0] < b[0] for a, b in zip(pairs, pairs[1:])))
    if not ok:
        raise ValueError(f"`rollout_schedule`: got {schedule!r}; {fix}")
    return pairs


class RolloutModule(GarmentModule):
    """An :class:`~garmentgnn.models.MGNStyle` trained by MeshGraphNets' recipe (module
    doc); in YAML (``recipes/mgn.yaml``): ``model: init_args: model: class_path:
    garmentgnn.models.MGNStyle``.

    Args:
        model: the learned simulator to train.
        lr: Adam's learning rate at step 0; ``decay``, ``decay_steps``, ``lr_min``: the
            rate is ``max(lr_min, lr * decay ** (step / decay_steps))``; ``decay_steps``
            default: the run's ``--trainer.max_steps`` (the rate decays by ``decay`` over
            the whole run); a run without one keeps ``lr`` (a
            :class:`~garmentgnn.training.TimeBudget` anneals it instead).
        noise: standard deviation (m) of the noise on the input positions (MeshGraphNets:
            3 mm; 1 cm rolled out best of 1, 3 and 10 mm on `learn`, docs/experiments.md).
        noise_gamma: the share of the noise the model removes in one step: the target
            position is the simulated one plus ``1 - noise_gamma`` times the noise (1:
            all of it; 0: none, only the velocity is corrected; MeshGraphNets: 0.1).
        rollout: frames a training window rolls forward, the first ``rollout - 1``
            without a gradient (pushforward); the data's ``chunk`` must be
            ``2 + rollout``.  ``rollout_start``: the optimizer step from which it does;
            one-step training (the window's last three frames) before it.  Three frames
            from step 3,500 on brought the `learn` test rollouts from 1.26x to 0.91x LBS
            at step 5,000 (docs/results/mgn_learn, "Pushforward"); ``rollout=1``: one-step
            training throughout (MeshGraphNets' own recipe).
        stats_steps: batches at the start that only accumulate the normalisation
            statistics.
        rollout_schedule: ``[[from_step, frames], ...]`` with ascending steps, the first
            0: the rollout length from each optimizer step on (replaces ``rollout`` and
            ``rollout_start``).
        rollout_mode: ``"pushforward"``, ``"random"`` or ``"per_frame"`` (module doc).
        clip: the largest gradient norm before an optimizer step (``None``: no clip;
            HOOD: 1).
        train_inextensible: sweeps of the inextensible projection (every edge toward
            its rest length, as the model's ``inextensible`` in eval mode) after each
            step of a training window's rollout, its pushforward frames and its trained
            frames' states
            (:meth:`~garmentgnn.models.sequence.PostSteps.inextensible_projection`); 0:
            the model's training-mode projection (its strain limit).
        lbs_start: the share of training windows whose rollout starts from the LBS
            garment of their first two frames (the start ``predict`` uses: no ground
            truth) instead of the simulated one; drawn per window (torch's global
            generator, which the run's seed sets); 0: every window from the simulation.
        preroll_frames: the steps of the ``"preroll"`` start.
        start: where validation, test and predict rollouts start (module doc).
    """

    #: the method's short name (``garmentgnn predict``'s summary)
    method = "mgn"
    #: the method protocol (:class:`GarmentModule`): a whole sequence rolled out from two
    #: frames, one model for every garment
    autoregressive = True
    min_frames = 3
    table_name = "MGN-style"
    timing_note = "one autoregressive step of `batch` independent garments per call"

    @property
    def learned_fps(self) -> Optional[float]:
        """The model's ``fps``: it predicts accelerations in metres per frame squared."""
        fps = getattr(self.model, "fps", None)
        return None if fps is None else float(fps)

    def __init__(self, model: MGNStyle, lr: float = 1e-3, decay: float = 0.1,
                 decay_steps: Optional[int] = None, lr_min: float = 1e-6,
                 noise: float = 0.01,
                 noise_gamma: float = 0.1, rollout: int = 3, rollout_start: int = 3500,
                 stats_steps: int = 100, start: str = "gt",
                 rollout_schedule: Optional[List[Tuple[int, int]]] = None,
                 rollout_mode: str = "pushforward", clip: Optional[float] = None,
                 preroll_frames: int = 15, train_inextensible: int = 0,
                 lbs_start: float = 0.0) -> None:
        super().__init__()
        if not isinstance(model, MGNStyle):
            raise TypeError(f"`model`: expected an MGNStyle, got {type(model).__name__}; "
                            f"RolloutModule(MGNStyle())")
        if not (lr > 0 and lr_min > 0 and 0 < decay <= 1):
            raise ValueError(f"`lr`, `lr_min`, `decay`: expected lr > 0, lr_min > 0 and "
                             f"0 < decay <= 1, got {lr!r}, {lr_min!r}, {decay!r}")
        if decay_steps is not None:
            _positive_int("decay_steps", decay_steps)
        _positive_int("rollout", rollout)
        _positive_int("rollout_start", rollout_start, 0)
        _positive_int("stats_steps", stats_steps, 0)
        _positive_int("preroll_frames", preroll_frames, 0)
        _positive_int("train_inextensible", train_inextensible, 0)
        if not (isinstance(noise, (int, float)) and noise >= 0):
            raise ValueError(f"`noise`: expected metres >= 0, got {noise!r}")
        if not (isinstance(lbs_start, (int, float)) and not isinstance(lbs_start, bool)
                and 0 <= lbs_start <= 1):
            raise ValueError(f"`lbs_start`: expected a share in [0, 1], got {lbs_start!r}")
        if not (isinstance(noise_gamma, (int, float)) and 0 <= noise_gamma <= 1):
            raise ValueError(f"`noise_gamma`: expected a value in [0, 1], got {noise_gamma!r}")
        if rollout_schedule is not None:
            rollout_schedule = check_schedule(rollout_schedule)
        if rollout_mode not in ROLLOUT_MODES:
            raise ValueError(f"`rollout_mode`: expected one of {ROLLOUT_MODES}, got "
                             f"{rollout_mode!r}")
        if clip is not None and not (isinstance(clip, (int, float)) and clip > 0):
            raise ValueError(f"`clip`: expected a gradient norm > 0 or None, got {clip!r}")
        if start not in START_STATES:
            raise ValueError(f"`start`: expected one of {START_STATES}, got {start!r}")
        if stats_steps > model.target_norm.max_updates:
            raise ValueError(f"`stats_steps`: {stats_steps} batches of statistics, but the "
                             f"model keeps updating them for only "
                             f"{model.target_norm.max_updates} (its `norm_updates`); give at "
                             f"most that")
        self.save_hyperparameters(ignore=["model"])
        self.hand_model(model)
        self.automatic_optimization = False  # per_frame steps several times a batch
        # the random rollout lengths follow the run's seed (torch's global generator)

    # -- the schedule -----------------------------------------------------------------
    @property
    def schedule(self) -> List[Tuple[int, int]]:
        """``[(from_step, frames), ...]``: the rollout length from each optimizer step on."""
        hp = self.hparams
        if hp.rollout_schedule is not None:
            return [tuple(p) for p in hp.rollout_schedule]
        if hp.rollout == 1 or hp.rollout_start == 0:
            return [(0, hp.rollout)]
        return [(0, 1), (hp.rollout_start, hp.rollout)]

    @property
    def window(self) -> int:
        """Frames of a training window: 2 + the schedule's longest rollout."""
        return 2 + max(r for _, r in self.schedule)

    def rollout_at(self, step: int) -> int:
        """The rollout length at optimizer step ``step``."""
        return [r for s, r in self.schedule if s <= step][-1]

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
            need = self.window
            if hp.chunk != need:
                raise ValueError(f"--data.chunk: the MGN-style model trains on windows of "
                                 f"2 + its longest rollout = {need} frames, got {hp.chunk}; "
                                 f"give --data.chunk {need} (with --data.stride 1 "
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
    def _window(self, batch: GarmentInputs) -> GarmentInputs:
        gt = batch.get("gt")
        if gt is None:
            raise ValueError("`batch`: the MGN-style model trains on simulated frames "
                             "(`gt`), the batch has none")
        if gt.shape[0] != self.window:
            raise ValueError(f"`batch`: expected windows of 2 + the longest rollout = "
                             f"{self.window} frames, got {gt.shape[0]} (--data.chunk "
                             f"{self.window})")
        return batch

    def frames_to_train(self, step: int) -> Tuple[int, int]:
        """``(frames rolled without a gradient, frames trained)`` at optimizer step
        ``step`` (module doc, ``rollout_mode``)."""
        r = self.rollout_at(step)
        mode = self.hparams.rollout_mode
        if mode == "per_frame":
            return 0, r
        if mode == "random":
            return int(torch.randint(r, ())), 1
        return r - 1, 1

    def window_loss(self, batch: GarmentInputs, free_frames: Optional[int] = None,
                    trained: int = 1, on_frame=None) -> Tuple[Tensor, Dict[str, Tensor]]:
        """The loss of a batch of training windows (module doc): ``free_frames`` frames
        rolled without a gradient (default: the schedule's at this step), then
        ``trained`` frames, each scored; ``on_frame(loss)`` is called after each trained
        frame (an optimizer step), else the frames' mean loss is returned."""
        hp = self.hparams
        batch = self._window(batch)
        if free_frames is None:
            free_frames, trained = self.frames_to_train(self.global_step)
        T = batch.gt.shape[0]
        n_use = 2 + free_frames + trained
        if n_use < T:  # the window's last frames
            batch = batch.select(torch.arange(T - n_use, T))
        model = self.model
        with model.inextensible_projection(hp.train_inextensible):
            return self._rolled_loss(batch, model, free_frames, on_frame)

    def _rolled_loss(self, batch: GarmentInputs, model: MGNStyle, free_frames: int,
                     on_frame) -> Tuple[Tensor, Dict[str, Tensor]]:
        hp = self.hparams
        gt, T = batch.gt, batch.gt.shape[0]
        motion = model.scene_motion(batch)
        x_prev, x_curr = self.start_states(batch, motion, "gt")
        if hp.lbs_start:  # some windows start from the LBS garment (no ground truth)
            lbs = torch.rand(batch.num_chunks, device=gt.device) < hp.lbs_start
            lbs = lbs[motion.vertex_chunk].unsqueeze(1)
            l_prev, l_curr = self.start_states(batch, motion, "lbs")
            x_prev = torch.where(lbs, l_prev, x_prev)
            x_curr = torch.where(lbs, l_curr, x_curr)
        with torch.no_grad():  # pushforward: the states its own rollout reaches
            for t in range(2, 2 + free_frames):
                x_prev, x_curr = x_curr, model.step(batch, motion, t, x_prev, x_curr)
        free = ~motion.pinned
        weight = free
        valid = batch.get("valid")
        if valid is not None:  # windows whose every frame is valid ground truth
            ok = valid.reshape(batch.num_chunks, T).all(1)
            weight = weight & ok[motion.vertex_chunk]
        losses, errs = [], []
        for t in range(2 + free_frames, T):
            n = hp.noise * torch.randn_like(x_curr) * free.unsqueeze(1) if hp.noise else 0.0
            target = gt[t] + (1.0 - hp.noise_gamma) * n
            loss, x_next, err = model.loss(batch, motion, t, x_prev, x_curr + n, target,
                                           weight)
            if on_frame is not None:
                on_frame(loss)
                loss = loss.detach()
            losses.append(loss)
            errs.append(err)
            x_prev, x_curr = x_curr, x_next.detach()
        return torch.stack(losses).mean(), {"one_step_m": torch.stack(errs).mean(),
                                            "rollout": torch.tensor(float(T - 2))}

    def training_loss(self, batch: GarmentInputs) -> Tensor:
        """The loss of a batch of windows at the schedule's current step."""
        return self.window_loss(batch)[0]

    def collecting_statistics(self) -> bool:
        """Whether this batch only accumulates the normalisation statistics."""
        return self.training and int(self.model.target_norm.updates) < self.hparams.stats_steps

    def _optimizer_step(self, loss: Tensor) -> None:
        if not torch.isfinite(loss):
            raise NonFiniteLossError(f"loss 'total' is {float(loss)}")
        opt = self.optimizers()
        opt.zero_grad(set_to_none=True)
        self.manual_backward(loss)
        if self.hparams.clip is not None:
            self.clip_gradients(opt, gradient_clip_val=self.hparams.clip,
                                gradient_clip_algorithm="norm")
        opt.step()
        self.lr_schedulers().step()

    def training_step(self, batch: GarmentInputs, batch_idx: int) -> Optional[Tensor]:
        if self.collecting_statistics():
            with torch.no_grad():
                self.window_loss(batch, 0, 1)
            return None  # no optimizer step
        free_frames, trained = self.frames_to_train(self.global_step)
        if trained > 1:  # an optimizer step after every frame
            loss, extra = self.window_loss(batch, free_frames, trained, self._optimizer_step)
        else:
            loss, extra = self.window_loss(batch, free_frames, trained)
            self._optimizer_step(loss)
        self.log_training_step(loss.detach(), {}, batch.num_chunks, extra)
        return loss.detach()

    def run_steps(self) -> Optional[int]:
        """The run's optimizer steps (the trainer's ``max_steps``); ``None`` without one,
        with a warning unless a :class:`~garmentgnn.training.TimeBudget` sets the rate."""
        try:
            trainer = self.trainer
        except RuntimeError:  # not attached to a Trainer
            return None
        if trainer.max_steps and trainer.max_steps > 0:
            return int(trainer.max_steps)
        if not any(isinstance(c, TimeBudget) for c in trainer.callbacks):
            rank_zero_warn("RolloutModule: no --trainer.max_steps and no decay_steps: the "
                           "learning rate stays at lr; give either to decay it")
        return None

    def configure_optimizers(self):
        hp = self.hparams
        opt = torch.optim.Adam(self.parameters(), lr=hp.lr)
        floor = hp.lr_min / hp.lr
        steps = hp.decay_steps or self.run_steps()

        def factor(step: int) -> float:
            return 1.0 if steps is None else max(floor, hp.decay ** (step / steps))

        sched = torch.optim.lr_scheduler.LambdaLR(opt, factor)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    # -- rollouts -------------------------------------------------------------------------
    def start_states(self, batch: GarmentInputs, motion: SceneMotion,
                     start: Union[str, Tensor, None] = None) -> Tuple[Tensor, Tensor]:
        """The garment ``[V, 3]`` at frames 0 and 1 that a rollout of ``batch`` starts
        from: ``start`` (default the module's) names one of :data:`START_STATES`, or is
        the garment ``[2, V, 3]`` of those frames from elsewhere (another method's
        prediction, e.g. a frame-parallel one: no ground truth)."""
        if isinstance(start, Tensor):
            V = motion.lbs.shape[1]
            if start.dim() != 3 or start.shape[0] < 2 or tuple(start.shape[1:]) != (V, 3):
                raise ValueError(f"`start`: the garment of frames 0 and 1 must be [2, {V}, 3] "
                                 f"(these inputs' {V} vertices), got {list(start.shape)}")
            if not torch.isfinite(start[:2]).all():
                raise ValueError("`start`: the garment of frames 0 and 1 is not finite")
            return start[0].to(motion.lbs), start[1].to(motion.lbs)
        start = start or self.hparams.start
        gt = batch.get("gt")
        if start in ("gt", "drape") and gt is None:
            raise ValueError(f"`start`: {start!r} starts from the simulated garment, which "
                             f"these inputs lack; start from 'lbs' or 'preroll'")
        if start == "gt":
            return gt[0], gt[1]
        if start == "drape":
            return gt[0], gt[0]
        if start == "preroll":
            return motion.lbs[0], motion.lbs[0]
        return motion.lbs[0], motion.lbs[1]

    def rollout(self, batch: GarmentInputs, start: Union[str, Tensor, None] = None) -> Tensor:
        """The garment ``[T, V, 3]`` of ``batch``'s frames, rolled out from ``start``
        (:meth:`start_states`)."""
        if batch.num_frames < 3:
            raise ValueError(f"`batch`: a rollout needs at least 3 frames (two to start "
                             f"from), got {batch.num_frames}")
        start = self.hparams.start if start is None else start
        if isinstance(start, str) and start == "preroll":
            # the first frame held for the pre-roll, then the motion
            k = self.hparams.preroll_frames
            held = batch.select(torch.cat([torch.zeros(k, dtype=torch.long),
                                           torch.arange(batch.num_frames)]))
            motion = self.model.scene_motion(held)
            x0, x1 = self.start_states(held, motion, start)
            return self.model.rollout(held, x0, x1, motion)[k:]
        motion = self.model.scene_motion(batch)
        x0, x1 = self.start_states(batch, motion, start)
        return self.model.rollout(batch, x0, x1, motion)

    def predict_garment(self, batch: GarmentInputs) -> Tensor:
        return self.rollout(batch)

    def predict_sequence(self, batch: GarmentInputs, start: Optional[Tensor] = None
                         ) -> Tensor:
        """The rollout from the LBS garment of the first two frames, or from ``start``:
        the garment ``[2, V, 3]`` of frames 0 and 1 that a frame-parallel method predicts
        (no simulated frame either way; :meth:`start_states`)."""
        return self.rollout(batch, start="lbs" if start is None else start)

    def timed_call(self, item: GarmentInputs, batch: int) -> Callable[[], Any]:
        """One step of ``batch`` garments (the item's first three frames, as ``batch``
        independent garments), the scene's motion prepared outside the call."""
        it = GarmentInputs.collate([item.select(torch.arange(3))] * batch)
        m = self.model.scene_motion(it)
        return lambda: self.model.step(it, m, 2, m.lbs[0], m.lbs[1])

    @classmethod
    def bench_overrides(cls, *, schedule_window: int,
                        shortest_sequence: int) -> Dict[str, Callable[[Any], Any]]:
        """The rollout and the window cut to what the shortest training sequence holds
        (a window of ``2 + rollout`` frames)."""
        fitted: Dict[str, int] = {}

        def rollout(n: int) -> int:
            fitted["rollout"] = max(1, min(n, shortest_sequence - 2))
            return fitted["rollout"]
        return {"model.init_args.rollout": rollout,
                "data.chunk": lambda c: min(c, 2 + fitted["rollout"])}

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
