"""The training configurations: YAML files shipped inside the package
(``garmentgnn/configs/``), read by ``garmentgnn train`` (LightningCLI's ``--config``)
and by the bench alike, so a method's settings are written down once.

* ``gartrans.yaml``: the full model, its data module, trainer and schedule;
* ``ablations/<name>.yaml``: what each Table 1 ablation changes on top of it (and
  ``ablations/paper.yaml``, the paper's own form of GarTrans);
* ``baselines/<name>.yaml``: the :class:`~garmentgnn.training.BaselineModule` settings
  of the DA-, HOOD- and NCS-style baselines, with their data module and trainer.

Each file's ``model:`` names the module (``class_path``) and its arguments
(``init_args``; an ablation gives only the ``init_args`` it changes); a GarTrans module's
arguments hold its model the same way (``model: class_path: garmentgnn.models.GarTrans``).
:func:`module_spec` merges files as ``garmentgnn train`` does, and :func:`instantiate`
builds the module they describe from Python.

``garmentgnn train fit --config gartrans --config ablations/wo_gating`` names packaged
files without their folder or ``.yaml`` (:func:`resolve_config_args`).
"""
from __future__ import annotations

import copy
import importlib
import inspect
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import yaml

__all__ = ["available", "config_path", "configs_of_model", "import_class", "instantiate",
           "load_config", "merge", "module_spec", "resolve_config_args", "schedule_args"]

_ROOT = resources.files("garmentgnn") / "configs"


def available() -> List[str]:
    """The packaged configurations, as names (``"gartrans"``, ``"ablations/gat"``, ...)."""
    root = Path(str(_ROOT))
    return sorted(str(p.relative_to(root).with_suffix("")) for p in root.rglob("*.yaml"))


def config_path(name: str) -> Path:
    """The file of packaged configuration ``name`` (``"gartrans"``, ``"ablations/gat"``);
    ``ValueError`` listing the names when there is no such file."""
    if not isinstance(name, str) or not name:
        raise TypeError(f"`name`: expected a configuration name, got {name!r}")
    path = Path(str(_ROOT)) / (name[:-5] if name.endswith(".yaml") else name)
    path = path.with_suffix(".yaml")
    if not path.is_file():
        raise ValueError(f"`name`: no packaged configuration {name!r}; choose from {available()}")
    return path


@lru_cache(maxsize=None)
def _load(name: str) -> Dict[str, Any]:
    return yaml.safe_load(config_path(name).read_text()) or {}


def load_config(name: str) -> Dict[str, Any]:
    """Packaged configuration ``name`` as a plain dict (a fresh copy on every call)."""
    return copy.deepcopy(_load(name))


def merge(base: Dict[str, Any], top: Dict[str, Any]) -> Dict[str, Any]:
    """``top`` over ``base`` as LightningCLI merges two ``--config`` files: mappings key
    by key, everything else (lists included) replaced."""
    out = copy.deepcopy(base)
    for k, v in top.items():
        out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) \
            else copy.deepcopy(v)
    return out


def module_spec(*names: str) -> Dict[str, Any]:
    """The ``model:`` entry (``{"class_path", "init_args"}``) of packaged configurations
    ``names`` merged in order (``module_spec("gartrans", "ablations/gat")``)."""
    spec: Dict[str, Any] = {}
    for name in names:
        spec = merge(spec, load_config(name).get("model") or {})
    return spec


def configs_of_model(class_path: str) -> List[str]:
    """The packaged configurations (ablations left out) whose module trains a model of
    class ``class_path`` (compared by class name): what a checkpoint of that model was
    trained with."""
    name = str(class_path).rsplit(".", 1)[-1]
    out = []
    for cfg in available():
        if cfg.startswith("ablations/"):
            continue
        model = (module_spec(cfg).get("init_args") or {}).get("model") or {}
        if str(model.get("class_path", "")).rsplit(".", 1)[-1] == name:
            out.append(cfg)
    return out


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


