"""``garmentgnn train``: Lightning's own CLI over every trained method -- any
:class:`~garmentgnn.training.base.GarmentModule` (``subclass_mode_model``: GarTrans and
its Table 1 variants, :class:`GarTransModule`; the DA-, HOOD- and NCS-style baselines,
:class:`BaselineModule`; the MGN-style simulator, :class:`RolloutModule`) -- and
:class:`GarmentDataModule`, configured by a recipe (:mod:`garmentgnn.training.recipes`:
a packaged one named without folder or suffix, or a YAML file's path).  Each recipe names
its module (``model: class_path: ...``, ``init_args: ...``).

The model sizes that depend on the data (number of joints, body vertices, Nyström
width, the garment's vertex count) are linked from the data module, so a recipe only
says *what* to train::

    garmentgnn train fit --config gartrans --data.root data/small
    garmentgnn train fit --config ablations/wo_gating --data.root data/small
    garmentgnn train fit --config baselines/da --data.root data/small
    garmentgnn train fit --config gartrans --ckpt_path last   # resume
    garmentgnn train test --config baselines/da --ckpt_path X.ckpt

:func:`~garmentgnn.training.loader.load_recipe` reads recipes with the same parser from
Python and builds their module, data module and callbacks;
:meth:`~garmentgnn.training.loader.Recipe.trainer` is the one ``Trainer`` built outside
the command.

``test`` prints the paper's metrics of the checkpoint's method and of "LBS only" on the
same frames side by side (:func:`metrics_table`); ``predict`` writes the predicted
garment of every sequence of ``--data.predict_split`` (default: the test split) to
``<log dir>/predictions/<sequence id>.npz`` (:class:`PredictionWriter`).

Every option of the module, the data module, the trainer and its callbacks is a flag
(``garmentgnn train fit --help``, ``--model.help GarTransModule``); ``--print_config``
shows the merged configuration.  At the end of ``fit`` the loss terms and validation
metrics per epoch are drawn into ``<log dir>/training_curves.png``
(:class:`~garmentgnn.training.plots.TrainingPlots`).  Beside the CSV logger every run
also logs to TensorBoard (when the ``tensorboard`` package is installed): the same
values go to ``<log dir>/tensorboard/events.out.tfevents.*``.

Where it all goes: the loggers' ``save_dir`` is linked to ``--trainer.default_root_dir``
(a ``save_dir`` of their own is overridden), so ``--trainer.default_root_dir DIR`` puts
the log folder ``DIR/logs/version_<n>`` -- metrics, checkpoints, TensorBoard events,
curve plots, ``config.yaml`` -- under DIR; ``--trainer.logger false`` keeps only the
checkpoints, in ``DIR/checkpoints``.  The packaged recipes set ``runs/<name>``.
"""
from __future__ import annotations

import importlib.util
import inspect
import os
import sys
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Union

import numpy as np
import torch
from lightning.pytorch import LightningModule, Trainer
from lightning.pytorch.callbacks import BasePredictionWriter, ModelCheckpoint
from lightning.pytorch.cli import LightningCLI
from lightning.pytorch.loggers import CSVLogger, TensorBoardLogger
from lightning.pytorch.utilities import rank_zero_info, rank_zero_warn

from garmentgnn.training.base import LBS_PREFIX, GarmentModule, stored_module
from garmentgnn.training.recipes import (import_class, named_module,
                                         recipes_of_model, resolve_config_args)
from garmentgnn.training.datamodule import MODEL_INPUTS, GarmentDataModule
from garmentgnn.training.evaluate import markdown_table
from garmentgnn.training.heap import KeepFreedMemory
from garmentgnn.training.integrity import CheckpointError, hparam_conflicts, load_checkpoint_file
from garmentgnn.training.plots import TrainingPlots

