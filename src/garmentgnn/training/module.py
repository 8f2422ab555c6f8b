"""GarTrans as a LightningModule (paper §4.1: Adamax, lr 0.003, cosine annealing).

One training step = one chunk (one garment on one body, ``B`` frames, see
:mod:`garmentgnn.training.datamodule`): ``encode_static`` once, ``forward`` on the
``B`` frames in parallel, then :class:`GarTransLoss`.  Which loss terms are active,
the supervised scale and whether the rest-pose branch is frozen are switched by
:class:`garmentgnn.training.ProgressiveSchedule`.
"""
from __future__ import annotations

from typing import Any, ClassVar, Dict, Iterable, Iterator, Optional

import torch

from garmentgnn.losses.gartrans_loss import SUPERVISED, GarTransLoss, LossInputs, vertex_loss
from garmentgnn.models import GarTrans, StaticFeatures
from garmentgnn.models.inputs import GarmentInputs
from garmentgnn.training.base import GarmentModule


def loss_inputs(inp: GarmentInputs, pred: torch.Tensor, dt: float,
                predicted: Optional[torch.Tensor] = None, ground_truth: bool = True
                ) -> LossInputs:
    """The :class:`LossInputs` of a prediction ``pred [B, V, 3]`` of ``inp``'s frames;
    ``predicted``: the inertial prediction ``2 x_{t-1} - x_{t-2}`` (inertia term);
    ``ground_truth=False`` leaves the simulated garment out (self-supervised methods)."""
    return LossInputs(pred=pred, faces=inp.faces, gt=inp.get("gt") if ground_truth else None,
                      body_pos=inp.get("body_pos"), body_faces=inp.get("body_faces"),
                      mass=inp.get("mass"), rest=inp.get("rest"), predicted=predicted, dt=dt)


#: ``optimizer`` choices (the paper: Adamax)
OPTIMIZERS = {"adamax": torch.optim.Adamax, "adam": torch.optim.Adam,
              "adamw": torch.optim.AdamW}

#: the rest-pose processing submodule frozen in the third phase (§4.1)
REST_BRANCH = ("rest_fc", "rest_attn", "nystrom_fc", "body_fc")


