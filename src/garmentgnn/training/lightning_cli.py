"""``garmentgnn train``: Lightning's own CLI over :class:`GarTransModule` and
:class:`GarmentDataModule`, configured by the YAML files in ``configs/``.

The model sizes that depend on the data (number of joints, body vertices, Nyström
width) are linked from the data module, so a config only says *what* to train::

    garmentgnn train fit --config configs/gartrans.yaml --data.root data/small
    garmentgnn train fit --config configs/gartrans.yaml --config configs/ablations/wo_gating.yaml ...
    garmentgnn train fit --config configs/gartrans.yaml --ckpt_path last   # resume

Every option of the module, the data module, the trainer and its callbacks is a flag
(``garmentgnn train fit --help``); ``--print_config`` shows the merged configuration.
At the end of ``fit`` the loss terms and validation metrics per epoch are drawn into
``<log dir>/training_curves.png`` (:class:`~garmentgnn.training.plots.TrainingPlots`).
"""
from __future__ import annotations

from typing import Optional, Sequence

from lightning.pytorch.cli import LightningCLI

from garmentgnn.training.datamodule import GarmentDataModule
from garmentgnn.training.module import GarTransModule
from garmentgnn.training.plots import TrainingPlots


def _dim(name: str):
    def get(data: GarmentDataModule) -> int:
        return data.dims[name]
    return get


class GarTransCLI(LightningCLI):
    """LightningCLI with the data-dependent model sizes linked from the data module."""

    def add_arguments_to_parser(self, parser) -> None:
        parser.link_arguments("data.nystrom_dim", "model.nystrom_dim")
        for name in ("num_joints", "num_body_vertices"):
            parser.link_arguments("data", f"model.{name}", apply_on="instantiate",
                                  compute_fn=_dim(name))


def main(args: Optional[Sequence[str]] = None, run: bool = True) -> GarTransCLI:
    """Run the CLI (``args`` default: ``sys.argv[1:]``); returns the CLI object.  Every
    run also gets :class:`TrainingPlots` (``training_curves.png`` in the log folder)."""
    return GarTransCLI(GarTransModule, GarmentDataModule, args=None if args is None else list(args),
                       run=run, seed_everything_default=0,
                       save_config_kwargs={"overwrite": True},
                       trainer_defaults={"callbacks": [TrainingPlots()]})


if __name__ == "__main__":  # pragma: no cover
    main()
