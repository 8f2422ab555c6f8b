"""What every trained method shares: :class:`GarmentModule`, the LightningModule base of
:class:`~garmentgnn.training.GarTransModule` and :class:`~garmentgnn.training.BaselineModule`.

It holds the parts that do not depend on the method: the checkpoint integrity hooks
(:mod:`garmentgnn.training.integrity`), the training-step logging, the held-out metrics
of ``validate``/``test`` (:func:`garmentgnn.metrics.evaluate_inputs` on the valid
ground-truth frames, ``valid``, as every metric that reads the data; ``test`` scores
"LBS only" on the same frames beside the method, ``test_lbs/...``) and ``predict``.  A
method only says how it predicts a chunk (:meth:`GarmentModule.predict_garment`) and how
it trains (``training_step``, ``configure_optimizers``).
"""
from __future__ import annotations

import atexit
import contextvars
import inspect
import io
import os
from typing import Any, ClassVar, Dict, Optional, Tuple, Union

import lightning as L
import torch
import torch.distributed as dist
from torch import Tensor, nn

from garmentgnn.data.store import read_manifest
from garmentgnn.losses.gartrans_loss import NonFiniteLossError
from garmentgnn.metrics import evaluate_inputs
from garmentgnn.models.blocks import Configurable
from garmentgnn.models.inputs import GarmentInputs
from garmentgnn.training.configs import import_class
from garmentgnn.training.integrity import (CheckpointError, load_checkpoint_file,
                                           stamp_checkpoint, verify_checkpoint)

__all__ = ["LBS_PREFIX", "GarmentModule", "build_model"]

#: set while :meth:`GarmentModule.load_from_checkpoint` loads a file it has verified
_VERIFIED: contextvars.ContextVar[bool] = contextvars.ContextVar("checkpoint_verified",
                                                                default=False)

#: checkpoint key of the dataset a method was trained on (:func:`dataset_stamp`)
DATASET_KEY = "garmentgnn_dataset"


def dataset_stamp(datamodule: Any) -> Dict[str, Any]:
    """``{"root", "content_sha256"}`` of a data module's dataset (its manifest's content
    hash), saved in every checkpoint a fit writes; ``{}`` without one."""
    root = getattr(datamodule, "root", None)
    if root is None:
        return {}
    try:
        sha = read_manifest(root).get("content_sha256")
    except (OSError, ValueError):
        return {}
    return {"root": str(root), "content_sha256": sha} if sha else {}


#: the prefix of the "LBS only" metrics that ``test`` logs beside the method's ``test/...``
LBS_PREFIX = "test_lbs"


def _init_args(hparams: Dict[str, Any]) -> Dict[str, Any]:
    """The ``init_args`` of the model spec in ``hparams`` (``{}`` where it has none)."""
    spec = hparams.get("model")
    init = spec.get("init_args") if isinstance(spec, dict) else None
    return init if isinstance(init, dict) else {}


def _destroy_process_group() -> None:
    if dist.is_initialized():
        dist.destroy_process_group()


_exit_hook_registered = False


def destroy_gloo_group_at_exit() -> None:
    """Destroy the default process group when the interpreter exits, if it is gloo's
    (registered once per process).

    Lightning registers this for NCCL only.  A gloo group (DDP on CPU) left to the
    interpreter's own teardown was seen to abort a replica after a successful fit
    ("terminate called without an active exception"), which fails the whole
    ``ddp_spawn`` run."""
    global _exit_hook_registered
    if not _exit_hook_registered and dist.is_available() and dist.is_initialized() \
            and dist.get_backend() == "gloo":
        atexit.register(_destroy_process_group)
        _exit_hook_registered = True


