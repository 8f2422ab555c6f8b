"""What the baselines share: output-layer initialisation and the LBS baseline (skinning itself is
:func:`garmentgnn.models.inputs.skin`, re-exported here)."""
from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor, nn

from garmentgnn.models.inputs import GarmentInputs, check_pose, skin

__all__ = ["LBSBaseline", "check_pose", "skin", "small_init_"]


def small_init_(linear: nn.Linear, scale: float = 1e-2) -> None:
    """Start an output layer near zero (so a fresh model predicts ~LBS / ~free fall)
    while keeping every upstream gradient non-zero."""
    with torch.no_grad():
        linear.weight.mul_(scale)
        linear.bias.zero_()


# --------------------------------------------------------------------------- LBS
class LBSBaseline(nn.Module):
    """No learning: the garment rest mesh skinned to each frame by linear blend
    skinning (the paper's Eq. 1) with the scene's weights -- the same initial state the
    reference simulator starts from.  Static and body-tight by construction: no
    gravity, no dynamics, no collision handling."""

    def forward(self, scene: GarmentInputs, rotations: Tensor,
                translation: Optional[Tensor] = None) -> Tensor:
        """``rotations [B, S, 3]``, ``translation [B, 3]`` -> positions ``[B, V, 3]``."""
        return skin(scene, rotations, translation)[0]
