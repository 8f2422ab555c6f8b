"""garmentgnn: a PyTorch Geometric toolkit for learned garment deformation (GarTrans)."""

__version__ = "0.1.0"