class GarmentModule(L.LightningModule):
    """Base of the garment methods trained by ``garmentgnn train`` (a batch of chunks
    per training step, :class:`~garmentgnn.training.GarmentDataModule`), in
    Lightning's system style: the module is handed its model (``model=GarTrans(...)``;
    in YAML, ``model: init_args: model: class_path: ...``) and says how it trains it.
    """

    #: hyper-parameters that no longer exist, with the only value a checkpoint may hold
    #: for them (anything else was another model: :meth:`check_removed` refuses it)
    removed_switches: ClassVar[Dict[str, Any]] = {}
    #: the same for the model's own arguments (the ``init_args`` of its spec)
    removed_model_switches: ClassVar[Dict[str, Any]] = {}
    #: hyper-parameters that acted only with a removed model switch on: dropped, whatever
    #: their value, from a checkpoint whose model names those switches (its layout had them)
    inert_settings: ClassVar[Tuple[str, ...]] = ()

    @classmethod
    def check_removed(cls, hparams: Dict[str, Any], where: str = "checkpoint") -> None:
        """A :class:`CheckpointError` when ``hparams`` (or its model's ``init_args``)
        switch on a removed option."""
        init = _init_args(hparams)
        bad = {k: v[k] for v, switches in ((hparams, cls.removed_switches),
                                           (init, cls.removed_model_switches))
               for k, off in switches.items() if k in v and v[k] != off}
        if bad:
            what = ", ".join(f"{k}={v!r}" for k, v in sorted(bad.items()))
            raise CheckpointError(f"{where}: trained with {what}, an option measured not to "
                                  f"help and removed (docs/experiments.md); this version "
                                  f"cannot rebuild that model")

    def predict_garment(self, batch: GarmentInputs) -> Tensor:
        """The garment ``[B, V, 3]`` of every frame of ``batch``."""
        raise NotImplementedError(f"{type(self).__name__}: define predict_garment")

    def setup(self, stage: str) -> None:
        destroy_gloo_group_at_exit()  # on every replica, once its process group exists

    # -- training ---------------------------------------------------------------------
    def log_training_step(self, total: Tensor, terms: Dict[str, Tensor], batch_size: int,
                          extra: Optional[Dict[str, Tensor]] = None) -> None:
        """Log a step's loss (``train/loss``, per step and epoch), its terms and ``extra``
        values (``train/<name>``, epoch means); a non-finite total raises
        :class:`NonFiniteLossError`.  DDP: epoch means over every replica's chunks."""
        if not torch.isfinite(total):
            raise NonFiniteLossError(f"loss 'total' is {float(total)}")
        self.log("train/loss", total, prog_bar=True, on_step=True, on_epoch=True,
                 batch_size=batch_size, sync_dist=True)
        for k, v in {**(extra or {}), **terms}.items():
            self.log(f"train/{k}", v, on_step=False, on_epoch=True, batch_size=batch_size,
                     sync_dist=True)

    # -- held-out metrics -------------------------------------------------------------
    def _score(self, pred: Tensor, batch: GarmentInputs, prefix: str) -> Dict[str, float]:
        """The metrics of the valid ground-truth frames (``batch.valid``,
        :meth:`garmentgnn.data.SequenceChunks.valid`; a chunk with none is not scored),
        logged as frame-weighted epoch means."""
        keep = batch.get("valid")
        frames = pred.shape[0] if keep is None else int(keep.sum())
        if frames == 0:
            return {}
        metrics = evaluate_inputs(pred, batch, keep)
        for k, v in metrics.items():
            self.log(f"{prefix}/{k}", v, on_epoch=True, batch_size=frames)
        return metrics

    def validation_step(self, batch: GarmentInputs, batch_idx: int) -> Dict[str, float]:
        """The paper's metrics of the prediction (``val/...``, frame-weighted epoch means)."""
        return self._score(self.predict_garment(batch), batch, "val")

    def test_step(self, batch: GarmentInputs, batch_idx: int) -> Dict[str, float]:
        """The paper's metrics on the data module's test split: the method's (``test/...``)
        and, on the same frames, the rest garment skinned by LBS (``test_lbs/...``)."""
        self._score(batch.skinned(), batch, LBS_PREFIX)
        return self._score(self.predict_garment(batch), batch, "test")

    def predict_step(self, batch: GarmentInputs, batch_idx: int,
                     dataloader_idx: int = 0) -> Dict[str, Any]:
        """``{"seq_id", "frames" [B], "positions" [B, V, 3]}`` of one chunk."""
        return {"seq_id": batch.get("seq_id"), "frames": batch.get("frames"),
                "positions": self.predict_garment(batch).detach()}

    # -- checkpoint integrity (garmentgnn.training.integrity) ---------------------------
    def on_save_checkpoint(self, checkpoint: Dict[str, Any]) -> None:
        try:
            datamodule = self.trainer.datamodule
        except RuntimeError:  # not attached to a Trainer
            datamodule = None
        stamp = dataset_stamp(datamodule)
        if stamp:
            checkpoint[DATASET_KEY] = stamp
        stamp_checkpoint(checkpoint)

    # -- the model it is handed (Lightning's system style) --------------------------------
    def hand_model(self, model: nn.Module) -> None:
        """Keep ``model`` (``self.model``) and its spec (``hparams["model"]``:
        ``{"class_path", "init_args"}``, :class:`~garmentgnn.models.blocks.Configurable`)
        so a checkpoint rebuilds it.  Called by ``__init__`` after
        ``save_hyperparameters(ignore=["model"])``."""
        if not isinstance(model, Configurable) or not isinstance(model, nn.Module):
            raise TypeError(f"`model`: expected a garmentgnn model (GarTrans, DAStyle, "
                            f"HOODStyle, NCSStyle), got {type(model).__name__}; build it "
                            f"first, e.g. {type(self).__name__}(GarTrans(**datamodule.dims))")
        self.model = model
        # LightningCLI's rebuild recipe (the spec rebuilds the model everywhere), and the
        # sizes it links to every module's arguments, kept by this one's model instead
        params = inspect.signature(type(self).__init__).parameters
        for k in [k for k in self.hparams if k not in params and k != "_class_path"]:
            self.hparams.pop(k)
        self.hparams["model"] = model.spec()

    @property
    def nystrom_dim(self) -> Optional[int]:
        """The Nyström width the model reads (``None``: it reads none)."""
        return getattr(self.model, "init_args", {}).get("nystrom_dim")

    @classmethod
    def upgrade_hparams(cls, saved: Dict[str, Any]) -> Dict[str, Any]:
        """A checkpoint's hyper-parameters in today's layout (``model``: the model's
        spec).  The base returns them as they are; a module whose earlier layout
        differs converts it here."""
        return dict(saved)

    @classmethod
    def saved_hparams(cls, checkpoint: Dict[str, Any], where: str = "checkpoint"
                      ) -> Dict[str, Any]:
        """A checkpoint's hyper-parameters, removed options refused
        (:meth:`check_removed`), in today's layout (:meth:`upgrade_hparams`)."""
        saved = dict(checkpoint.get("hyper_parameters") or {})
        if isinstance(saved.get("model"), Configurable):  # written in by load_from_checkpoint
            saved["model"] = saved["model"].spec()
        cls.check_removed(saved, where)
        saved = {k: v for k, v in saved.items() if k not in cls.removed_switches}
        init = _init_args(saved)
        if any(k in init for k in cls.removed_model_switches):
            saved = {k: v for k, v in saved.items() if k not in cls.inert_settings}
            saved["model"] = dict(saved["model"], init_args={
                k: v for k, v in init.items() if k not in cls.removed_model_switches})
        saved = cls.upgrade_hparams(saved)
        saved.pop("_instantiator", None)
        return saved

    @classmethod
    def upgrade_checkpoint(cls, src: Union[str, os.PathLike],
                           dst: Union[str, os.PathLike]) -> None:
        """Write checkpoint ``src`` (verified) to ``dst`` with its hyper-parameters in
        today's layout (:meth:`saved_hparams`), stamped anew: what ``garmentgnn train
        ... --ckpt_path`` reads."""
        ckpt = load_checkpoint_file(src)
        ckpt["hyper_parameters"] = cls.saved_hparams(ckpt, str(src))
        stamp_checkpoint(ckpt)
        torch.save(ckpt, dst)

    @classmethod
    def model_spec(cls, saved: Dict[str, Any]) -> Dict[str, Any]:
        """The ``{"class_path", "init_args"}`` of the model a checkpoint's hyper-parameters
        ``saved`` (:meth:`saved_hparams`) describe: their ``model`` entry."""
        spec = saved.get("model")
        if not (isinstance(spec, dict) and "class_path" in spec):
            raise CheckpointError(f"its hyper-parameters name no model (`model: "
                                  f"class_path:`): not a checkpoint of {cls.__name__}")
        return spec

    @classmethod
    def load_from_checkpoint(cls, checkpoint_path, *args, **kwargs):
        """Lightning's ``load_from_checkpoint``, with the model rebuilt from the
        checkpoint's spec (``hparams["model"]``; a checkpoint of an earlier layout is
        converted, :meth:`upgrade_hparams`).  ``kwargs`` naming an argument of the model
        change its spec; the others are the module's, as in Lightning.  The file is
        verified as it was written (:mod:`~garmentgnn.training.integrity`)."""
        if not isinstance(checkpoint_path, (str, os.PathLike)):
            raise TypeError(f"`checkpoint_path`: expected the path of a checkpoint file, "
                            f"got {type(checkpoint_path).__name__}")
        ckpt = load_checkpoint_file(checkpoint_path)  # CheckpointError on a changed file
        saved = cls.saved_hparams(ckpt, str(checkpoint_path))
        spec = saved.get("model")
        if isinstance(spec, dict) and "class_path" in spec and "model" not in kwargs:
            spec = dict(spec, init_args=dict(spec.get("init_args") or {}))
            model_args = inspect.signature(import_class(spec["class_path"]).__init__).parameters
            for k in [k for k in kwargs if k in model_args]:
                spec["init_args"][k] = kwargs.pop(k)
            kwargs["model"] = build_model(spec)
        ckpt["hyper_parameters"] = saved
        buf = io.BytesIO()
        torch.save(ckpt, buf)
        buf.seek(0)
        token = _VERIFIED.set(True)
        try:
            return super().load_from_checkpoint(buf, *args, **kwargs)
        finally:
            _VERIFIED.reset(token)

    def on_load_checkpoint(self, checkpoint: Dict[str, Any]) -> None:
        if not _VERIFIED.get():
            verify_checkpoint(checkpoint)
        saved = self.saved_hparams(checkpoint)
        if saved:  # (a checkpoint without hyper-parameters cannot say what it was)
            self.check_model(self.model_spec(saved), checkpoint.get(DATASET_KEY))

    #: model arguments that change how it runs, not what it computes: a checkpoint
    #: restores into a model that differs from it only in these
    RUNTIME_ARGS: ClassVar[Tuple[str, ...]] = ("compile_search", "compile")
    #: model arguments set by the data (``garmentgnn train`` links them from
    #: :attr:`GarmentDataModule.dims`)
    DATA_SIZES: ClassVar[Tuple[str, ...]] = ("num_joints", "num_body_vertices",
                                             "nystrom_dim", "num_vertices")

    def check_model(self, spec: Dict[str, Any],
                    dataset: Optional[Dict[str, Any]] = None) -> None:
        """A :class:`CheckpointError` when the checkpoint's model ``spec`` is not this
        module's model: another class, or other settings (``--ckpt_path X`` resuming or
        scoring with another configuration).  Sizes set by the data (joints, body
        vertices, Nyström width, the garment's vertices) are named as such, with the
        dataset the checkpoint was trained on, before the weights fail to fit."""
        name = type(self.model).__name__
        if spec.get("class_path", "").rsplit(".", 1)[-1] != name:
            raise CheckpointError(f"a checkpoint of {spec.get('class_path')}, not of {name}; "
                                  f"give the configuration it was trained with")
        saved, mine = spec.get("init_args") or {}, self.model.init_args
        bad = {k: (saved[k], mine[k]) for k in saved
               if k in mine and k not in self.RUNTIME_ARGS and saved[k] != mine[k]}
        sizes = {k: v for k, v in bad.items() if k in self.DATA_SIZES}
        if sizes:
            what = saved.get("dynamic_layer") or ""
            text = ", ".join(f"{k} {c} (the data: {d})" for k, (c, d) in sorted(sizes.items()))
            data = (f" (dataset {dataset.get('content_sha256', '?')[:12]} at "
                    f"{dataset.get('root')})" if dataset else "")
            raise CheckpointError(f"a checkpoint of {type(self).__name__} ({name}"
                                  f"{f', {what}' if what else ''}) trained on data{data} of "
                                  f"other sizes: {text}; score it on data of its body model "
                                  f"and --data.nystrom_dim, or train a new model on this data")
        if bad:
            text = ", ".join(f"{k}={c!r} (this model: {d!r})"
                             for k, (c, d) in sorted(bad.items()))
            raise CheckpointError(f"a checkpoint of {name} with other settings: {text}; "
                                  f"build the model with the checkpoint's settings, or load "
                                  f"it with {type(self).__name__}.load_from_checkpoint")


def build_model(spec: Dict[str, Any]) -> nn.Module:
    """The model a ``{"class_path", "init_args"}`` spec describes (a checkpoint's
    ``hparams["model"]``, a YAML ``model:`` entry)."""
    cls = import_class(spec["class_path"])
    if not (isinstance(cls, type) and issubclass(cls, Configurable)):
        raise CheckpointError(f"model class_path {spec['class_path']!r}: not a garmentgnn "
                              f"model")
    return cls(**(spec.get("init_args") or {}))
