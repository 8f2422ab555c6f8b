"""A trained method from its checkpoint file: the one place that loads one.

:func:`load_checkpoint` picks the LightningModule class from what the checkpoint
stores: the module's class path (``hyper_parameters["_class_path"]``, which
``garmentgnn train`` writes), or, in a checkpoint written without the command line (the
bench, a script), the module that trains the class of its model
(``hyper_parameters["model"]["class_path"]``).  ``garmentgnn show``, ``garmentgnn
predict`` and the benchmark scripts load checkpoints through it.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Dict, Union

from garmentgnn.models import MGNStyle
from garmentgnn.training.base import GarmentModule
from garmentgnn.training.baselines import BaselineModule
from garmentgnn.training.integrity import CheckpointError, load_checkpoint_file
from garmentgnn.training.module import GarTransModule
from garmentgnn.training.recipes import import_class
from garmentgnn.training.simulator import SimulatorModule

PathLike = Union[str, os.PathLike]


def module_class(hparams: Dict[str, Any]) -> type:
    """The :class:`GarmentModule` subclass that a checkpoint's ``hyper_parameters``
    were written by: the class its ``_class_path`` names, else the module that trains
    its model's class (:class:`SimulatorModule` for the MGN-style simulator,
    :class:`BaselineModule` for a baseline's model, :class:`GarTransModule` otherwise)."""
    stored = hparams.get("_class_path")
    if stored:
        try:
            cls = import_class(str(stored))
        except ValueError as err:
            raise CheckpointError(f"its module `{stored}` cannot be imported ({err})") from None
        if not (isinstance(cls, type) and issubclass(cls, GarmentModule)):
            raise CheckpointError(f"its module `{stored}` is not a garmentgnn module "
                                  f"(a GarmentModule)")
        return cls
    model = hparams.get("model")
    model_cls = str(model.get("class_path", "")) if isinstance(model, dict) else ""
    name = model_cls.rsplit(".", 1)[-1]
    if name == MGNStyle.__name__:
        return SimulatorModule
    if hparams.get("method") is not None or name in {c.__name__ for c in BaselineModule.METHODS}:
        return BaselineModule
    return GarTransModule


def load_checkpoint(path: PathLike) -> GarmentModule:
    """The trained method of a Lightning checkpoint (the module class that
    :func:`module_class` reads from it), on the CPU, in eval mode.  A missing file is a
    ``FileNotFoundError``; a changed, truncated or foreign one the
    :class:`~garmentgnn.training.integrity.CheckpointError` naming it and the fix."""
    if not Path(path).is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    cls = module_class(load_checkpoint_file(path).get("hyper_parameters") or {})
    try:
        return cls.load_from_checkpoint(str(path), map_location="cpu").eval()
    except (ValueError, TypeError):
        raise
    except Exception:  # a truncated or foreign file: the error naming it and the fix
        load_checkpoint_file(path)
        raise


__all__ = ["load_checkpoint", "module_class"]
