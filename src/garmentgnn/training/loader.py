"""Recipes from Python: :func:`load_recipe` reads them with ``garmentgnn train``'s own
parser (:class:`~garmentgnn.training.lightning_cli.GarmentCLI`, LightningCLI's) and
builds the module, the data module and the callbacks they describe, and
:meth:`Recipe.trainer` their ``Trainer``: what the bench, the benchmark scripts and the
examples train, with the same defaults, links and checks as the command::

    recipe = load_recipe("ablations/gat", args=["--data.root", "data/small"])
    recipe.trainer(max_epochs=2).fit(recipe.module, recipe.datamodule)
"""
from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Union

from lightning.pytorch import Trainer, seed_everything

from garmentgnn.training.base import GarmentModule
from garmentgnn.training.datamodule import GarmentDataModule
from garmentgnn.training.lightning_cli import GarmentCLI
from garmentgnn.training.recipes import (available, check_one_recipe, import_class,
                                         model_of, named_module, recipe_path)

__all__ = ["Recipe", "load_recipe"]


class _RecipeCLI(GarmentCLI):
    """:class:`GarmentCLI` that parses on construction and builds (seeds, instantiates
    the module and the data module) only when :meth:`build` is called, and its trainer
    only when :meth:`Recipe.trainer` is."""

    _building = False

    def instantiate_classes(self) -> None:
        if not self._building:
            return
        self.config_init = self.parser.instantiate_classes(self.config)
        self.datamodule, self.model = self.config_init["data"], self.config_init["model"]

    def build(self) -> None:
        self._building = True
        seed = self.config.get("seed_everything")  # an int once parsed (True drew one)
        if seed is not None and not isinstance(seed, bool):
            seed_everything(seed, workers=True, verbose=False)
        self.instantiate_classes()


class Recipe:
    """What :func:`load_recipe` read and built.

    Attributes:
        module: the :class:`GarmentModule` (its model handed to it, the data's sizes
            linked in).
        datamodule: the :class:`GarmentDataModule`.
        callbacks: the recipe's trainer callbacks (its checkpoints; the module's own,
            such as GarTrans's schedule, come from its ``configure_callbacks``).
        config: the parsed configuration as a plain dict (what ``--print_config``
            shows), with the values ``set`` changed.
    """

    def __init__(self, cli: _RecipeCLI) -> None:
        self._cli = cli
        self.module: GarmentModule = cli.model
        self.datamodule: GarmentDataModule = cli.datamodule
        self.callbacks: List[Any] = list(cli.config_init.trainer.get("callbacks") or [])
        self.config: Dict[str, Any] = cli.config.as_dict()
        # the parser's instantiators outlive the call (jsonargparse keeps the latest
        # parser): the CLI keeps only the trainer's settings, not the module and data
        cli.model = cli.datamodule = None
        cli.config_init.model = cli.config_init.data = None

    def trainer(self, **overrides: Any) -> Trainer:
        """The recipe's ``Trainer``: its ``trainer:`` settings over
        :data:`~garmentgnn.training.lightning_cli.TRAINER_DEFAULTS`, with ``overrides``
        (``Trainer`` arguments; a ``callbacks`` list replaces the recipe's).  Build one
        per loaded recipe: its callbacks hold the state of one fit."""
        return self._cli.instantiate_trainer(**overrides)

    def __repr__(self) -> str:
        return (f"Recipe(module={type(self.module).__name__}, "
                f"model={type(getattr(self.module, 'model', None)).__name__}, "
                f"root={self.datamodule.root})")


def parser_problem(text: str) -> "tuple[Optional[str], str]":
    """``(key, problem)`` of the parser's message: the innermost ``Parser key "K":`` and
    the line after it (its first line names only the outermost key, ``"model"``, above
    a dump of the whole configuration)."""
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    at = [i for i, ln in enumerate(lines) if ln.startswith("Parser key")]
    if not at:
        return None, lines[0] if lines else text
    i = at[-1]
    key = lines[i].split('"')[1] if lines[i].count('"') >= 2 else None
    return key, (f"{lines[i].rstrip(':')}: {lines[i + 1]}" if i + 1 < len(lines)
                 else lines[i])


