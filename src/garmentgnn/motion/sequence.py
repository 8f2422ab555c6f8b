"""Pose sequences: local joint rotations + root translation over time."""
from __future__ import annotations

from dataclasses import dataclass
from typing import List

import torch
from torch import Tensor


@dataclass
class Motion:
    """A pose sequence at ``fps`` frames per second (the paper uses 30).

    Attributes:
        rotations: ``[T, S, 3]`` local axis-angle rotations, relative to the
            parent in world-aligned rest axes (the convention of
            :func:`garmentgnn.body.forward_kinematics`).
        translation: ``[T, 3]`` root translation in metres (Z up).
        joint_names: the ``S`` joint names the rotations refer to.
        fps: frame rate.
    """

    rotations: Tensor
    translation: Tensor
    joint_names: List[str]
    fps: float = 30.0

    def __post_init__(self) -> None:
        if self.rotations.dim() != 3 or self.rotations.shape[-1] != 3:
            raise ValueError(f"`rotations`: expected [T, S, 3] axis-angle, got "
                             f"{tuple(self.rotations.shape)}")
        T, S = self.rotations.shape[:2]
        if len(self.joint_names) != S:
            raise ValueError(f"`joint_names`: {len(self.joint_names)} names for {S} joints")
        if self.translation.shape != (T, 3):
            raise ValueError(f"`translation`: expected [{T}, 3], got {tuple(self.translation.shape)}")
        if not (torch.isfinite(self.rotations).all() and torch.isfinite(self.translation).all()):
            raise ValueError("`rotations`/`translation`: contain NaN/inf")
        if not self.fps > 0:
            raise ValueError(f"`fps`: must be positive, got {self.fps}")

    @property
    def num_frames(self) -> int:
        return self.rotations.shape[0]

    def __len__(self) -> int:
        return self.num_frames
