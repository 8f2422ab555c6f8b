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
"""
from __future__ import annotations

import sys
from typing import Optional, Sequence

from lightning.pytorch.cli import LightningCLI

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

    def add_arguments_to_parser(self, parser) -> None:
        parser.link_arguments("data.nystrom_dim", "model.nystrom_dim")
        for name in ("num_joints", "num_body_vertices"):
            parser.link_arguments("data", f"model.{name}", apply_on="instantiate",
                                  compute_fn=_dim(name))


def main(args: Optional[Sequence[str]] = None, run: bool = True) -> GarTransCLI:
    """Run the CLI (``args`` default: ``sys.argv[1:]``; ``--config NAME`` may name a
    packaged configuration, :func:`~garmentgnn.training.configs.resolve_config_args`);
    returns the CLI object.  Every
    run also gets :class:`TrainingPlots` (``training_curves.png`` in the log folder)."""
    args = resolve_config_args(sys.argv[1:] if args is None else args)
    return GarTransCLI(GarTransModule, GarmentDataModule, args=args,
                       run=run, seed_everything_default=0,
                       save_config_kwargs={"overwrite": True},
                       trainer_defaults={"callbacks": [TrainingPlots()]})


if __name__ == "__main__":  # pragma: no cover
    main()