class GarTransModule(GarmentModule):
    """GarTrans trained by Lightning.  The model defaults are :class:`GarTrans`'s (and
    ``garmentgnn/configs/gartrans.yaml``'s); ``GarTransModule(..., skin_prior=False,
    **PAPER_FORM)`` is the paper's form.

    Args:
        num_joints, num_body_vertices, nystrom_dim: model sizes (see
            :attr:`GarmentDataModule.dims`).
        rest_layer, blend_layer, dynamic_layer: registry names of the attention slots.
        heads, fps: model settings.
        lr: Adamax learning rate; ``t_max``: CosineAnnealingLR period in epochs
            (default: the trainer's ``max_epochs``); ``eta_min``.
        loss_weights, edge_reduction, collision_margin: :class:`GarTransLoss` settings.
        enabled, supervised_scale: initial loss terms / scale (phase 1).
        use_body: feed the body-vertex-to-joint distances (else the learned code).
        skin_prior: start the learned skinning weights from the body's weights
            transferred to the garment (``encode_static(skin_prior=...)``); ``False`` is
            the paper's from-scratch ``W^t``.
        lbs_start: gates on what the learned branches add to LBS (:class:`GarTrans`'s
            ``lbs_start``, started at ``gate_init``); needs ``skin_prior``.  ``False``:
            the paper's form.
        collision_projection: margin (metres) of GarTrans's last step that moves
            garment vertices out of the body (:class:`GarTrans`); ``None``: off (the
            paper).  Applied in training and inference alike.
        blend_shape: ``False`` leaves out GarTrans's blend shape ``B^t`` (``True``: the
            paper).
        strain_limit: sweeps of GarTrans's strain-limiting step (``0``: none, the paper).
        compile_search: ``torch.compile`` the nearest-body-face search of the collision
            projection and the collision loss (same results; see docs/model.md).
        gate_init, accel_unit, garment_state, input_norm, local_frame, motion_history:
            :class:`GarTrans` settings.
        optimizer: ``"adamax"`` (the paper), ``"adam"`` or ``"adamw"``.
        state_noise: ``garment_state`` training: the standard deviation (metres) of the
            Gaussian noise added to the simulated frame ``t-1`` given as the state
            (MeshGraphNets' and HOOD's noise injection: the model learns to correct the
            errors its own rollout makes).
        state_dropout: ``garment_state`` training: the share of training chunks given no
            state (the frame-parallel inputs), so that a rollout can start from no state.
        state_rollout: ``garment_state`` training on the model's own rollout of each
            chunk (:meth:`GarTrans.rollout` from the simulated frames before the chunk,
            gradients through every step) instead of the simulated previous frames of
            every frame (teacher forcing).
        num_vertices, history: accepted (and ignored) so that the data module's sizes
            are linked to every method alike (:class:`BaselineModule` reads them).
    """

    def __init__(self, num_joints: int, num_body_vertices: int, nystrom_dim: int = 16,
                 rest_layer: str = "gt", blend_layer: str = "gt", dynamic_layer: str = "sat",
                 heads: int = 4, fps: float = 30.0, lr: float = 3e-3,
                 t_max: Optional[int] = None, eta_min: float = 0.0,
                 loss_weights: Optional[Dict[str, float]] = None,
                 edge_reduction: str = "sum", collision_margin: float = 2e-3,
                 enabled: Iterable[str] = SUPERVISED, supervised_scale: float = 1.0,
                 use_body: bool = True, skin_prior: bool = True, lbs_start: bool = True,
                 collision_projection: Optional[float] = 0.002, blend_shape: bool = False,
                 strain_limit: int = 10, compile_search: bool = False, gate_init: float = 1.0,
                 accel_unit: Optional[float] = 0.01, optimizer: str = "adamax",
                 garment_state: bool = False, state_noise: float = 0.0,
                 state_dropout: float = 0.0, state_rollout: bool = False,
                 input_norm: bool = True, local_frame: bool = True,
                 motion_history: int = 1, num_vertices: Optional[int] = None,
                 history: Optional[int] = None) -> None:
        super().__init__()
        if lbs_start and not skin_prior:
            raise ValueError("`lbs_start`: starting from LBS needs `skin_prior=True` "
                             "(or set `lbs_start=False`)")
        enabled = sorted(enabled)
        self.save_hyperparameters()
        self.model = GarTrans(num_joints, num_body_vertices, nystrom_dim=nystrom_dim,
                              rest_layer=rest_layer, blend_layer=blend_layer,
                              dynamic_layer=dynamic_layer, heads=heads, fps=fps,
                              lbs_start=lbs_start, collision_projection=collision_projection,
                              blend_shape=blend_shape, strain_limit=strain_limit,
                              compile_search=compile_search, gate_init=gate_init,
                              accel_unit=accel_unit, garment_state=garment_state,
                              input_norm=input_norm, local_frame=local_frame,
                              motion_history=motion_history)
        if not 0.0 <= state_dropout <= 1.0:
            raise ValueError(f"`state_dropout`: expected a share in [0, 1], got {state_dropout}")
        if not state_noise >= 0.0:
            raise ValueError(f"`state_noise`: expected a standard deviation >= 0 (metres), "
                             f"got {state_noise}")
        if optimizer not in OPTIMIZERS:
            raise ValueError(f"`optimizer`: expected one of {sorted(OPTIMIZERS)}, got "
                             f"{optimizer!r}")
        # only one of the body code paths is ever used; freeze the other (DDP requires
        # every trainable parameter to receive a gradient)
        unused = self.model.body_default if use_body else self.model.body_fc
        unused.requires_grad_(False)
        self.loss_fn = GarTransLoss(loss_weights, enabled=enabled,
                                    supervised_scale=supervised_scale,
                                    collision_margin=collision_margin,
                                    edge_reduction=edge_reduction,
                                    compile_search=compile_search)

    # -- phase controls (used by ProgressiveSchedule) ---------------------------------
    def set_rest_branch_frozen(self, frozen: bool) -> None:
        unused = self.model.body_default if self.hparams.use_body else self.model.body_fc
        never = {id(p) for p in unused.parameters()} if isinstance(unused, torch.nn.Module) \
            else {id(unused)}
        for name in REST_BRANCH:
            for p in getattr(self.model, name).parameters():
                p.requires_grad_(not frozen and id(p) not in never)
                if frozen:
                    p.grad = None

    def rest_branch_parameters(self) -> Iterator[torch.nn.Parameter]:
        for name in REST_BRANCH:
            yield from getattr(self.model, name).parameters()

    # -- forward ------------------------------------------------------------------
    def encode_static(self, inp: GarmentInputs) -> StaticFeatures:
        """The static branch of one garment on one body (a data-module item)."""
        hp = self.hparams
        return self.model.encode_static(
            inp.rest_pos, inp.faces, inp.edge_index, inp.rest_joints, inp.nystrom,
            inp.get("body_joint_dists") if hp.use_body else None,
            inp.skin_weights if hp.get("skin_prior", False) else None)

    def forward(self, inp: GarmentInputs, static: Optional[StaticFeatures] = None,
                autoregressive: Optional[bool] = None) -> Dict[str, torch.Tensor]:
        """GarTrans on every frame of ``inp``: frame-parallel (the paper's mode), or
        ``autoregressive`` (:meth:`GarTrans.rollout`; the default with ``garment_state``,
        frame-parallel otherwise).  ``static``: a cached :meth:`encode_static` of the same
        garment (default: computed here)."""
        static = self.encode_static(inp) if static is None else static
        if autoregressive is None:
            autoregressive = self.model.garment_state
        run = self.model.rollout if autoregressive else self.model
        return run(static, inp.rest_pos, inp.faces, inp.edge_index, inp.rest_joints,
                   inp.parents, inp.rotations, inp.translation, body_pos=inp.get("body_pos"),
                   body_faces=inp.get("body_faces"))

    def predict_garment(self, batch: GarmentInputs) -> torch.Tensor:
        """:meth:`forward`'s garment ``[B, V, 3]`` (frame-parallel, or the rollout with
        ``garment_state``): what ``validate``, ``test`` and ``predict`` score."""
        return self(batch)["final"]

    def training_forward(self, inp: GarmentInputs) -> Dict[str, torch.Tensor]:
        """The prediction a training step scores: :meth:`forward` (frame-parallel), or
        with ``garment_state`` every frame of ``inp`` given the simulated frames
        ``t-2, t-1`` (``inp.gt_prev``) as its state, with ``state_noise`` on frame ``t-1``
        (teacher forcing), or the model's own rollout of the chunk from the frames before
        it (``state_rollout``); no state for a ``state_dropout`` share of the chunks."""
        if not self.model.garment_state:
            return self(inp)
        hp = self.hparams
        state = inp.get("gt_prev")
        if state is None:
            raise ValueError("`inp`: a model with `garment_state` trains on chunks with "
                             "`gt_prev` (the simulated frames t-2, t-1; GarmentDataModule's "
                             "training chunks carry them)")
        if hp.state_dropout and float(torch.rand(())) < hp.state_dropout:
            state = None
        elif hp.state_noise:
            noise = torch.randn_like(state[:, 1]) * hp.state_noise
            state = torch.stack([state[:, 0], state[:, 1] + noise], 1)
        args = (self.encode_static(inp), inp.rest_pos, inp.faces, inp.edge_index,
                inp.rest_joints, inp.parents, inp.rotations, inp.translation)
        kw = dict(body_pos=inp.get("body_pos"), body_faces=inp.get("body_faces"))
        if hp.get("state_rollout", False):
            return self.model.rollout(*args, state=None if state is None else state[0], **kw)
        return self.model(*args, state=state, **kw)

    def compute_loss(self, batch: GarmentInputs, out: Dict[str, torch.Tensor]):
        inp = loss_inputs(batch, out["final"], dt=1.0 / self.hparams.fps)
        return self.loss_fn(inp)  # NaN/inf raises NonFiniteLossError naming the term

    def training_step(self, batch: GarmentInputs, batch_idx: int):
        out = self.training_forward(batch)
        B = out["final"].shape[0]
        # raises NonFiniteLossError naming the term; Trainer.fit re-raises it (stops)
        total, terms = self.compute_loss(batch, out)
        with torch.no_grad():
            vert_err = vertex_loss(out["final"], batch["gt"]).mean()  # metres, unscaled
        self.log_training_step(total, terms, B, extra={"vert_err": vert_err})
        return {"loss": total, "vert_err": vert_err.detach(),
                "terms": {k: v.detach() for k, v in terms.items()}}

    # -- checkpoints (integrity and the former defaults: GarmentModule) -------------------
    #: switches whose default has changed, with the value a checkpoint that does not name
    #: them was trained with (the base's ``load_from_checkpoint`` builds it so; a
    #: checkpoint from before ``accel_unit`` existed gets its former value in
    #: ``on_load_checkpoint``, which a resumed fit runs too)
    former_defaults: ClassVar[Dict[str, Any]] = {"input_norm": False, "local_frame": False}

    def on_load_checkpoint(self, checkpoint: Dict[str, Any]) -> None:
        super().on_load_checkpoint(checkpoint)
        saved = checkpoint.get("hyper_parameters")
        if saved is not None and "accel_unit" not in saved:
            # saved before ``accel_unit`` existed: its dynamic output was an acceleration
            # (``a dt^2``), not the centimetres of today's default
            self.model.accel_unit = None
            self.hparams.accel_unit = None

    def configure_optimizers(self):
        opt = OPTIMIZERS[self.hparams.get("optimizer", "adamax")](self.parameters(),
                                                                   lr=self.hparams.lr)
        t_max = self.hparams.t_max
        if t_max is None:
            try:
                me = self.trainer.max_epochs
            except RuntimeError:  # not attached to a Trainer
                me = None
            t_max = me if me and me > 0 else 100
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=int(t_max),
                                                           eta_min=self.hparams.eta_min)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "epoch"}}
