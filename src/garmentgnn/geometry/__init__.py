"""Pure, batched tensor mesh operations (no knowledge of bodies, garments or models)."""
from garmentgnn.geometry.mesh import edge_features, faces_to_edge_index, grid_mesh

__all__ = ["edge_features", "faces_to_edge_index", "grid_mesh"]
