"""A shaped body ready to pose, and the protocol every body model follows."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Protocol, Tuple

import torch
from torch import Tensor

from garmentgnn.body.lbs import forward_kinematics, linear_blend_skinning
from garmentgnn.body.skeleton import Skeleton


@dataclass
class Body:
    """A body of one shape in its rest pose (Z up, facing -Y, metres).

    Attributes:
        vertices: ``[V, 3]`` rest-pose vertices (the template with the shape applied).
        faces: ``[F, 3]`` triangles (outward normals, counter-clockwise).
        skeleton: the joint tree.
        joints: ``[S, 3]`` rest joint positions.
        weights: ``[V, S]`` skinning weights, rows summing to 1.
        shape: the model's shape parameters that produced this body (the
            paper's beta; for anny the phenotype values).
    """

    vertices: Tensor
    faces: Tensor
    skeleton: Skeleton
    joints: Tensor
    weights: Tensor
    shape: Optional[Tensor] = None

    def __post_init__(self) -> None:
        V, S = self.vertices.shape[0], self.skeleton.num_joints
        if self.vertices.dim() != 2 or self.vertices.shape[1] != 3:
            raise ValueError(f"`vertices`: expected [V, 3], got {tuple(self.vertices.shape)}")
        if self.faces.dim() != 2 or self.faces.shape[1] != 3:
            raise ValueError(f"`faces`: expected [F, 3], got {tuple(self.faces.shape)}")
        if self.faces.numel() and (int(self.faces.min()) < 0 or int(self.faces.max()) >= V):
            raise ValueError(f"`faces`: indices must lie in [0, {V})")
        if self.joints.shape != (S, 3):
            raise ValueError(f"`joints`: expected [{S}, 3], got {tuple(self.joints.shape)}")
        if self.weights.shape != (V, S):
            raise ValueError(f"`weights`: expected [{V}, {S}], got {tuple(self.weights.shape)}")
        if not torch.isfinite(self.vertices).all():
            raise ValueError("`vertices`: contains NaN/inf")

    def pose(self, rotations: Tensor, translation: Optional[Tensor] = None
             ) -> Tuple[Tensor, Tensor]:
        """Skin the body (Eq. 1): ``rotations`` ``[T, S, 3]`` axis-angle or
        ``[T, S, 3, 3]``, ``translation`` ``[T, 3]``.  Returns posed vertices
        ``[T, V, 3]`` and joints ``[T, S, 3]``."""
        if rotations.shape[1] != self.skeleton.num_joints:
            raise ValueError(f"`rotations`: has {rotations.shape[1]} joints, the skeleton has "
                             f"{self.skeleton.num_joints}; retarget the motion first")
        A, joints = forward_kinematics(rotations.to(self.vertices.dtype), self.joints,
                                       self.skeleton.parents, translation)
        return linear_blend_skinning(self.vertices, self.weights, A), joints


class BodyModel(Protocol):
    """Anything that turns shape parameters into a :class:`Body`."""

    skeleton: Skeleton

    def __call__(self, shape: Optional[Tensor] = None) -> Body:
        ...
