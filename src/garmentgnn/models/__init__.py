"""GarTrans, the MGN-style learned simulator and their building blocks (never imports the
simulator)."""
from garmentgnn.models.blocks import batch_edges, geometric_init_
from garmentgnn.models.encode_process_decode import EncodeProcessDecode
from garmentgnn.models.gartrans import PAPER_FORM, GarTrans, StaticFeatures
from garmentgnn.models.mgn import MGNStyle, SceneMotion

__all__ = ["PAPER_FORM", "EncodeProcessDecode", "GarTrans", "MGNStyle", "SceneMotion",
           "StaticFeatures", "batch_edges", "geometric_init_"]