#: TensorBoard's event files go into this sub-folder of the CSV logger's run folder
TENSORBOARD_SUBDIR = "tensorboard"
#: the module a recipe without ``model: class_path`` trains, and the model it is handed
DEFAULT_MODEL = "garmentgnn.training.GarTransModule"
DEFAULT_MODEL_MODEL = "garmentgnn.models.GarTrans"
#: Lightning's special ``--ckpt_path`` values (not files)
SPECIAL_CKPT = ("last", "best", "hpc", "registry")
#: the subcommands that score a trained model (refused without ``--ckpt_path``): what
#: each would do with an untrained one
EVALUATING = {"validate": "validate", "test": "test", "predict": "predict with"}
#: per subcommand, the trainer settings at which it would run nothing, and what is lost:
#: ``fit`` would exit 0 with no step and no checkpoint, ``test`` with an empty table
NOTHING_RUNS = {
    "fit": (("max_steps", "train no step and write no checkpoint", "-1: no limit"),
            ("max_epochs", "train no epoch and write no checkpoint", "-1: no limit"),
            ("limit_train_batches", "train on no batch", "1.0: every batch")),
    "validate": (("limit_val_batches", "validate no batch", "1.0: every batch"),),
    "test": (("limit_test_batches", "test no batch", "1.0: every batch"),),
    "predict": (("limit_predict_batches", "predict no batch", "1.0: every batch"),),
}
#: the sizes linked from the data module into the model a module is handed, when the
#: classes are built (:attr:`GarmentDataModule.dims`) or parsed (its arguments); a model
#: class that does not take one is left without it
LINKS = {"instantiate": ("num_joints", "num_body_vertices", "num_vertices"),
         "parse": ("nystrom_dim",)}
#: where they go
LINK_TARGET = "model.init_args.model.init_args"
#: the epochs a run trains when neither it nor its recipe sets ``max_epochs``,
#: ``max_steps`` or ``max_time``; a run that ends at its steps or its time has no epoch
#: limit (Lightning's own rule for ``max_epochs=None``: :meth:`GarmentCLI.instantiate_trainer`)
DEFAULT_EPOCHS = 30
#: the trainer settings of every recipe that does not set its own: one GPU when present,
#: else the CPU; :data:`DEFAULT_EPOCHS` epochs unless the steps or the time end the run
#: (``max_epochs: None`` here); the checkpoint of the best validation E_dist and the latest
#: one with ``last.ckpt`` (Lightning writes ``last.ckpt`` only along with a top-k
#: checkpoint, so with the monitored one alone it stays at the best epoch); a CSV log
#: under ``default_root_dir`` (no ``save_dir`` of its own: ``--trainer.default_root_dir
#: DIR`` moves the log, checkpoints, TensorBoard events and curve plots together)
TRAINER_DEFAULTS: Dict[str, Any] = {
    "accelerator": "auto", "devices": 1, "max_epochs": None, "log_every_n_steps": 10,
    "callbacks": [
        {"class_path": "lightning.pytorch.callbacks.ModelCheckpoint",
         "init_args": {"save_top_k": 1, "monitor": "val/E_dist", "mode": "min",
                       "filename": "best-{epoch}"}},
        {"class_path": "lightning.pytorch.callbacks.ModelCheckpoint",
         "init_args": {"save_top_k": 1, "save_last": True, "filename": "latest-{epoch}"}}],
    "logger": {"class_path": "lightning.pytorch.loggers.CSVLogger",
               "init_args": {"name": "logs"}},
}
#: every argument linked from the data module
LINKED = LINKS["instantiate"] + LINKS["parse"]
#: ``fit --ckpt_path`` resumes a run exactly: the training windows and batches too
RESUMED_ORDER = ("chunk", "stride", "batch_size", "drop_last", "shuffle", "train_split",
                 "train_ids")


def _plain(ns: Any) -> Dict[str, Any]:
    """A jsonargparse Namespace (or None) as a plain dict."""
    if ns is None:
        return {}
    return ns.as_dict() if hasattr(ns, "as_dict") else dict(ns)


def add_tensorboard(trainer: Trainer) -> Optional[TensorBoardLogger]:
    """Give ``trainer`` a :class:`TensorBoardLogger` writing into its ``CSVLogger``'s run
    folder (``<save_dir>/<name>/version_<n>/tensorboard``), unless it already has one or
    has no CSV logger.  Returns the logger added, or ``None`` (with a warning when the
    ``tensorboard`` package is missing)."""
    loggers = list(trainer.loggers)
    csv = next((lg for lg in loggers if isinstance(lg, CSVLogger)), None)
    if csv is None or any(isinstance(lg, TensorBoardLogger) for lg in loggers):
        return None
    if importlib.util.find_spec("tensorboard") is None:
        rank_zero_warn("no TensorBoard log: the `tensorboard` package is not installed "
                       "(`make install`, or pip install tensorboard); the CSV log is written")
        return None
    tb = TensorBoardLogger(save_dir=csv.save_dir, name=csv.name, version=csv.version,
                           sub_dir=TENSORBOARD_SUBDIR, default_hp_metric=False)
    trainer.loggers = loggers + [tb]
    return tb