def instantiate(spec: Dict[str, Any], sizes: Optional[Dict[str, Any]] = None) -> Any:
    """The object a ``{"class_path", "init_args"}`` spec describes (a packaged
    configuration's ``model:`` entry, :func:`module_spec`), nested specs built first.
    ``sizes`` (:attr:`GarmentDataModule.dims`) fill the arguments of that name a class
    takes and the spec leaves out, as ``garmentgnn train`` links them from the data."""
    if not isinstance(spec, dict) or "class_path" not in spec:
        raise ValueError(f"`spec`: expected {{'class_path': ..., 'init_args': ...}}, got "
                         f"{spec!r}")
    cls = import_class(spec["class_path"])
    args = {k: instantiate(v, sizes) if isinstance(v, dict) and "class_path" in v else v
            for k, v in (spec.get("init_args") or {}).items()}
    params = inspect.signature(cls.__init__).parameters
    args.update({k: v for k, v in (sizes or {}).items() if k in params and k not in args})
    return cls(**args)


def schedule_args(config: Dict[str, Any]) -> Optional[Dict[str, Any]]:
    """The ``init_args`` of the :class:`ProgressiveSchedule` callback in a configuration's
    ``trainer.callbacks`` (``None`` when it lists none)."""
    for cb in (config.get("trainer") or {}).get("callbacks") or []:
        if str(cb.get("class_path", "")).endswith("ProgressiveSchedule"):
            return dict(cb.get("init_args") or {})
    return None


def _ablation_name(path: str) -> Optional[str]:
    """``"ablations/<name>"`` when ``path`` is a packaged ablation file, else ``None``."""
    try:
        rel = Path(path).resolve().relative_to(Path(str(_ROOT)).resolve() / "ablations")
    except (ValueError, OSError):
        return None
    return f"ablations/{rel.with_suffix('')}"


def _module_named(path: str) -> Optional[str]:
    """The module the YAML file ``path`` names (``model: class_path:``), as a base
    configuration does; ``None`` when it names none, ``""`` when it cannot be read
    (LightningCLI reports that)."""
    try:
        doc = yaml.safe_load(Path(path).read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return ""
    model = doc.get("model") if isinstance(doc, dict) else None
    return str(model["class_path"]) if isinstance(model, dict) and "class_path" in model \
        else None


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
            found = _module_named(value) or found
        elif key in ("--model", "--model.class_path") and value \
                and not value.lstrip().startswith(("{", "class_path")) \
                and not value.endswith((".yaml", ".yml")):
            found = value if "." in value else f"garmentgnn.training.{value}"
    return found


def resolve_config_args(args: Sequence[str]) -> List[str]:
    """``args`` with each ``--config NAME`` (or ``--config=NAME``) that is not an existing
    file but a packaged configuration's name replaced by that file's path; a value that
    is neither (nor an inline YAML/JSON document) is a ``ValueError`` listing the
    packaged names.

    An ablation (``ablations/<name>``) says only what it changes on top of GarTrans: given
    without a configuration before it that names the module (``--config gartrans``), it
    would train without GarTrans's schedule, checkpoints and loss weights (after a
    baseline's, another module's), so that is a ``ValueError`` naming the flags to give."""
    out = list(args)
    base: Optional[str] = None  # the module the last --config naming one named
    for i, a in enumerate(out):
        if a == "--config" and i + 1 < len(out):
            j, value, prefix = i + 1, out[i + 1], ""
        elif a.startswith("--config="):
            j, value, prefix = i, a.split("=", 1)[1], "--config="
        else:
            continue
        if not Path(value).exists() and "\n" not in value and ":" not in value:
            try:
                out[j] = prefix + str(config_path(value))
            except (ValueError, TypeError):
                raise ValueError(f"--config {value}: no such file, and no packaged "
                                 f"configuration of that name; give a YAML file or one of "
                                 f"{', '.join(available())}") from None
        path = out[j][len(prefix):]
        ablation = _ablation_name(path) if Path(path).is_file() else None
        if ablation is not None and not (base == "" or str(base).endswith("GarTransModule")):
            after = f" (not on {base})" if base else ""
            raise ValueError(f"--config {value}: an ablation changes only what differs from "
                             f"GarTrans; give the GarTrans configuration before it{after}: "
                             f"--config gartrans --config {ablation}")
        if Path(path).is_file() and ablation is None:
            base = _module_named(path) or base
    return out
