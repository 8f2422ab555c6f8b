"""What every trained method shares: :class:`GarmentModule`, the LightningModule base of
:class:`~garmentgnn.training.GarTransModule` and :class:`~garmentgnn.training.BaselineModule`.

It holds the parts that do not depend on the method: the checkpoint integrity hooks
(:mod:`garmentgnn.training.integrity`), the training-step logging, the held-out metrics
of ``validate``/``test`` (:func:`garmentgnn.metrics.evaluate_inputs` on the valid
ground-truth frames, ``valid``, as every metric that reads the data; ``test`` scores
"LBS only" on the same frames beside the method, ``test_lbs/...``) and ``predict``.  A
method only says how it predicts a chunk (:meth:`GarmentModule.predict_garment`) and how
it trains (``training_step``, ``configure_optimizers``).

The method protocol: what ``garmentgnn bench``, ``predict``, ``show`` and ``train`` ask of
a method, so that none of them knows a method by its class (docs/model.md, "Adding a
method").  Every attribute has a default that fits a frame-parallel method of one model
for every garment:

* :attr:`~GarmentModule.autoregressive` -- frame-parallel (any frames at once, in chunks)
  or one frame after another over a whole sequence; :attr:`~GarmentModule.min_frames`;
* :meth:`~GarmentModule.trains_per_garment` -- one model for every garment, or one per
  (garment, body) trained on that garment's poses (the bench trains one per test garment;
  ``predict`` refuses another garment);
* :meth:`~GarmentModule.predict_sequence` -- the garment from what a user has (no
  simulated frame); :meth:`~GarmentModule.predict_garment` -- the held-out evaluation
  ``validate``/``test`` score (it may start from the simulated first frames);
* :meth:`~GarmentModule.timed_call` and :attr:`~GarmentModule.timing_note` -- what the
  bench times; :meth:`~GarmentModule.bench_overrides` -- the recipe settings the bench's
  budget sets; :meth:`~GarmentModule.fit_info` -- what a bench record adds after fitting;
  :meth:`~GarmentModule.training_loss` -- one step's loss (the learning diagnostics);
* :attr:`~GarmentModule.family` (the bench's seed plan), :attr:`~GarmentModule.table_name`,
  :attr:`~GarmentModule.learned_fps` (the frame rate its dynamics were learned at).
"""
from __future__ import annotations

import atexit
import contextvars
import inspect
import io
import os
from typing import Any, Callable, ClassVar, Dict, Optional, Tuple

import lightning as L
import torch
import torch.distributed as dist
from torch import Tensor, nn

from garmentgnn.data.store import read_manifest
from garmentgnn.losses.gartrans_loss import NonFiniteLossError
from garmentgnn.metrics import evaluate_inputs
from garmentgnn.models.blocks import Configurable
from garmentgnn.models.inputs import GarmentInputs
from garmentgnn.training.recipes import import_class
from garmentgnn.training.integrity import (CheckpointError, load_checkpoint_file,
                                           stamp_checkpoint, verify_checkpoint)

__all__ = ["LBS_PREFIX", "RENAMED_MODULES", "GarmentModule", "build_model", "stored_module"]

#: set while :meth:`GarmentModule.load_from_checkpoint` loads a file it has verified
_VERIFIED: contextvars.ContextVar[bool] = contextvars.ContextVar("checkpoint_verified",
                                                                default=False)

#: modules renamed since a checkpoint could name them (its ``_class_path``): the former
#: class path -> today's, so that a checkpoint written before the rename loads
#: (:func:`~garmentgnn.training.load_checkpoint`: ``show``, ``predict``, ``train test``).
#: Resuming one with ``garmentgnn train fit --ckpt_path`` needs its ``_class_path``
#: rewritten first: LightningCLI parses that class path itself, before this module runs
RENAMED_MODULES = {
    "garmentgnn.training.SimulatorModule": "garmentgnn.training.RolloutModule",
    "garmentgnn.training.simulator.SimulatorModule": "garmentgnn.training.RolloutModule",
}


def stored_module(class_path: Any) -> str:
    """A checkpoint's ``_class_path`` under today's name (:data:`RENAMED_MODULES`)."""
    return RENAMED_MODULES.get(str(class_path), str(class_path))


