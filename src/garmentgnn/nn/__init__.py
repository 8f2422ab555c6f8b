"""Attention layers for garment meshes, all behind one contract (see :mod:`.registry`)."""
from garmentgnn.nn._graph import TensorCache
from garmentgnn.nn.edge_transformer_conv import EdgeTransformerConv
from garmentgnn.nn.gat_conv import GATBaselineConv
from garmentgnn.nn.gt_conv import GraphTransformerConv
from garmentgnn.nn.registry import LAYERS, layer_class, make_layer
from garmentgnn.nn.sat_conv import SATConv
from garmentgnn.nn.structure_aware_conv import StructureAwareTransformerConv

__all__ = [
    "SATConv",
    "GraphTransformerConv",
    "EdgeTransformerConv",
    "StructureAwareTransformerConv",
    "GATBaselineConv",
    "make_layer",
    "layer_class",
    "LAYERS",
    "TensorCache",
]
