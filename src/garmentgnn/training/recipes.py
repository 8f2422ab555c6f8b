"""The recipes: one complete YAML file per trained method, what ``garmentgnn train``
(LightningCLI's ``--config``), the bench, the benchmark scripts and the examples train.

The packaged ones live in ``garmentgnn/recipes/``:

* ``gartrans.yaml``: the full model;
* ``ablations/<name>.yaml``: each Table 1 ablation (and ``ablations/paper.yaml``, the
  paper's own form of GarTrans);
* ``baselines/<name>.yaml``: the DA-, HOOD- and NCS-style baselines
  (:class:`~garmentgnn.training.BaselineModule`);
* ``mgn.yaml``: the MGN-style learned simulator
  (:class:`~garmentgnn.training.RolloutModule`).

A recipe's ``model:`` names the module (``class_path``) and the arguments where it
differs from the module's defaults (``init_args``), the model it trains among them
(``model: class_path: garmentgnn.models.GarTrans``); ``data:`` the data module's
settings that differ from its defaults, ``trainer:`` the trainer's that differ from
``garmentgnn train``'s (:data:`~garmentgnn.training.lightning_cli.TRAINER_DEFAULTS`).
Every default is written once, in the class that has it.  Any YAML file of that form
is a recipe too: a packaged one is named without its folder's path or ``.yaml``
(``"ablations/gat"``), any other by its path.

:func:`~garmentgnn.training.load_recipe` reads recipes with LightningCLI's own parser
and builds the module, the data module and the trainer's callbacks they describe.
"""
from __future__ import annotations

import importlib
from importlib import resources
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import yaml

__all__ = ["available", "check_one_recipe", "import_class", "model_of", "named_module",
           "recipe_path", "recipes_of_model", "resolve_config_args"]

_ROOT = resources.files("garmentgnn") / "recipes"


def available() -> List[str]:
    """The packaged recipes, as names (``"gartrans"``, ``"ablations/gat"``, ...)."""
    root = Path(str(_ROOT))
    return sorted(str(p.relative_to(root).with_suffix("")) for p in root.rglob("*.yaml"))


def recipe_path(recipe: Union[str, Path]) -> Path:
    """The file of ``recipe``: a YAML file's path, or a packaged recipe's name
    (``"gartrans"``, ``"ablations/gat"``); ``ValueError`` listing the names when it is
    neither."""
    if not isinstance(recipe, (str, Path)) or not str(recipe):
        raise TypeError(f"`recipe`: expected a recipe's name or a YAML file's path, got "
                        f"{recipe!r}")
    if Path(recipe).is_file():
        return Path(recipe)
    name = str(recipe)
    path = (Path(str(_ROOT)) / (name[:-5] if name.endswith(".yaml") else name))
    path = path.with_suffix(".yaml")
    if not path.is_file():
        raise ValueError(f"`recipe`: no file {recipe!r} and no packaged recipe of that name; "
                         f"give a YAML file or one of {', '.join(available())}")
    return path


def _read(path: Union[str, Path]) -> Dict[str, Any]:
    """A recipe file as a plain dict (``{}`` when it cannot be read: LightningCLI
    reports that)."""
    try:
        doc = yaml.safe_load(Path(path).read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return {}
    return doc if isinstance(doc, dict) else {}


def model_of(recipe: Union[str, Path]) -> Dict[str, Optional[str]]:
    """The class paths a recipe names: ``{"module": ..., "model": ...}`` (``None``
    where it names none)."""
    module = _read(recipe_path(recipe)).get("model")
    module = module if isinstance(module, dict) else {}
    model = (module.get("init_args") or {}).get("model")
    return {"module": module.get("class_path"),
            "model": model.get("class_path") if isinstance(model, dict) else None}


def recipes_of_model(class_path: str) -> List[str]:
    """The packaged recipes (ablations left out) whose module trains a model of class
    ``class_path`` (compared by class name): what a checkpoint of that model was
    trained with."""
    name = str(class_path).rsplit(".", 1)[-1]
    return [r for r in available() if not r.startswith("ablations/")
            and str(model_of(r)["model"] or "").rsplit(".", 1)[-1] == name]


def import_class(class_path: str) -> type:
    """The class ``"package.module.Name"`` names; ``ValueError`` naming it when there is
    none."""
    module, _, name = str(class_path).rpartition(".")
    try:
        cls = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError, ValueError):
        cls = None
    if not isinstance(cls, type):
        raise ValueError(f"`class_path`: no class {class_path!r}")
    return cls


def named_module(args: Sequence[str]) -> Optional[str]:
    """The module class that ``args`` (after :func:`resolve_config_args`) train: the last
    ``--model X`` / ``--model.class_path X`` flag or ``--config`` file that names one
    (LightningCLI applies them in order); ``None`` where none does.  A bare class name
    (``BaselineModule``) is one of :mod:`garmentgnn.training`'s."""
    found: Optional[str] = None
    for i, a in enumerate(args):
        key, _, value = a.partition("=")
        if not value and i + 1 < len(args):
            value = args[i + 1]
        if key == "--config" and Path(value).is_file():
            module = _read(value).get("model")
            if isinstance(module, dict) and module.get("class_path"):
                found = str(module["class_path"])
        elif key in ("--model", "--model.class_path") and value \
                and not value.lstrip().startswith(("{", "class_path")) \
                and not value.endswith((".yaml", ".yml")):
            found = value if "." in value else f"garmentgnn.training.{value}"
    return found


def resolve_config_args(args: Sequence[str]) -> List[str]:
    """``args`` with each ``--config NAME`` (or ``--config=NAME``) that is not an existing
    file but a packaged recipe's name replaced by that file's path; a value that is
    neither (nor an inline YAML/JSON document) is a ``ValueError`` listing the packaged
    names."""
    out = list(args)
    configs = []
    for i, a in enumerate(out):
        if a == "--config" and i + 1 < len(out):
            j, value, prefix = i + 1, out[i + 1], ""
        elif a.startswith("--config="):
            j, value, prefix = i, a.split("=", 1)[1], "--config="
        else:
            continue
        if not Path(value).exists() and "\n" not in value and ":" not in value:
            try:
                out[j] = prefix + str(recipe_path(value))
            except (ValueError, TypeError):
                raise ValueError(f"--config {value}: no such file, and no packaged recipe "
                                 f"of that name; give a YAML file or one of "
                                 f"{', '.join(available())}") from None
        configs.append((value, out[j][len(prefix):]))
    check_one_recipe(configs, "--config")
    return out


def check_one_recipe(configs: Sequence[Tuple[str, Union[str, Path]]], flag: str) -> None:
    """Refuse two complete recipes among ``configs`` (``(as given, path)`` pairs): each
    names its module (``model: class_path``), so the later would replace the earlier
    whole, its layer, losses and schedule dropped without a word (``--config
    baselines/da --config ablations/gat`` trained the ablation).  A YAML file of
    changes that names no module goes on top of one recipe as before."""
    complete = [shown for shown, path in configs
                if Path(path).is_file() and isinstance(_read(path).get("model"), dict)
                and _read(path)["model"].get("class_path")]
    if len(complete) > 1:
        given = " and ".join(f"{flag} {c}" for c in complete)
        raise ValueError(f"{given}: each is a complete recipe (it names its module, "
                         f"`model: class_path`), so the later would replace the earlier "
                         f"whole; give one recipe, and its changes as flags or in a YAML "
                         f"file that names no module")