def method_name(model: LightningModule) -> str:
    """The table row name of a trained module (its ``table_name``: ``"DA-style"``,
    ``"GarTrans (sat)"``...)."""
    return str(getattr(model, "table_name", type(model).__name__))


def metrics_table(metrics: Dict[str, Any], name: str, prefix: str = "test") -> str:
    """The logged ``<prefix>/<metric>`` (the method, row ``name``) and
    ``test_lbs/<metric>`` (row ``LBS only``) values as a markdown table."""
    rows: Dict[str, Dict[str, float]] = {}
    for row, pre in ((name, prefix), ("LBS only", LBS_PREFIX)):
        vals = {k[len(pre) + 1:]: float(v) for k, v in metrics.items()
                if k.startswith(pre + "/")}
        if vals:
            rows[row] = vals
    return markdown_table(rows)


class PredictionWriter(BasePredictionWriter):
    """``predict``: the garment of every predicted sequence to
    ``<folder>/<sequence id>.npz`` (``positions [T, V, 3]`` float32 metres and
    ``frames [T]``, in frame order); ``folder`` default: ``<log dir>/predictions``
    (``<default_root_dir>/predictions`` without a logger)."""

    def __init__(self, folder: Optional[str] = None) -> None:
        super().__init__(write_interval="epoch")
        self.folder = folder
        self.written: List[Path] = []

    def write_on_epoch_end(self, trainer: Trainer, pl_module: LightningModule,
                           predictions: Sequence[Any], batch_indices: Sequence[Any]) -> None:
        base = trainer.log_dir if trainer.loggers else trainer.default_root_dir
        folder = Path(self.folder or Path(base) / "predictions")
        folder.mkdir(parents=True, exist_ok=True)
        seqs: Dict[str, List[Dict[str, Any]]] = {}
        for out in predictions[0] if predictions and isinstance(predictions[0], list) \
                else predictions:
            seqs.setdefault(str(out["seq_id"]), []).append(out)
        for seq_id, outs in seqs.items():
            frames = torch.cat([o["frames"] for o in outs]).cpu().numpy()
            pos = torch.cat([o["positions"] for o in outs]).float().cpu().numpy()
            order = np.argsort(frames, kind="stable")
            path = folder / f"{seq_id}.npz"
            np.savez(path, positions=pos[order], frames=frames[order])
            self.written.append(path)
        rank_zero_info(f"predictions: {len(seqs)} sequence(s) in {folder}")


def _dim(name: str):
    def get(data: GarmentDataModule) -> Optional[int]:
        return data.dims[name]
    return get


def count_first(typehint: Any) -> Any:
    """``typehint`` with ``int`` tried before ``float`` in every union it holds.

    Lightning reads an int as a count and a float as a fraction
    (``--trainer.limit_test_batches 1`` is one batch, ``1.0`` all of them), and the
    parser tries a union's types in order.  ``typing`` caches unions by equality, which
    ignores order: a library that wrote ``Union[float, int]`` first (PyG does) makes the
    Trainer's ``Optional[Union[int, float]]`` float-first, so ``1`` was read as ``1.0``.
    A union is rebuilt directly (``Union[...]`` would return the cached one)."""
    args = getattr(typehint, "__args__", None)
    if getattr(typehint, "__origin__", None) is not Union or not isinstance(args, tuple):
        return typehint
    new = tuple(count_first(a) for a in args)
    if int in new and float in new and new.index(float) < new.index(int):
        new = tuple(a for a in new if a is not float)
        new = new[:new.index(int) + 1] + (float,) + new[new.index(int) + 1:]
    if all(a is b for a, b in zip(new, args)):
        return typehint
    return type(typehint)(Union, new)


def _defaults(cls: type) -> Dict[str, Any]:
    return {k: p.default for k, p in inspect.signature(cls.__init__).parameters.items()
            if p.default is not inspect.Parameter.empty}


