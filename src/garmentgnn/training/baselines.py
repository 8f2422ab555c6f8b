"""The DA-, HOOD- and NCS-style baselines as one LightningModule, trained by the same
Lightning ``Trainer``, data module (:class:`GarmentDataModule`: ``batch_size`` chunks per
step, the epoch order of :class:`EpochShuffleSampler`) and checkpointing as GarTrans; a
batch's loss is the mean of its chunks' (DA-style predicts a batch in one pass, HOOD- and
NCS-style, whose models take one garment at a time, chunk by chunk).  A method is a model
plus its losses plus a recipe (``garmentgnn/recipes/baselines/*.yaml``,
:func:`garmentgnn.training.load_recipe`):

* ``da`` (:class:`~garmentgnn.models.baselines.DAStyle`): supervised, the supervised
  terms of :class:`GarTransLoss` against the simulated garment; predicts each frame
  from its pose.
* ``hood`` (:class:`~garmentgnn.models.baselines.HOODStyle`): the physics terms only
  (inertia included); trained one step at a time on its own rollout of each chunk,
  started from the LBS garment of the two frames before the chunk (or, with
  ``start_state="own"``, from its own states there, left by its latest training
  rollout of the chunk before), inputs detached between steps; HOOD's recipe adds noise
  on the input positions (``rollout_noise``), rollouts restarted from the LBS garment
  every ``rollout`` frames, growing over ``rollout_ramp`` steps, and a learning-rate
  warm-up (``warmup``); predicts by an autoregressive rollout over the whole input from
  the LBS garment of its first two frames, pinned vertices driven by LBS.
* ``ncs`` (:class:`~garmentgnn.models.baselines.NCSStyle`): garment-specific and
  self-supervised -- the physics terms on its own predictions of three consecutive
  frames; the chunks' simulated positions are removed before the loss ever sees them.
  One model per garment (its ``num_vertices``): ``garmentgnn train`` links it from the data
  module, whose training sequences must then all show one garment on one body.
"""
from __future__ import annotations

from typing import Any, Callable, Dict, Optional, Tuple, Union

import torch
from torch import Tensor

from garmentgnn.losses.gartrans_loss import GarTransLoss
from garmentgnn.models.baselines import CoarseLevel, DAStyle, HOODStyle, NCSStyle
from garmentgnn.models.inputs import GarmentInputs
from garmentgnn.training.base import COMPILE_SEARCH, GarmentModule
from garmentgnn.training.module import chunk_mean_loss, loss_inputs

__all__ = ["BASELINE_METHODS", "BaselineModule"]

#: the methods this module trains
BASELINE_METHODS = ("da", "hood", "ncs")
#: where a ``hood`` training rollout starts (``start_state``)
START_STATES = ("lbs", "own")
#: checkpoint key of the kept start states (``start_state="own"``)
STATES_KEY = "garmentgnn_start_states"


def ramped_length(rollout: int, ramp: int, step: int) -> int:
    """The training rollout's length at optimizer step ``step``: ``1 + (rollout - 1)
    min(1, step / ramp)`` rounded down, growing from 1 to ``rollout`` over ``ramp`` steps
    (HOOD: by one every 5,000 iterations); ``rollout`` from the start where ``ramp`` is 0."""
    if not ramp:
        return rollout
    return 1 + int((rollout - 1) * min(1.0, step / ramp))


def _check_rollout(rollout: int, noise: float, ramp: int) -> None:
    if not isinstance(rollout, int) or isinstance(rollout, bool) or rollout < 1:
        raise ValueError(f"`rollout`: expected frames >= 1, got {rollout!r}")
    if not (isinstance(noise, (int, float)) and noise >= 0):
        raise ValueError(f"`rollout_noise`: expected metres >= 0, got {noise!r}")
    if not isinstance(ramp, int) or isinstance(ramp, bool) or ramp < 0:
        raise ValueError(f"`rollout_ramp`: expected optimizer steps >= 0, got {ramp!r}")


