"""A trained method from its checkpoint file: the one place that loads one.

:func:`load_checkpoint` picks the LightningModule class from what the checkpoint
stores: the module's class path (``hyper_parameters["_class_path"]``, which
``garmentgnn train`` writes), or, in a checkpoint written without the command line (the
bench, a script), the module whose ``model`` argument takes the class of its model
(``hyper_parameters["model"]["class_path"]``): no module is known here by name.
``garmentgnn show``, ``garmentgnn predict`` and the benchmark scripts load checkpoints
through it.  :func:`fork_checkpoint` writes a resumable copy of one with some of its
settings changed: a branch of a run that keeps everything else it had.
"""
from __future__ import annotations

import inspect
import os
import typing
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Union

import torch

# the packaged modules, imported so that a checkpoint without a module's class path
# finds the module of its model among them
import garmentgnn.training.baselines  # noqa: F401
import garmentgnn.training.module  # noqa: F401
import garmentgnn.training.rollout  # noqa: F401
from garmentgnn.training.base import GarmentModule, stored_module
from garmentgnn.training.datamodule import MODEL_INPUTS
from garmentgnn.training.integrity import (CheckpointError, load_checkpoint_file,
                                           stamp_checkpoint)
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


def _changed(ckpt: Dict[str, Any], entry: str, changes: Mapping[str, Any],
             arg: str, fixed: tuple, later: tuple = ()) -> None:
    saved = ckpt.get(entry)
    if changes and not isinstance(saved, dict):
        raise ValueError(f"`{arg}`: the checkpoint has no {entry!r} to change; fork a "
                         f"checkpoint written by `garmentgnn train fit`")
    known = set(saved) | (set(later) - {"self", "args", "kwargs"})
    for k, v in changes.items():
        if k not in known or k in fixed:
            names = ", ".join(sorted(n for n in known if n not in fixed))
            raise ValueError(f"`{arg}`: {k!r} is not a setting the checkpoint can change; "
                             f"give some of: {names}")
        saved[k] = v


def fork_checkpoint(source: PathLike, dest: PathLike,
                    model: Optional[Mapping[str, Any]] = None,
                    data: Optional[Mapping[str, Any]] = None) -> Path:
    """Write ``dest``: the checkpoint ``source`` with some of its module's settings
    (``model``, e.g. ``{"rollout": 5}``) and its data module's (``data``, e.g.
    ``{"chunk": 7}``) changed, and its integrity digest renewed.

    ``garmentgnn train fit --ckpt_path DEST`` with the flags of the changed settings
    then resumes a branch of the run that keeps everything else the run had: its
    weights, their moving average, the optimizer's state, the step (so the learning
    rate's schedule) and the data order's seed and place.  A resumed fit refuses flags
    that differ from its checkpoint; this is how a run changes course on purpose.  The
    module's architecture (``model``'s own ``model`` entry), the data's root and the
    inputs the model reads (``MODEL_INPUTS``: ``history``, ``num_landmarks``,
    ``nystrom_dim``) stay.  A setting the module gained after the checkpoint was
    written (its default until now) can be given too.
    The forked checkpoint is loaded before it is kept: a value its module refuses is
    that module's ``ValueError``, and nothing is written."""
    dest = Path(dest)
    if dest.resolve() == Path(source).resolve():
        raise ValueError(f"`dest`: {dest} is the source checkpoint; give another path")
    ckpt = load_checkpoint_file(source)
    hp = ckpt.get("hyper_parameters")
    later = ()  # the module's settings added after the checkpoint was written
    if model and isinstance(hp, dict):
        later = tuple(inspect.signature(module_class(hp).__init__).parameters)
    _changed(ckpt, "hyper_parameters", dict(model or {}), "model", ("model", "_class_path"),
             later)
    _changed(ckpt, "datamodule_hyper_parameters", dict(data or {}), "data",
             ("root", "_instantiator") + MODEL_INPUTS)
    stamp_checkpoint(ckpt)
    dest.parent.mkdir(parents=True, exist_ok=True)
    part = dest.with_name(dest.name + ".part")
    torch.save(ckpt, part)
    try:
        load_checkpoint(part)  # the module built from the changed settings
    except BaseException:
        part.unlink()
        raise
    os.replace(part, dest)
    return dest


__all__ = ["fork_checkpoint", "load_checkpoint", "module_class"]
