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
import os
from typing import Any, ClassVar, Dict, Optional, Tuple

import lightning as L
import torch
import torch.distributed as dist
from torch import Tensor

from garmentgnn.data.store import read_manifest
from garmentgnn.losses.gartrans_loss import NonFiniteLossError
from garmentgnn.metrics import evaluate_inputs
from garmentgnn.models.inputs import GarmentInputs
from garmentgnn.training.integrity import (CheckpointError, load_checkpoint_file,
                                           stamp_checkpoint, verify_checkpoint)

__all__ = ["LBS_PREFIX", "GarmentModule"]

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
    per training step, :class:`~garmentgnn.training.GarmentDataModule`).

    Attributes:
        former_defaults: hyper-parameters whose default has changed, with the value a
            checkpoint that does not name them was trained with;
            :meth:`load_from_checkpoint` builds such a checkpoint with it.
    """

    former_defaults: ClassVar[Dict[str, Any]] = {}
    #: hyper-parameters that no longer exist, with the only value a checkpoint may hold
    #: for them (anything else was another model: :meth:`check_removed` refuses it)
    removed_switches: ClassVar[Dict[str, Any]] = {}

    @classmethod
    def check_removed(cls, hparams: Dict[str, Any], where: str = "checkpoint") -> None:
        """A :class:`CheckpointError` when ``hparams`` switch on a removed option."""
        bad = {k: hparams[k] for k, off in cls.removed_switches.items()
               if k in hparams and hparams[k] != off}
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

    @classmethod
    def load_from_checkpoint(cls, checkpoint_path, *args, **kwargs):
        """Lightning's ``load_from_checkpoint``; a checkpoint that does not name a
        hyper-parameter of :attr:`former_defaults` is built with its former value (the
        model it was trained as), unless ``kwargs`` name it.  Lightning writes
        ``kwargs`` into the loaded checkpoint before :meth:`on_load_checkpoint` sees
        it, so with ``kwargs`` (or former defaults to look up) a local file is verified
        as it was written, first; a stream or a remote URL is verified as loaded."""
        if not (kwargs or cls.former_defaults or cls.removed_switches) or not isinstance(
                checkpoint_path, (str, os.PathLike)) or not os.path.isfile(checkpoint_path):
            return super().load_from_checkpoint(checkpoint_path, *args, **kwargs)
        # raises CheckpointError on a changed file
        saved = load_checkpoint_file(checkpoint_path).get("hyper_parameters") or {}
        cls.check_removed(saved, str(checkpoint_path))
        kwargs = {**{k: v for k, v in cls.former_defaults.items() if k not in saved},
                  **kwargs}
        token = _VERIFIED.set(True)
        try:
            return super().load_from_checkpoint(checkpoint_path, *args, **kwargs)
        finally:
            _VERIFIED.reset(token)

    def on_load_checkpoint(self, checkpoint: Dict[str, Any]) -> None:
        if not _VERIFIED.get():
            verify_checkpoint(checkpoint)
        saved = checkpoint.get("hyper_parameters") or {}
        self.check_removed(saved)
        self.check_data_sizes(saved, checkpoint.get(DATASET_KEY))

    def data_sizes(self) -> Tuple[str, ...]:
        """The hyper-parameters set by the data that the weights depend on."""
        return ()

    def check_data_sizes(self, saved: Dict[str, Any],
                         dataset: Optional[Dict[str, Any]] = None) -> None:
        """A :class:`CheckpointError` when a checkpoint's hyper-parameters ``saved`` were
        trained on data of other sizes (joints, body vertices, Nyström width, the
        garment's vertices) than this module was built for (``garmentgnn train test
        --ckpt_path X`` on another dataset), naming each, before the weights fail to fit."""
        bad = {k: (saved[k], self.hparams[k]) for k in self.data_sizes()
               if saved.get(k) is not None and self.hparams.get(k) is not None
               and saved[k] != self.hparams[k]}
        if bad:
            what = saved.get("method") or saved.get("dynamic_layer") or ""
            sizes = ", ".join(f"{k} {c} (the data: {d})" for k, (c, d) in sorted(bad.items()))
            data = (f" (dataset {dataset.get('content_sha256', '?')[:12]} at "
                    f"{dataset.get('root')})" if dataset else "")
            raise CheckpointError(f"a checkpoint of {type(self).__name__}"
                                  f"{f' ({what})' if what else ''} trained on data{data} of "
                                  f"other sizes: {sizes}; score it on data of its body model "
                                  f"and --data.nystrom_dim, or train a new model on this data")
