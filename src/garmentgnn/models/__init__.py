"""GarTrans and its building blocks (never imports the simulator)."""
from garmentgnn.models.gartrans import GarTrans, StaticFeatures, batch_edges, geometric_init_

__all__ = ["GarTrans", "StaticFeatures", "batch_edges", "geometric_init_"]