def load_recipe(*recipes: Union[str, Path], args: Sequence[str] = (),
                data: Optional[Dict[str, Any]] = None,
                set: Optional[Dict[str, Any]] = None) -> Recipe:
    """Read ``recipes`` (packaged names or YAML paths, later ones over earlier ones, as
    repeated ``--config``; at most one of them a complete recipe, the others files of
    changes that name no module), ``args`` (``garmentgnn train`` flags, e.g.
    ``["--data.root", "data/small", "--seed_everything", "1"]``) and ``data`` (data
    module settings as values, ``{"root": path, "val_split": None, "history": 2}``,
    given as the ``--data.*`` flags after ``args``) with the CLI's parser, change the
    parsed values ``set`` names (dotted keys such as ``"model.init_args.lr"``; a
    callable value is applied to the recipe's value), seed, and build the module, the
    data module and the callbacks.  A flag or a value the parser rejects is a
    ``ValueError`` with its message; sizes linked from the data (``nystrom_dim``) follow
    ``args`` and ``data``, not ``set``."""
    if not recipes:
        raise ValueError("`recipes`: give at least one recipe (e.g. 'gartrans'); "
                         f"the packaged ones: {', '.join(available())}")
    for r in recipes:  # a module that does not import: named, not blamed on `args`
        cls = model_of(r)["module"]
        if cls:
            try:
                import_class(cls if "." in cls else f"garmentgnn.training.{cls}")
            except ValueError:
                where = str(r) if str(recipe_path(r)) == str(r) else f"{r} ({recipe_path(r)})"
                raise ValueError(f"`recipes`: {where} names the module "
                                 f"`model: class_path: {cls}`, and there is no such class; "
                                 f"name a GarmentModule, e.g. garmentgnn.training."
                                 f"GarTransModule") from None
    if isinstance(args, str):
        raise TypeError("`args`: expected a list of flags, got a string; "
                        "e.g. ['--data.root', 'data/small']")
    argv: List[str] = []
    for r in recipes:
        argv += ["--config", str(recipe_path(r))]
    check_one_recipe([(str(r), recipe_path(r)) for r in recipes], "recipe")
    argv += [str(a) for a in args]
    for key, value in (data or {}).items():  # a string as it is, anything else as JSON
        argv += [f"--data.{key}", value if isinstance(value, str) else
                 str(value) if isinstance(value, Path) else json.dumps(value)]
    try:
        with warnings.catch_warnings():  # (that the process has command-line arguments too)
            warnings.filterwarnings("ignore", "LightningCLI's args parameter")
            cli = _RecipeCLI(GarmentModule, GarmentDataModule, args=argv,
                             default_model=named_module(argv), run=False,
                             seed_everything_default=0, save_config_callback=None,
                             auto_configure_optimizers=False)
    except SystemExit as err:  # jsonargparse reports a bad flag by exiting
        raise ValueError(f"`args`: the recipe {list(map(str, recipes))} with {list(args)} "
                         f"does not parse (its message above)") from err
    for key, value in (set or {}).items():
        if key not in cli.config:
            raise ValueError(f"`set`: {key!r} is no setting of the recipe; give a dotted "
                             f"key of its configuration (e.g. 'model.init_args.lr')")
        cli.config[key] = value(cli.config[key]) if callable(value) else value
    try:
        cli.parser.validate(cli.config)
    except (TypeError, ValueError) as err:
        key, problem = parser_problem(str(err))
        named = [k for k in (set or {}) if key is not None and k.rsplit(".", 1)[-1] == key]
        which = ", ".join(f"{k!r} = {set[k]!r}" for k in named) if named else \
            ", ".join(map(repr, set or {}))
        raise ValueError(f"`set`: {which}: {problem}") from None
    cli.build()
    return Recipe(cli)
