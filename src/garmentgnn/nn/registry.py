"""Layer registry: swap attention layers by name (``make_layer("sat", ...)``)."""
from __future__ import annotations

from typing import Callable, Dict, Optional

from torch import nn

from garmentgnn.nn.edge_transformer_conv import EdgeTransformerConv
from garmentgnn.nn.gat_conv import GATBaselineConv
from garmentgnn.nn.gt_conv import GraphTransformerConv
from garmentgnn.nn.sat_conv import SATConv
from garmentgnn.nn.structure_aware_conv import StructureAwareTransformerConv

LAYERS: Dict[str, Callable[..., nn.Module]] = {
    "sat": SATConv,
    "gt": GraphTransformerConv,
    "gt_edge": EdgeTransformerConv,
    "structure_aware": StructureAwareTransformerConv,
    "gat": GATBaselineConv,
}


def make_layer(name: str, in_channels: int, out_channels: int, *, edge_dim: Optional[int] = None,
               heads: int = 1, concat: bool = True, **kwargs) -> nn.Module:
    """Build a layer of the common contract by registry name.

    Every layer is called as ``layer(x, edge_index, edge_attr) -> x_out`` like a PyG
    conv; ``return_edge_attr=True`` gives ``(x_out, edge_attr_out)`` for stacks that
    carry edge features from layer to layer.

    Args:
        name: one of ``"sat"``, ``"gt"``, ``"gt_edge"``, ``"structure_aware"``, ``"gat"``.
        in_channels: input node width (``-1``: inferred from the first call).
        out_channels: channels per head.
        edge_dim: input edge feature width (required by ``"sat"`` and ``"gt_edge"``).
        heads: attention heads.
        concat: concatenate (``True``) or average heads.
        **kwargs: passed to the layer's constructor.
    """
    if name not in LAYERS:
        raise ValueError(f"`name`: unknown layer {name!r}; choose one of {sorted(LAYERS)}")
    return LAYERS[name](in_channels, out_channels, edge_dim=edge_dim, heads=heads, concat=concat,
                        **kwargs)
