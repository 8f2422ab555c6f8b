"""What the baselines share: skinning a garment (Eq. 1) and small MLPs."""
from __future__ import annotations

from typing import Optional, Sequence, Tuple

import torch
from torch import Tensor, nn

from garmentgnn.body.lbs import forward_kinematics, linear_blend_skinning
from garmentgnn.models.inputs import GarmentInputs

__all__ = ["LBSBaseline", "check_pose", "mlp", "skin", "small_init_"]


def check_pose(scene: GarmentInputs, rotations: Tensor, translation: Optional[Tensor],
                name: str = "rotations") -> None:
    if rotations.dim() != 3 or rotations.shape[1:] != (scene.num_joints, 3):
        raise ValueError(f"`{name}`: expected [B, {scene.num_joints}, 3] axis-angle, got "
                         f"{tuple(rotations.shape)}")
    if translation is not None and translation.shape != (rotations.shape[0], 3):
        raise ValueError(f"`translation`: expected [{rotations.shape[0]}, 3], got "
                         f"{tuple(translation.shape)}")


def skin(scene: GarmentInputs, rotations: Tensor, translation: Optional[Tensor] = None,
         offsets: Optional[Tensor] = None) -> Tuple[Tensor, Tensor]:
    """Linear blend skinning (Eq. 1) of the rest garment, plus optional canonical offsets.

    Args:
        rotations: ``[B, S, 3]`` local axis-angle joint rotations.
        translation: ``[B, 3]`` root translation (default zero).
        offsets: ``[B, V, 3]`` added to the rest vertices *before* skinning.

    Returns:
        ``(positions [B, V, 3], posed joints [B, S, 3])`` in the dtype of ``rest_pos``
        (the computation follows the simulator's: kinematics in that dtype).
    """
    check_pose(scene, rotations, translation)
    dt = scene.rest_pos.dtype
    A, joints = forward_kinematics(rotations.to(dt), scene.rest_joints.to(dt), scene.parents,
                                   None if translation is None else translation.to(dt))
    verts = scene.rest_pos if offsets is None else scene.rest_pos + offsets
    return linear_blend_skinning(verts, scene.skin_weights.to(dt), A), joints


def mlp(sizes: Sequence[int], act: type = nn.ELU, norm: bool = False) -> nn.Sequential:
    layers = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        layers.append(nn.Linear(a, b))
        if i < len(sizes) - 2:
            layers.append(act())
    if norm:
        layers.append(nn.LayerNorm(sizes[-1]))
    return nn.Sequential(*layers)


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
