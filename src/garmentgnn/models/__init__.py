"""GarTrans and its building blocks (never imports the simulator)."""
from garmentgnn.models.blocks import batch_edges, geometric_init_
from garmentgnn.models.gartrans import PAPER_FORM, GarTrans, StaticFeatures

__all__ = ["PAPER_FORM", "GarTrans", "StaticFeatures", "batch_edges", "geometric_init_"]