class BaselineModule(GarmentModule):
    """A baseline trained by Lightning: the module is handed its model (Lightning's system
    style), whose class is the method -- :class:`DAStyle` (``da``), :class:`HOODStyle`
    (``hood``) or :class:`NCSStyle` (``ncs``) -- and holds the training settings.  In YAML
    (the recipes ``garmentgnn/recipes/baselines/*.yaml``): ``model: init_args: model: class_path:
    garmentgnn.models.baselines.DAStyle``, its sizes linked from the data module.

    Args:
        model: the baseline model to train.
        lr: Adam learning rate.
        loss: :class:`GarTransLoss` settings (``enabled``, ``weights``, ...).
        coarse: ``hood``'s coarse level (``ratio``, ``k`` of :meth:`CoarseLevel.build`).
        fps: the data's frame rate (the loss's ``dt = 1 / fps``; a HOOD-style model must
            step the same ``dt``).
        start_state: ``hood``: where a training chunk's rollout starts. ``"lbs"``: the
            LBS garment of the two frames before the chunk. ``"own"``: the model's own
            states at those two frames, kept from its latest training rollout of the
            chunk before it (so over the epochs the rollouts chain through whole
            sequences, the states a test rollout reaches); the LBS garment where there
            is none yet (a sequence's first chunk, the first epoch) or where that state
            is on average more than ``max_start_drift`` metres from LBS.  The kept states
            (two frames per chunk) travel in the checkpoint; with DDP each process keeps
            those of the chunks it trained, and the checkpoint holds rank 0's.
        max_start_drift: see ``start_state``.
        rollout, rollout_ramp, rollout_noise: ``hood``'s training rollouts (HOOD's
            recipe, detached steps): a rollout restarts from the LBS garment of the two
            frames before it every ``rollout`` frames of a chunk (``None``: one rollout
            per chunk), ``rollout`` growing from 1 over the first ``rollout_ramp``
            optimizer steps (:func:`ramped_length`); every step's current and
            previous positions get Gaussian noise of ``rollout_noise`` metres, and its
            inertial prediction is taken from those noisy positions (HOOD: 3 mm).
        warmup: the learning rate grows linearly over the first ``warmup`` optimizer
            steps (HOOD: 100), on top of any schedule.  Gradient clipping (HOOD: 1.0)
            is the Trainer's ``gradient_clip_val``.
        compile_search: ``torch.compile`` the collision loss's nearest-face search, unless
            ``loss`` sets its own ``compile_search``
            (:data:`~garmentgnn.training.base.COMPILE_SEARCH`).
    """

    #: the method of each model class
    METHODS = {DAStyle: "da", HOODStyle: "hood", NCSStyle: "ncs"}

    def __init__(self, model: Union[DAStyle, HOODStyle, NCSStyle], lr: float = 1e-3,
                 loss: Optional[Dict[str, Any]] = None, coarse: Optional[Dict[str, Any]] = None,
                 fps: float = 30.0, start_state: str = "lbs",
                 max_start_drift: float = 0.25, rollout: Optional[int] = None,
                 rollout_ramp: int = 0, rollout_noise: float = 0.0, warmup: int = 0,
                 compile_search: bool = COMPILE_SEARCH) -> None:
        super().__init__()
        if type(model) not in self.METHODS:
            raise TypeError(f"`model`: expected a DAStyle, HOODStyle or NCSStyle, got "
                            f"{type(model).__name__}")
        #: ``"da"``, ``"hood"`` or ``"ncs"``
        self.method = self.METHODS[type(model)]
        if start_state not in START_STATES:
            raise ValueError(f"`start_state`: expected one of {START_STATES}, got "
                             f"{start_state!r}")
        if start_state != "lbs" and self.method != "hood":
            raise ValueError(f"`start_state`: only the autoregressive HOOD-style model has a "
                             f"start state; leave it at 'lbs' for {type(model).__name__}")
        if not max_start_drift > 0:
            raise ValueError(f"`max_start_drift`: expected metres > 0, got {max_start_drift!r}")
        _check_rollout(1 if rollout is None else rollout, rollout_noise, rollout_ramp)
        if (rollout is not None or rollout_ramp or rollout_noise) and self.method != "hood":
            raise ValueError(f"`rollout`, `rollout_ramp`, `rollout_noise`: only the "
                             f"autoregressive HOOD-style model rolls out in training; leave "
                             f"them unset for {type(model).__name__}")
        if not isinstance(warmup, int) or isinstance(warmup, bool) or warmup < 0:
            raise ValueError(f"`warmup`: expected optimizer steps >= 0, got {warmup!r}")
        if not fps > 0:
            raise ValueError(f"`fps`: expected frames per second > 0, got {fps!r}")
        self.dt = 1.0 / fps
        if self.method == "hood" and abs(model.dt - self.dt) > 1e-9 * self.dt:
            raise ValueError(f"`fps`: the HOOD-style model steps dt = {model.dt:g} s, the "
                             f"loss {self.dt:g} s; give the model dt = 1 / fps")
        self.save_hyperparameters(ignore=["model"])
        self.hand_model(model)
        lk = dict(loss or {})
        lk.setdefault("compile_search", bool(compile_search))
        self.loss_fn = GarTransLoss(lk.pop("weights", None), **lk)
        self._coarse: Dict[str, CoarseLevel] = {}  # HOOD's coarse level per sequence
        # start_state "own": sequence id -> frame -> the state of the latest rollout (CPU)
        self._states: Dict[str, Dict[int, Tensor]] = {}

    # -- the method protocol (:class:`GarmentModule`) -----------------------------------
    #: each method's row name in tables
    TABLE_NAMES = {"da": "DA-style", "hood": "HOOD-style", "ncs": "NCS-style"}

    @property
    def autoregressive(self) -> bool:
        """HOOD-style rolls out one frame after another; DA- and NCS-style are
        frame-parallel."""
        return self.method == "hood"

    @property
    def min_frames(self) -> int:
        return 2 if self.method == "hood" else 1

    @classmethod
    def trains_per_garment(cls, model: type) -> bool:
        """NCS-style: one model per (garment, body), trained on its poses."""
        return cls.METHODS.get(model) == "ncs"

    @property
    def table_name(self) -> str:
        return self.TABLE_NAMES[self.method]

    @property
    def timing_note(self) -> str:
        return ("one autoregressive step of `batch` independent sequences per call"
                if self.autoregressive else "one call predicting `batch` frames")

    def timed_call(self, item: GarmentInputs, batch: int) -> Callable[[], Any]:
        """One call predicting ``batch`` frames, or (HOOD-style) one autoregressive step
        of ``batch`` frames."""
        it = item.cycled(batch)
        if not self.autoregressive:
            return lambda: self(it)
        coarse, lbs = self.coarse_level(it), it.skinned()
        prev, curr = it.history_slot(-3).skinned(), it.history_slot(-2).skinned()
        return lambda: self.model.step(it, coarse, prev, curr, it.body_pos, lbs)

    def min_history(self) -> Tuple[int, str]:
        if self.method == "hood":
            return 2, ("HOOD-style starts each rollout from the LBS garment of the 2 frames "
                       "before a chunk")
        if self.method == "ncs":
            h = self.model.history
            return h + 2, (f"NCS-style (model history {h}) reads {h + 3} poses per frame "
                           f"for its loss's inertia term")
        return super().min_history()

    # -- pieces ---------------------------------------------------------------------
    def coarse_level(self, inp: GarmentInputs) -> CoarseLevel:
        """HOOD's coarse level of ``inp``'s garment (built once per sequence and device)."""
        key = f"{inp.get('seq_id') or id(inp.rest_pos)}@{inp.rest_pos.device}"
        if key not in self._coarse:
            c = self.hparams.coarse or {}
            self._coarse[key] = CoarseLevel.build(inp.rest_pos, inp.faces, **c)
        return self._coarse[key]

    def _ncs_poses(self, inp: GarmentInputs, j: int) -> Tuple[Tensor, Tensor]:
        """(rotations ``[B, h + 1, S, 3]``, translation ``[B, 3]``) ending at history
        slot ``j`` of ``inp``."""
        h = self.model.history
        if inp.num_vertices != self.model.num_vertices:
            raise ValueError(f"`inp`: this NCS-style model is specific to a garment of "
                             f"{self.model.num_vertices} vertices, sequence "
                             f"{inp.get('seq_id')!r} has {inp.num_vertices}; give the data "
                             f"module one garment's sequences (--data.train_ids)")
        if inp.rotations.shape[1] < h + 3:
            raise ValueError(f"`inp`: NCS with model history {h} needs a pose history of "
                             f"{h + 3} frames, the data gives {inp.rotations.shape[1]} "
                             f"(--data.history {h + 2})")
        end = inp.rotations.shape[1] + j + 1
        return inp.rotations[:, end - h - 1:end], inp.translation[:, end - 1]

    # -- prediction -----------------------------------------------------------------
    def forward(self, inp: GarmentInputs) -> Tensor:
        """The garment ``[B, V, 3]`` of every frame of ``inp`` (HOOD: a rollout over
        the frames in order, from the LBS garment of the first two)."""
        m = self.method
        if m == "da":  # one chunk or a batch of them (the pose of frame t: history's last)
            return self.model(inp, inp.rotations[..., -1, :, :], inp.translation[..., -1, :])
        if m == "ncs":
            return self.model(inp, *self._ncs_poses(inp, -1))
        lbs = inp.skinned()
        if lbs.shape[0] < 2:
            raise ValueError("`inp`: a HOOD-style rollout needs at least 2 frames")
        return self.model.rollout(inp, self.coarse_level(inp), lbs[0], lbs[1], inp.body_pos,
                                  pinned_targets=lbs)

    def predict_garment(self, batch: GarmentInputs) -> Tensor:
        return self(batch)

    # -- training -------------------------------------------------------------------
    def training_loss(self, batch: GarmentInputs) -> Tensor:
        return self.compute_loss(batch)[0]

    def compute_loss(self, inp: GarmentInputs) -> Tuple[Tensor, Dict[str, Tensor]]:
        """The loss of one chunk, or the mean over the chunks of a ``Batch`` (``da``: one
        forward over the union graph; ``hood`` and ``ncs``, whose models take one garment
        at a time: each chunk on its own)."""
        m = self.method
        if m == "da":  # a batch in one forward over the union graph
            return chunk_mean_loss(self.loss_fn, inp, self(inp), self.dt)
        if inp.num_chunks > 1:
            losses = [self.compute_loss(c) for c in inp.chunks()]
            n = len(losses)
            return (sum(t for t, _ in losses) / n,
                    {k: sum(t[k] for _, t in losses) / n for k in losses[0][1]})
        if m == "ncs":
            inp = inp.without_ground_truth()  # self-supervised: never the simulation
            p = [self.model(inp, *self._ncs_poses(inp, j)) for j in (-1, -2, -3)]
            return self.loss_fn(loss_inputs(inp, p[0], self.dt, predicted=2 * p[1] - p[2],
                                            ground_truth=False))
        coarse = self.coarse_level(inp)
        lbs = inp.skinned()
        before = self._lbs_before(inp)
        x_prev, x_curr = self._start(inp, before)
        k = self.rollout_length()
        noise = self.hparams.rollout_noise
        preds, inertial = [], []
        for b in range(lbs.shape[0]):  # one step at a time on its own rollout
            if k and b and b % k == 0:  # a new rollout, from the LBS garment of frames b-2, b-1
                x_prev, x_curr = (lbs[b - 2] if b > 1 else before[1]), lbs[b - 1]
            p, c = x_prev, x_curr
            if noise:  # HOOD: noise on the current and previous positions
                p, c = p + noise * torch.randn_like(p), c + noise * torch.randn_like(c)
            nxt = self.model.step(inp, coarse, p[None], c[None],
                                  inp.body_pos[b:b + 1], lbs[b:b + 1])[0]
            preds.append(nxt)
            inertial.append(2 * c - p)
            x_prev, x_curr = x_curr, nxt.detach()
        self._keep(inp, x_prev, x_curr)
        return self.loss_fn(loss_inputs(inp, torch.stack(preds), self.dt,
                                        predicted=torch.stack(inertial), ground_truth=False))

    def rollout_length(self) -> Optional[int]:
        """``hood``: the frames of a training rollout at this step (``None``: a chunk's
        rollout is never restarted)."""
        hp = self.hparams
        if hp.rollout is None:
            return None
        return ramped_length(hp.rollout, hp.rollout_ramp, self.global_step)

    @staticmethod
    def _lbs_before(inp: GarmentInputs) -> Tuple[Tensor, Tensor]:
        """The LBS garment ``[V, 3]`` at the two frames before ``inp``'s first (clamped at
        the sequence's frame 0)."""
        first = inp.select(torch.tensor([0]))
        return first.history_slot(-3).skinned()[0], first.history_slot(-2).skinned()[0]

    def _start(self, inp: GarmentInputs,
               lbs_before: Optional[Tuple[Tensor, Tensor]] = None) -> Tuple[Tensor, Tensor]:
        """``hood``: the states ``[V, 3]`` at the two frames before ``inp``'s first (see
        ``start_state``); ``lbs_before``: :meth:`_lbs_before` of ``inp`` where known."""
        x_prev, x_curr = lbs_before or self._lbs_before(inp)
        frames, seq = inp.get("frames"), inp.get("seq_id")
        if self.hparams.start_state != "own" or frames is None or seq is None:
            return x_prev, x_curr
        t0 = int(frames[0])
        kept = self._states.get(seq, {})
        if t0 < 2 or t0 - 2 not in kept or t0 - 1 not in kept:
            return x_prev, x_curr
        own_prev, own_curr = (kept[t].to(x_curr) for t in (t0 - 2, t0 - 1))
        drift = float((own_curr - x_curr).norm(dim=-1).mean())
        if not drift <= self.hparams.max_start_drift:  # also NaN
            return x_prev, x_curr
        return own_prev, own_curr

    def _keep(self, inp: GarmentInputs, x_prev: Tensor, x_curr: Tensor) -> None:
        """``start_state="own"``: keep the rollout's states at ``inp``'s last two frames."""
        frames, seq = inp.get("frames"), inp.get("seq_id")
        if self.hparams.start_state == "own" and frames is not None and seq is not None:
            last = int(frames[-1])
            self._states.setdefault(seq, {}).update(
                {last - 1: x_prev.detach().cpu(), last: x_curr.detach().cpu()})

    def on_save_checkpoint(self, checkpoint: Dict[str, Any]) -> None:
        if self._states:
            checkpoint[STATES_KEY] = self._states
        super().on_save_checkpoint(checkpoint)

    def on_load_checkpoint(self, checkpoint: Dict[str, Any]) -> None:
        super().on_load_checkpoint(checkpoint)
        self._states = dict(checkpoint.get(STATES_KEY, {}))

    def training_step(self, batch: GarmentInputs, batch_idx: int) -> Tensor:
        total, terms = self.compute_loss(batch)
        self.log_training_step(total, terms, batch.num_frames * batch.num_chunks)
        return total

    def configure_optimizers(self):
        return torch.optim.Adam(self.parameters(), lr=self.hparams.lr)

    def warmup_factor(self) -> float:
        """The factor on the learning rate at this step: ``min(1, (step + 1) / warmup)``."""
        w = self.hparams.warmup
        return min(1.0, (self.global_step + 1) / w) if w else 1.0

    def optimizer_step(self, epoch, batch_idx, optimizer, optimizer_closure=None) -> None:
        """The optimizer's step at the warmed-up rate (:meth:`warmup_factor` times the rate
        its schedule or :class:`TimeBudget` set), which is put back after the step."""
        f = self.warmup_factor()
        rates = [g["lr"] for g in optimizer.param_groups]
        for g in optimizer.param_groups:
            g["lr"] *= f
        try:
            super().optimizer_step(epoch, batch_idx, optimizer, optimizer_closure)
        finally:
            for g, lr in zip(optimizer.param_groups, rates):
                g["lr"] = lr