#: checkpoint key of the dataset a method was trained on (:func:`dataset_stamp`)
DATASET_KEY = "garmentgnn_dataset"


def dataset_stamp(datamodule: Any) -> Dict[str, Any]:
    """``{"root", "content_sha256", "num_vertices"}`` of a data module's dataset (its
    manifest's content hash; the fewest and most vertices of its training garments, what
    ``garmentgnn predict`` compares a garment with), saved in every checkpoint a fit
    writes; ``{}`` without one."""
    root = getattr(datamodule, "root", None)
    if root is None:
        return {}
    try:
        man = read_manifest(root)
    except (OSError, ValueError):
        return {}
    sha = man.get("content_sha256")
    if not sha:
        return {}
    split = getattr(getattr(datamodule, "hparams", None), "train_split", "train")
    counts = [int(r["num_vertices"]) for r in man.get("items", [])
              if r.get("status") == "ok" and r.get("num_vertices")
              and (split is None or r.get("split") == split)]
    return {"root": str(root), "content_sha256": sha,
            **({"num_vertices": [min(counts), max(counts)]} if counts else {})}


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


#: the modules' ``compile_search`` default: ``torch.compile`` the nearest-body-face
#: search of the collision projection and loss while a module trains -- the same result
#: (docs/model.md: 1.25x a GarTrans step, the largest single saving), a one-off compile
#: of 10-20 s per process
COMPILE_SEARCH = True
#: garment vertex-frames (frames x vertices) from which that compile pays back where
#: nothing trains (``predict``, ``train test``): on 2 idle CPU cores it costs 3.9-5.2 s
#: once and saves 0.010-0.015 ms per vertex-frame (docs/results/predict_compile)
COMPILE_WORK = 350_000


def compile_pays(work: int, device: Any = "cpu") -> bool:
    """Whether compiling the nearest-face search pays back on ``work`` garment
    vertex-frames evaluated on ``device``: on a CPU from :data:`COMPILE_WORK` on, on a
    GPU always."""
    return torch.device(device).type != "cpu" or work >= COMPILE_WORK

