"""Layer registry: swap attention layers by name (``make_layer("sat", ...)``).

The registry is open: every class with a ``layer_name`` in a ``*_conv.py`` module of
this package is found by that name (:data:`LAYERS`), and any other layer by its class
path (``make_layer("my_layers.toy_conv.ToyConv", ...)``, or ``dynamic_layer:
my_layers.toy_conv.ToyConv`` in a configuration): adding a layer edits no list here
(docs/layers.md, "Adding a layer")."""
from __future__ import annotations

import importlib
import pkgutil
from typing import Dict, Optional

from torch import nn


#: the package whose ``*_conv.py`` modules hold the named layers
PACKAGE = "garmentgnn.nn"


def _package_layers() -> Dict[str, type]:
    """``{layer_name: class}`` of the layers of this package's ``*_conv.py`` modules."""
    found: Dict[str, type] = {}
    path = importlib.import_module(PACKAGE).__path__  # (set before its __init__ runs)
    for info in sorted(pkgutil.iter_modules(path), key=lambda i: i.name):
        if not info.name.endswith("_conv"):
            continue
        module = importlib.import_module(f"{PACKAGE}.{info.name}")
        for obj in vars(module).values():
            name = getattr(obj, "layer_name", None)
            if isinstance(obj, type) and obj.__module__ == module.__name__ and name:
                if name in found:
                    raise RuntimeError(f"layer name {name!r} is taken by both "
                                       f"{found[name].__name__} and {obj.__name__}")
                found[name] = obj
    return found


#: the package's layers by name: ``sat``, ``gt``, ``gt_edge``, ``structure_aware``,
#: ``gat`` (and any ``*_conv.py`` module added beside them)
LAYERS: Dict[str, type] = _package_layers()


def layer_class(name: str) -> type:
    """The layer class ``name`` stands for: a key of :data:`LAYERS`, or a class path
    ``package.module.Class`` of a ``torch.nn.Module``; ``ValueError`` naming both forms
    otherwise."""
    if isinstance(name, str) and name in LAYERS:
        return LAYERS[name]
    cls = None
    if isinstance(name, str) and "." in name:
        module, _, attr = name.rpartition(".")
        try:
            cls = getattr(importlib.import_module(module), attr, None)
        except ImportError:
            cls = None
    if not (isinstance(cls, type) and issubclass(cls, nn.Module)):
        raise ValueError(f"`name`: unknown layer {name!r}; choose one of {sorted(LAYERS)} "
                         f"or give a layer's class path (package.module.Class)")
    return cls


def make_layer(name: str, in_channels: int, out_channels: int, *, edge_dim: Optional[int] = None,
               heads: int = 1, concat: bool = True, **kwargs) -> nn.Module:
    """Build a layer of the common contract by registry name or class path
    (:func:`layer_class`).

    Every layer is called as ``layer(x, edge_index, edge_attr) -> x_out`` like a PyG
    conv; ``return_edge_attr=True`` gives ``(x_out, edge_attr_out)`` for stacks that
    carry edge features from layer to layer.

    Args:
        name: a key of :data:`LAYERS` (``"sat"``, ``"gt"``, ``"gt_edge"``,
            ``"structure_aware"``, ``"gat"``) or a layer's class path.
        in_channels: input node width (``-1``: inferred from the first call).
        out_channels: channels per head.
        edge_dim: input edge feature width (required by ``"sat"`` and ``"gt_edge"``).
        heads: attention heads.
        concat: concatenate (``True``) or average heads.
        **kwargs: passed to the layer's constructor.
    """
    return layer_class(name)(in_channels, out_channels, edge_dim=edge_dim, heads=heads,
                             concat=concat, **kwargs)
