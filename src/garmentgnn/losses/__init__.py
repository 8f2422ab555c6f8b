"""Training losses: supervised (Eqs. 7-9) and physics-informed (Eqs. 10-13) terms."""
from garmentgnn.losses.gartrans_loss import (
                                             PAPER_WEIGHTS,
                                             GarTransLoss,
                                             LossInputs,
                                             NonFiniteLossError,
                                             edge_loss,
                                             normal_loss,
                                             vertex_loss,
)

__all__ = ["PAPER_WEIGHTS", "GarTransLoss", "LossInputs", "NonFiniteLossError", "edge_loss",
           "normal_loss", "vertex_loss"]