class GarmentModule(L.LightningModule):
    """Base of the garment methods trained by ``garmentgnn train`` (a batch of chunks
    per training step, :class:`~garmentgnn.training.GarmentDataModule`), in
    Lightning's system style: the module is handed its model (``model=GarTrans(...)``;
    in YAML, ``model: init_args: model: class_path: ...``) and says how it trains it.
    """

    # -- the method protocol (the module docstring) ----------------------------------------
    #: ``False``: frame-parallel, any frames of a sequence at once (in chunks); ``True``:
    #: autoregressive, a whole sequence one frame after another from its first frames
    autoregressive: bool = False
    #: the fewest frames a sequence must have for :meth:`predict_sequence`
    min_frames: int = 1
    #: the bench's seed plan gives every seed to the best method of each family
    #: (:func:`garmentgnn.bench.methods.seed_plan`): ``"gartrans"`` (the paper's model and
    #: its variants) or ``"baseline"`` (every other method)
    family: str = "baseline"
    #: what :meth:`timed_call` times, in the bench's timing table
    timing_note: str = "one call predicting `batch` frames"

    @classmethod
    def trains_per_garment(cls, model: type) -> bool:
        """Whether this module with a model of class ``model`` trains one model per
        (garment, body), on that garment's poses (the bench trains one per test garment;
        ``predict`` refuses another garment), rather than one for every garment: known
        from the recipe, before any data.  Default: ``False``."""
        return False

    @property
    def per_garment(self) -> bool:
        """:meth:`trains_per_garment` of this module's model."""
        return self.trains_per_garment(type(self.model))

    @property
    def table_name(self) -> str:
        """The method's row name in tables (``garmentgnn train test``)."""
        return type(self).__name__

    @property
    def learned_fps(self) -> Optional[float]:
        """The frame rate the method learned its dynamics at, which ``predict`` must give
        it (``None``: any rate)."""
        return None

    def predict_garment(self, batch: GarmentInputs) -> Tensor:
        """The garment ``[B, V, 3]`` of every frame of ``batch``: the held-out evaluation
        that ``validate``, ``test``, ``predict`` and ``show`` score."""
        raise NotImplementedError(f"{type(self).__name__}: define predict_garment")

    def predict_sequence(self, batch: GarmentInputs) -> Tensor:
        """The garment ``[T, V, 3]`` of ``batch``'s frames from what a user has (the body,
        the rest garment, its skinning; never a simulated frame): what ``garmentgnn
        predict`` and the bench's scores run.  Default: :meth:`predict_garment`."""
        return self.predict_garment(batch)

    def timed_call(self, item: GarmentInputs, batch: int) -> Callable[[], Any]:
        """A function predicting ``batch`` frames of ``item`` per call, its inputs prepared
        outside it (:attr:`timing_note` says what it does): the bench's timing sweep."""
        cycled = item.cycled(batch)
        return lambda: self.predict_garment(cycled)

    @classmethod
    def bench_overrides(cls, *, schedule_window: int,
                        shortest_sequence: int) -> Dict[str, Callable[[Any], Any]]:
        """The recipe settings the bench's budget changes (``{dotted key: old value ->
        new value}``, :func:`~garmentgnn.training.load_recipe`'s ``set``), given the
        budget's schedule window in epochs and the frames of the shortest training
        sequence.  Default: none."""
        return {}

    def training_loss(self, batch: GarmentInputs) -> Tensor:
        """The total loss of one training step on ``batch``, the weights unchanged (the
        learning diagnostics' backward pass, :mod:`garmentgnn.training.diagnostics`)."""
        raise NotImplementedError(f"{type(self).__name__}: define training_loss")

    def fit_info(self) -> Dict[str, Any]:
        """What a bench record adds about this fitted run (JSON-able).  Default: nothing."""
        return {}

    def min_history(self) -> Tuple[int, str]:
        """The fewest previous poses per frame (the data module's ``history``) this
        method reads, and what reads them; checked when a run is set up."""
        return 1, f"{type(self).__name__} reads the pose before each frame"

    def setup(self, stage: str) -> None:
        destroy_gloo_group_at_exit()  # on every replica, once its process group exists
        try:
            dm = self.trainer.datamodule
        except RuntimeError:  # no trainer attached
            dm = None
        have = getattr(getattr(dm, "hparams", None), "history", None)
        need, why = self.min_history()
        if isinstance(have, int) and have < need:  # checked here, not at the first step
            raise ValueError(f"--data.history {have}: {why}; give --data.history {need} "
                             f"or more")

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
                            f"first, e.g. "
                            f"GarTransModule(GarTrans(**datamodule.model_sizes(GarTrans)))")
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
    def saved_hparams(cls, checkpoint: Dict[str, Any], where: str = "checkpoint"
                      ) -> Dict[str, Any]:
        """A checkpoint's hyper-parameters: the module's arguments and ``model``, its
        model's spec.  A checkpoint whose hyper-parameters this version's module or model
        does not take (another module's, or an earlier layout's) is a
        :class:`CheckpointError` that says so and to retrain: there is no conversion.  A
        checkpoint without hyper-parameters gives ``{}`` (it cannot say what it was)."""
        saved = dict(checkpoint.get("hyper_parameters") or {})
        if isinstance(saved.get("model"), Configurable):  # written in by load_from_checkpoint
            saved["model"] = saved["model"].spec()
        saved.pop("_instantiator", None)
        other = stored_module(saved.pop("_class_path", "")).rsplit(".", 1)[-1]
        if other and other != cls.__name__:
            raise CheckpointError(f"{where}: a checkpoint of {other}, not of {cls.__name__}; "
                                  f"load it with {other}.load_from_checkpoint")
        spec = saved.get("model")
        unknown = [k for k in saved if k not in inspect.signature(cls.__init__).parameters]
        if isinstance(spec, dict) and "class_path" in spec:
            try:
                params = inspect.signature(import_class(spec["class_path"]).__init__).parameters
            except ValueError:
                params = {}
            unknown += [f"model.{k}" for k in spec.get("init_args") or {} if k not in params]
        if saved and (unknown or not (isinstance(spec, dict) and "class_path" in spec)):
            model = (f"(its model: {str(spec['class_path']).rsplit('.', 1)[-1]}) "
                     if isinstance(spec, dict) and "class_path" in spec else "")
            what = (f"its hyper-parameters {', '.join(sorted(unknown))} are not "
                    f"{cls.__name__}'s" if unknown else "it names no model")
            raise CheckpointError(f"{where}: a checkpoint {model}of another module or of an "
                                  f"earlier layout of {cls.__name__} ({what}); load it with "
                                  f"the module it was trained with, or retrain it with this "
                                  f"version (garmentgnn train fit)")
        return saved

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
        refused, :meth:`saved_hparams`).  ``kwargs`` naming an argument of the model
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
        #: the dataset and data settings it was trained with (``show`` follows them)
        self.trained_on = checkpoint.get(DATASET_KEY)
        self.trained_data = checkpoint.get("datamodule_hyper_parameters") or {}
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
                                  f"give the recipe (--config) it was trained with")
        saved, mine = spec.get("init_args") or {}, self.model.init_args
        bad = {k: (saved[k], mine[k]) for k in saved
               if k in mine and k not in self.RUNTIME_ARGS and saved[k] != mine[k]}
        sizes = {k: v for k, v in bad.items() if k in self.DATA_SIZES}
        if sizes:
            raise CheckpointError(self.sizes_message(sizes, saved, dataset,
                                                     "and --data.nystrom_dim"))
        if bad:
            text = ", ".join(f"{k}={c!r} (this model: {d!r})"
                             for k, (c, d) in sorted(bad.items()))
            raise CheckpointError(f"a checkpoint of {name} with other settings: {text}; "
                                  f"build the model with the checkpoint's settings, or load "
                                  f"it with {type(self).__name__}.load_from_checkpoint")

    def sizes_message(self, sizes: Dict[str, Tuple[Any, Any]], init: Dict[str, Any],
                      dataset: Optional[Dict[str, Any]] = None, also: str = "") -> str:
        """What :meth:`check_model` and :meth:`check_data` say of a checkpoint whose model
        (``init``: its arguments) has other data ``sizes`` (name -> (checkpoint's, the
        data's)) than the data it is given: the sizes, the dataset it was trained on and
        the fix (``also``: the flag that sets a size too)."""
        name = type(self.model).__name__
        what = init.get("dynamic_layer") or ""
        text = ", ".join(f"{k} {c} (the data: {d})" for k, (c, d) in sorted(sizes.items()))
        data = (f" (dataset {dataset.get('content_sha256', '?')[:12]} at "
                f"{dataset.get('root')})" if dataset else "")
        return (f"a checkpoint of {type(self).__name__} ({name}{f', {what}' if what else ''}) "
                f"trained on data{data} of other sizes: {text}; use it on data of its body "
                f"model{f' {also}' if also else ''}, or train a new model on this data")

    def check_data(self, dims: Dict[str, Optional[int]], where: str = "checkpoint") -> None:
        """A :class:`CheckpointError` (prefixed ``where``: the file) when the data sizes
        ``dims`` (as :attr:`GarmentDataModule.dims`) differ from those this module's model
        was built with; :meth:`check_model`'s words, before a forward pass fails on
        them."""
        init = self.model.init_args
        sizes = {k: (init[k], d) for k, d in dims.items() if k in self.DATA_SIZES
                 and init.get(k) is not None and d is not None and init[k] != d}
        if sizes:
            raise CheckpointError(f"{where}: " + self.sizes_message(
                sizes, init, getattr(self, "trained_on", None)))


def build_model(spec: Dict[str, Any]) -> nn.Module:
    """The model a ``{"class_path", "init_args"}`` spec describes (a checkpoint's
    ``hparams["model"]``, a YAML ``model:`` entry)."""
    cls = import_class(spec["class_path"])
    if not (isinstance(cls, type) and issubclass(cls, Configurable)):
        raise CheckpointError(f"model class_path {spec['class_path']!r}: not a garmentgnn "
                              f"model")
    return cls(**(spec.get("init_args") or {}))
