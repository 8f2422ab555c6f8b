"""``garmentgnn train``: Lightning's own CLI over :class:`GarTransModule` and
:class:`GarmentDataModule`, configured by the YAML files packaged in
``garmentgnn/configs/`` (named without folder or suffix, or given as paths).

The model sizes that depend on the data (number of joints, body vertices, Nyström
width) are linked from the data module, so a config only says *what* to train::

    garmentgnn train fit --config gartrans --data.root data/small
    garmentgnn train fit --config gartrans --config ablations/wo_gating ...
    garmentgnn train fit --config gartrans --ckpt_path last   # resume

Every option of the module, the data module, the trainer and its callbacks is a flag
(``garmentgnn train fit --help``); ``--print_config`` shows the merged configuration.
At the end of ``fit`` the loss terms and validation metrics per epoch are drawn into
``<log dir>/training_curves.png`` (:class:`~garmentgnn.training.plots.TrainingPlots`).
Beside the configured ``CSVLogger`` every run also logs to TensorBoard (when the
``tensorboard`` package is installed): the same values go to
``<log dir>/tensorboard/events.out.tfevents.*`` (``tensorboard --logdir runs``).

Where it all goes: the loggers' ``save_dir`` is linked to ``--trainer.default_root_dir``
(a ``save_dir`` of their own is overridden), so ``--trainer.default_root_dir DIR`` puts
the log folder ``DIR/logs/version_<n>`` -- metrics, checkpoints, TensorBoard events,
curve plots, ``config.yaml`` -- under DIR; ``--trainer.logger false`` keeps only the
checkpoints, in ``DIR/checkpoints``.  The packaged configs set ``runs/<name>``.
"""
from __future__ import annotations

import importlib.util
import os
import sys
from typing import Any, Optional, Sequence

from lightning.pytorch import Trainer
from lightning.pytorch.cli import LightningCLI
from lightning.pytorch.loggers import CSVLogger, TensorBoardLogger
from lightning.pytorch.utilities import rank_zero_warn

from garmentgnn.training.configs import resolve_config_args
from garmentgnn.training.datamodule import GarmentDataModule
from garmentgnn.training.integrity import CheckpointError, hparam_conflicts, load_checkpoint_file
from garmentgnn.training.module import GarTransModule
from garmentgnn.training.plots import TrainingPlots


def _plain(ns) -> dict:
    """A jsonargparse Namespace (or None) as a plain dict."""
    if ns is None:
        return {}
    return ns.as_dict() if hasattr(ns, "as_dict") else dict(ns)


#: TensorBoard's event files go into this sub-folder of the CSV logger's run folder
TENSORBOARD_SUBDIR = "tensorboard"


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


def _dim(name: str):
    def get(data: GarmentDataModule) -> int:
        return data.dims[name]
    return get


class GarTransCLI(LightningCLI):
    """LightningCLI with the data-dependent model sizes linked from the data module.

    Subcommands: ``fit``, ``validate`` and ``test`` (the test split's metrics);
    Lightning's ``predict`` is not offered (use ``examples/evaluate_checkpoint.py``).
    ``--ckpt_path X`` is checked first: an unreadable or changed file, or a
    ``--model.*`` flag (or config value) that differs from X's hyper-parameters, is a
    :class:`~garmentgnn.training.integrity.CheckpointError`."""

    @staticmethod
    def subcommands() -> dict[str, set[str]]:
        subs = LightningCLI.subcommands()
        return {k: subs[k] for k in ("fit", "validate", "test")}

    def _parse_ckpt_path(self) -> None:
        sub = self.config.get("subcommand") if self.config is not None else None
        ckpt_path = self.config[sub].get("ckpt_path") if sub else None
        if not ckpt_path or ckpt_path in ("last", "best", "hpc", "registry"):
            return super()._parse_ckpt_path()
        ckpt = load_checkpoint_file(ckpt_path)
        given = _plain(self.config[sub].get("model"))
        defaults = _plain(self._subcommand_parsers[sub].get_defaults().get("model"))
        bad = hparam_conflicts(given, defaults, ckpt.get("hyper_parameters") or {})
        if bad:
            what = ", ".join(f"--model.{k} {v!r} (checkpoint: {c!r})"
                             for k, (v, c) in sorted(bad.items()))
            raise CheckpointError(f"{ckpt_path}: {what}; the model is rebuilt from the "
                                  f"checkpoint's hyper-parameters, so drop the flag(s), or "
                                  f"start a new run without --ckpt_path")
        return super()._parse_ckpt_path()

    def instantiate_trainer(self, **kwargs: Any) -> Trainer:
        """Lightning's trainer, with a TensorBoard logger beside the CSV one
        (:func:`add_tensorboard`)."""
        trainer = super().instantiate_trainer(**kwargs)
        add_tensorboard(trainer)
        return trainer

    def add_arguments_to_parser(self, parser) -> None:
        parser.link_arguments("data.nystrom_dim", "model.nystrom_dim")
        # every logger writes under the trainer's root folder (the current folder when it
        # is unset, as in Lightning), so --trainer.default_root_dir moves logs,
        # checkpoints, TensorBoard events and curve plots together
        parser.link_arguments("trainer.default_root_dir", "trainer.logger.init_args.save_dir",
                              compute_fn=lambda d: d or os.getcwd())
        for name in ("num_joints", "num_body_vertices"):
            parser.link_arguments("data", f"model.{name}", apply_on="instantiate",
                                  compute_fn=_dim(name))


def main(args: Optional[Sequence[str]] = None, run: bool = True,
         prog: Optional[str] = None) -> GarTransCLI:
    """Run the CLI (``args`` default: ``sys.argv[1:]``; ``--config NAME`` may name a
    packaged configuration, :func:`~garmentgnn.training.configs.resolve_config_args`;
    ``prog``: the program name its usage lines show); returns the CLI object.  Every
    run also gets :class:`TrainingPlots` (``training_curves.png`` in the log folder) and
    a TensorBoard log (:func:`add_tensorboard`)."""
    args = resolve_config_args(sys.argv[1:] if args is None else args)
    return GarTransCLI(GarTransModule, GarmentDataModule, args=args,
                       run=run, seed_everything_default=0,
                       parser_kwargs={"prog": prog} if prog else None,
                       save_config_kwargs={"overwrite": True},
                       trainer_defaults={"callbacks": [TrainingPlots()]})


if __name__ == "__main__":  # pragma: no cover
    main()