class GarmentCLI(LightningCLI):
    """LightningCLI over every :class:`GarmentModule` with the data-dependent model sizes
    linked from the data module; subcommands ``fit``, ``validate``, ``test`` (the
    method's and LBS's metrics, :func:`metrics_table`) and ``predict``.

    ``validate``, ``test`` and ``predict`` need ``--ckpt_path`` (without it they would
    score an untrained model).  ``--ckpt_path X`` is checked first: an unreadable or
    changed file, a checkpoint of another module class or of an earlier layout, or a
    ``--model.*`` flag (or config value) that differs from X's hyper-parameters, is a
    :class:`~garmentgnn.training.integrity.CheckpointError`
    (the model is rebuilt from X's hyper-parameters)."""

    def __init__(self, *args: Any, default_model: Optional[str] = None, **kwargs: Any) -> None:
        kwargs.setdefault("subclass_mode_model", True)
        #: the module class the parser starts from (:func:`named_module` of the arguments)
        self.default_model = default_model or DEFAULT_MODEL
        super().__init__(*args, **kwargs)

    def parse_arguments(self, parser: Any, args: Any) -> None:
        super().parse_arguments(parser, args)
        self.check_something_runs()
        self.check_checkpoint_given()
        cls_path = self.check_checkpoint_flags()
        if cls_path is not None:
            # Lightning rebuilds the model from the checkpoint's hyper-parameters next;
            # a checkpoint written outside LightningCLI does not name its class, which is
            # then the configured one (not the parser's default)
            parser.set_defaults({f"{self.config.subcommand}.model": {"class_path": cls_path}})

    def check_something_runs(self) -> None:
        """A trainer setting of 0 that leaves the subcommand nothing to do
        (:data:`NOTHING_RUNS`: ``fit --trainer.max_steps 0`` exited 0 without a step or a
        checkpoint) is a ``ValueError`` naming the flag."""
        sub = self.config.get("subcommand") if self.config is not None else None
        trainer = _plain(self.config[sub].get("trainer")) if sub else {}
        for key, lost, hint in NOTHING_RUNS.get(sub, ()):
            if trainer.get(key) == 0 and not isinstance(trainer.get(key), bool):
                raise ValueError(f"--trainer.{key} {trainer[key]}: `{sub}` would {lost}; "
                                 f"give a positive value ({hint})")

    def check_checkpoint_given(self) -> None:
        """``validate``, ``test`` and ``predict`` score a trained model: without
        ``--ckpt_path`` they would score the untrained one that the configuration builds,
        so they are refused (:class:`CheckpointError` naming the flag)."""
        sub = self.config.get("subcommand") if self.config is not None else None
        if sub in EVALUATING and not self.config[sub].get("ckpt_path"):
            raise CheckpointError(
                f"--ckpt_path: `{sub}` without a checkpoint would {EVALUATING[sub]} the "
                f"untrained model the configuration builds; pass --ckpt_path PATH, a "
                f"checkpoint written by `garmentgnn train fit` (e.g. <default_root_dir>/"
                f"logs/version_<n>/checkpoints/last.ckpt)")

    def check_checkpoint_flags(self) -> Optional[str]:
        """Refuse a ``--ckpt_path`` that does not match the configured module (see the
        class docstring); returns the configured module's class path when a checkpoint
        file is given."""
        sub = self.config.get("subcommand") if self.config is not None else None
        ckpt_path = self.config[sub].get("ckpt_path") if sub else None
        if not ckpt_path or ckpt_path in SPECIAL_CKPT:
            return None
        ckpt = load_checkpoint_file(ckpt_path)
        raw = dict(ckpt.get("hyper_parameters") or {})
        model = _plain(self.config[sub].get("model"))
        cls_path = model.get("class_path") or DEFAULT_MODEL
        saved_cls = raw.pop("_class_path", None)
        saved_cls = stored_module(saved_cls) if saved_cls else None
        module_cls = import_class(cls_path)
        spec, given = raw.get("model"), _plain(model.get("init_args"))
        saved_model = spec.get("class_path") if isinstance(spec, dict) else None
        given_model = _plain(given.get("model")).get("class_path")
        if (saved_cls and saved_cls.rsplit(".", 1)[-1] != cls_path.rsplit(".", 1)[-1]) \
                or (saved_model and given_model and saved_model.rsplit(".", 1)[-1]
                    != given_model.rsplit(".", 1)[-1]):
            what = saved_model.rsplit(".", 1)[-1] if saved_model else saved_cls
            fits = recipes_of_model(saved_model) if saved_model else []
            mine = (given_model or cls_path).rsplit(".", 1)[-1]
            hint = (f"give --config {fits[0]}" if fits else
                    "give the --config of the method it was trained with")
            raise CheckpointError(f"{ckpt_path}: a checkpoint of {what}, not of {mine}; "
                                  f"{hint}")
        # the configured module's: an earlier layout of it is refused, saying to retrain
        stored = module_cls.saved_hparams(ckpt, str(ckpt_path)) \
            if issubclass(module_cls, GarmentModule) else raw
        bad = {f"--model.{k}": c for k, c in hparam_conflicts(
            {k: v for k, v in given.items()
             if k != "model" and k not in GarmentModule.RUNTIME_ARGS}, _defaults(module_cls),
            stored).items()}
        given_spec = _plain(given.get("model"))
        if isinstance(spec, dict) and "class_path" in spec:
            model_cls = import_class(spec["class_path"])
            # a size linked from the data is no flag: the check of the sizes names it
            flags = {k: v for k, v in _plain(given_spec.get("init_args")).items()
                     if k not in LINKED}
            bad.update({f"--model.model.{k}": c for k, c in hparam_conflicts(
                flags, _defaults(model_cls), spec.get("init_args") or {}).items()})
        if bad:
            what = ", ".join(f"{k} {v!r} (checkpoint: {c!r})"
                             for k, (v, c) in sorted(bad.items()))
            raise CheckpointError(f"{ckpt_path}: {what}; the model is rebuilt from the "
                                  f"checkpoint's hyper-parameters, so drop the flag(s), "
                                  f"start a new run without --ckpt_path, or branch the run "
                                  f"with garmentgnn.training.fork_checkpoint")
        self.check_checkpoint_data(sub, ckpt_path, ckpt)
        return cls_path

    def check_checkpoint_data(self, sub: str, ckpt_path: str, ckpt: Dict[str, Any]) -> None:
        """The data module is configured by the recipe and the flags, not rebuilt from
        the checkpoint: a value of
        :data:`~garmentgnn.training.datamodule.MODEL_INPUTS` other than the checkpoint's
        data module's (``train predict --data.history 1`` on a model trained with 3) would give
        the model other inputs than it learned from, and for ``fit`` one of
        :data:`RESUMED_ORDER` another run than the one resumed; a
        :class:`CheckpointError` naming each ``--data.*`` flag and both values."""
        stored = ckpt.get("datamodule_hyper_parameters") or {}
        data = _plain(self.config[sub].get("data"))
        keys = MODEL_INPUTS + (RESUMED_ORDER if sub == "fit" else ())
        defaults = _defaults(GarmentDataModule)
        bad = {}
        for k in keys:
            if k not in stored:
                continue
            mine, theirs = data.get(k, defaults.get(k)), stored[k]
            if isinstance(mine, (list, tuple)) and isinstance(theirs, (list, tuple)):
                mine, theirs = list(mine), list(theirs)
            if mine != theirs:
                bad[f"--data.{k}"] = (mine, theirs)
        if not bad:
            return
        what = ", ".join(f"{k} {v!r} (checkpoint: {c!r})" for k, (v, c) in sorted(bad.items()))
        why = ("the model learned from inputs of the checkpoint's values" if sub != "fit"
               else "a resumed run goes on with the checkpoint's data settings")
        fix = ("give the checkpoint's values" if sub != "fit" else
               "give the checkpoint's values, start a new run without --ckpt_path, or "
               "branch the run with garmentgnn.training.fork_checkpoint")
        raise CheckpointError(f"{ckpt_path}: {what}; {why}; {fix}")

    def instantiate_trainer(self, **kwargs: Any) -> Trainer:
        """Lightning's trainer, with a TensorBoard logger beside the CSV one
        (:func:`add_tensorboard`).  ``enable_checkpointing`` false (a flag or an
        argument) leaves out the checkpoint callbacks of the defaults and the recipe,
        which Lightning would otherwise refuse beside it.  Without ``max_epochs``, a run
        trains :data:`DEFAULT_EPOCHS` epochs, or without an epoch limit when
        ``max_steps`` or ``max_time`` ends it (a step-counted recipe given more steps
        than the default epochs hold trains them all)."""
        cfg = self.config_init[self.subcommand] if self.subcommand else self.config_init
        trainer_cfg = cfg.get("trainer") or {}
        given = {**trainer_cfg, **kwargs}
        if given.get("max_epochs") is None:
            ends = given.get("max_steps", -1) not in (None, -1) \
                or given.get("max_time") is not None
            kwargs["max_epochs"] = -1 if ends else DEFAULT_EPOCHS
        if kwargs.get("enable_checkpointing", trainer_cfg.get("enable_checkpointing")) is False \
                and "callbacks" not in kwargs:
            kwargs["callbacks"] = [c for c in trainer_cfg.get("callbacks") or []
                                   if not isinstance(c, ModelCheckpoint)]
        trainer = super().instantiate_trainer(**kwargs)
        add_tensorboard(trainer)
        return trainer

    def add_arguments_to_parser(self, parser: Any) -> None:
        for action in parser._actions:  # an int flag stays a count (:func:`count_first`)
            if getattr(action, "_typehint", None) is not None:
                action._typehint = count_first(action._typehint)
        # the parser starts from the module the arguments name: jsonargparse keeps the
        # values of same-named arguments when a recipe switches the class, so starting
        # from GarTransModule would hand a BaselineModule GarTransModule's defaults
        # (its learning rate, its rollout settings) where the recipe leaves them out
        nested = {"model": {"class_path": DEFAULT_MODEL_MODEL}} \
            if self.default_model == DEFAULT_MODEL else {}
        parser.set_defaults({"model": {"class_path": self.default_model, "init_args": nested}})
        parser.set_defaults({f"trainer.{k}": v for k, v in TRAINER_DEFAULTS.items()})
        for name in LINKS["parse"]:
            parser.link_arguments(f"data.{name}", f"{LINK_TARGET}.{name}")
        # every logger writes under the trainer's root folder (the current folder when it
        # is unset, as in Lightning), so --trainer.default_root_dir moves logs,
        # checkpoints, TensorBoard events and curve plots together
        parser.link_arguments("trainer.default_root_dir", "trainer.logger.init_args.save_dir",
                              compute_fn=lambda d: d or os.getcwd())
        for name in LINKS["instantiate"]:
            parser.link_arguments("data", f"{LINK_TARGET}.{name}", apply_on="instantiate",
                                  compute_fn=_dim(name))

    def check_special_checkpoint(self, sub: str) -> None:
        """``--ckpt_path last`` / ``best`` for ``validate``, ``test`` or ``predict``:
        Lightning looks in this run's log folder (a new ``version_<n>``) and, finding no
        file there, goes on with the untrained model (``last``) or fails with a message
        about ``ModelCheckpoint`` (``best``); refused here, naming the flag."""
        ckpt_path = self.config[sub].get("ckpt_path")
        if ckpt_path not in ("last", "best"):
            return
        found = set()
        for cb in self.trainer.checkpoint_callbacks:
            if isinstance(cb, ModelCheckpoint):
                found |= (cb._find_last_checkpoints(self.trainer) if ckpt_path == "last"
                          else {cb.best_model_path} - {""})
        if not any(os.path.isfile(f) for f in found):
            raise CheckpointError(
                f"--ckpt_path {ckpt_path}: `{sub}` finds no {ckpt_path} checkpoint in this "
                f"run's folder ({self.trainer.log_dir}); it would {EVALUATING[sub]} the "
                f"untrained model; give the checkpoint file, e.g. <default_root_dir>/logs/"
                f"version_<n>/checkpoints/last.ckpt")

    def before_validate(self) -> None:
        self.check_special_checkpoint("validate")

    def before_test(self) -> None:
        self.check_special_checkpoint("test")

    def before_predict(self) -> None:
        self.check_special_checkpoint("predict")

    def after_test(self) -> None:
        """Print the method's and LBS's test metrics side by side."""
        if self.trainer.is_global_zero:
            table = metrics_table(self.trainer.callback_metrics, method_name(self.model))
            print(f"\ntest split {self.datamodule.hparams.test_split!r}, frame-weighted "
                  f"means:\n{table}")


def main(args: Optional[Sequence[str]] = None, run: bool = True,
         prog: Optional[str] = None) -> GarmentCLI:
    """Run the CLI (``args`` default: ``sys.argv[1:]``; ``--config NAME`` may name a
    packaged recipe, :func:`~garmentgnn.training.recipes.resolve_config_args`;
    ``prog``: the program name its usage lines show); returns the CLI object.  Every
    run also gets :class:`TrainingPlots` (``training_curves.png`` in the log folder),
    :class:`PredictionWriter`, :class:`~garmentgnn.training.KeepFreedMemory` (glibc
    keeps a step's freed blocks for the next) and a TensorBoard log
    (:func:`add_tensorboard`)."""
    args = resolve_config_args(sys.argv[1:] if args is None else args)
    return GarmentCLI(GarmentModule, GarmentDataModule, args=args,
                      default_model=named_module(args),
                      run=run, seed_everything_default=0,
                      parser_kwargs={"prog": prog} if prog else None,
                      save_config_kwargs={"overwrite": True},
                      trainer_defaults={"callbacks": [TrainingPlots(), PredictionWriter(),
                                                      KeepFreedMemory()]})


if __name__ == "__main__":  # pragma: no cover
    main()
