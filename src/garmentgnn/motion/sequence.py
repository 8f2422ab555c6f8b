"""Pose sequences: local joint rotations + root translation over time."""
from __future__ import annotations

from dataclasses import dataclass
from typing import List, Sequence

import torch
from torch import Tensor

from garmentgnn.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle


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
            raise ValueError(f"`translation`: expected [{T}, 3], got "
                             f"{tuple(self.translation.shape)}")
        if not (torch.isfinite(self.rotations).all() and torch.isfinite(self.translation).all()):
            raise ValueError("`rotations`/`translation`: contain NaN/inf")
        if not self.fps > 0:
            raise ValueError(f"`fps`: must be positive, got {self.fps}")

    @property
    def num_frames(self) -> int:
        return self.rotations.shape[0]

    def __len__(self) -> int:
        return self.num_frames

    @property
    def duration(self) -> float:
        """Seconds from the first to the last frame."""
        return (self.num_frames - 1) / self.fps if self.num_frames else 0.0

    def resample(self, fps: float) -> "Motion":
        """The motion at another frame rate (e.g. 120 fps mocap -> the paper's 30):
        rotations by slerp between neighbouring frames, translation linearly,
        covering the same duration."""
        if not isinstance(fps, (int, float)) or not fps > 0 or fps == float("inf"):
            raise ValueError(f"`fps`: expected a positive finite frame rate, got {fps!r}")
        T = self.num_frames
        if T < 2:
            return Motion(self.rotations.clone(), self.translation.clone(),
                          list(self.joint_names), float(fps))
        n = int(round(self.duration * fps + 1e-9)) + 1
        pos = torch.arange(n, dtype=torch.float64) * (self.fps / fps)
        pos = pos.clamp(max=T - 1)
        i0 = pos.floor().long().clamp(max=T - 2)
        w = (pos - i0).to(self.rotations.dtype)
        R0 = axis_angle_to_matrix(self.rotations[i0])
        R1 = axis_angle_to_matrix(self.rotations[i0 + 1])
        delta = matrix_to_axis_angle(R0.transpose(-1, -2) @ R1)
        rot = matrix_to_axis_angle(R0 @ axis_angle_to_matrix(delta * w.view(-1, 1, 1)))
        wt = w.to(self.translation.dtype).view(-1, 1)
        tr = self.translation[i0] * (1 - wt) + self.translation[i0 + 1] * wt
        return Motion(rot, tr, list(self.joint_names), float(fps))


def match_joints(motion, joint_names: Sequence[str]) -> Tensor:
    """``motion.rotations`` ``[T, S, 3]`` in the order of ``joint_names`` (a body
    skeleton's), matched by name: a motion saved to BVH and loaded back lists its
    joints depth-first, which need not be the skeleton's order.  Raises
    ``ValueError`` naming the unknown and missing joints when the names differ.  An
    object without ``joint_names`` is matched by joint count (and must agree)."""
    rot = motion.rotations
    names = getattr(motion, "joint_names", None)
    target = list(joint_names)
    if names is None:
        if rot.shape[1] != len(target):
            raise ValueError(f"`motion`: has {rot.shape[1]} joints, the skeleton "
                             f"{len(target)}; retarget it first (garmentgnn.motion.retarget)")
        return rot
    names = list(names)
    if names == target:
        return rot
    if len(set(names)) != len(names):
        raise ValueError(f"`motion.joint_names`: repeated names "
                         f"{sorted({n for n in names if names.count(n) > 1})}")
    unknown = [n for n in names if n not in set(target)]
    missing = [n for n in target if n not in set(names)]
    if unknown or missing:
        raise ValueError(f"`motion`: joint names differ from the skeleton's (unknown: "
                         f"{unknown[:8]}, missing: {missing[:8]}); retarget it first "
                         f"(garmentgnn.motion.retarget(motion, skeleton))")
    index = {n: i for i, n in enumerate(names)}
    return rot[:, [index[n] for n in target]]
