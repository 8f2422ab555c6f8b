"""A trained method from its checkpoint file: the one place that loads one.

:func:`load_checkpoint` picks the LightningModule class from what the checkpoint
stores: the module's class path (``hyper_parameters["_class_path"]``, which
``garmentgnn train`` writes), or, in a checkpoint written without the command line (the
bench, a script), the module whose ``model`` argument takes the class of its model
(``hyper_parameters["model"]["class_path"]``): no module is known here by name.
``garmentgnn show``, ``garmentgnn predict`` and the benchmark scripts load checkpoints
through it.
"""
from __future__ import annotations

import os
import typing
from pathlib import Path
from typing import Any, Dict, List, Union

# the packaged modules, imported so that a checkpoint without a module's class path
# finds the module of its model among them
import garmentgnn.training.baselines  # noqa: F401
import garmentgnn.training.module  # noqa: F401
import garmentgnn.training.rollout  # noqa: F401
from garmentgnn.training.base import GarmentModule, stored_module
from garmentgnn.training.integrity import CheckpointError, load_checkpoint_file
from garmentgnn.training.recipes import import_class

PathLike = Union[str, os.PathLike]


def _subclasses(cls: type) -> List[type]:
    out = []
    for sub in cls.__subclasses__():
        out += [sub, *_subclasses(sub)]
    return out


def trains(module: type, model: type) -> bool:
    """Whether the :class:`GarmentModule` subclass ``module`` is handed a model of class
    ``model``: its ``__init__``'s ``model`` argument is annotated with that class (or a
    ``Union`` holding it)."""
    try:
        hint = typing.get_type_hints(module.__init__).get("model")
    except Exception:  # an annotation that does not resolve here
        return False
    options = typing.get_args(hint) if typing.get_origin(hint) is typing.Union else (hint,)
    return any(isinstance(o, type) and issubclass(model, o) for o in options)


def module_class(hparams: Dict[str, Any]) -> type:
    """The :class:`GarmentModule` subclass that a checkpoint's ``hyper_parameters``
    were written by: the class its ``_class_path`` names, else (a checkpoint written
    without the command line) the module whose ``model`` argument takes its model's class
    (:func:`trains`; the most general such module), among the modules imported so
    far."""
    stored = hparams.get("_class_path")
    if stored:
        stored = stored_module(stored)
        try:
            cls = import_class(str(stored))
        except ValueError as err:
            raise CheckpointError(f"its module `{stored}` cannot be imported ({err})") from None
        if not (isinstance(cls, type) and issubclass(cls, GarmentModule)):
            raise CheckpointError(f"its module `{stored}` is not a garmentgnn module "
                                  f"(a GarmentModule)")
        return cls
    model = hparams.get("model")
    path = str(model.get("class_path", "")) if isinstance(model, dict) else ""
    try:
        model_cls = import_class(path)
    except ValueError:
        raise CheckpointError(f"its model `{path or '(none)'}` cannot be imported; load it "
                              f"with the module it was trained with") from None
    found = [m for m in _subclasses(GarmentModule) if trains(m, model_cls)]
    # the most general of them (a subclass of a module inherits the model it takes)
    found = [m for m in found if not any(o is not m and issubclass(m, o) for o in found)]
    if len(found) != 1:
        raise CheckpointError(f"it names no module, and {len(found)} modules take a "
                              f"{model_cls.__name__} ({', '.join(m.__name__ for m in found)}); "
                              f"load it with its module's load_from_checkpoint")
    return found[0]


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
