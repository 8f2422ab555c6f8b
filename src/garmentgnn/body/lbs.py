"""Forward kinematics and linear blend skinning, the paper's W(T, J, theta, W) (Eq. 1)."""
from __future__ import annotations

from typing import Optional, Tuple

import torch
from torch import Tensor

from garmentgnn.geometry.rotations import axis_angle_to_matrix


def as_rotation_matrices(rotations: Tensor) -> Tensor:
    """Axis-angle ``[T, S, 3]`` or matrices ``[T, S, 3, 3]`` (told apart by rank) to matrices."""
    if rotations.dim() == 3 and rotations.shape[-1] == 3:
        return axis_angle_to_matrix(rotations)
    if rotations.dim() == 4 and rotations.shape[-2:] == (3, 3):
        return rotations
    raise ValueError(f"`rotations`: expected [T, S, 3] axis-angle or [T, S, 3, 3] matrices, "
                     f"got {tuple(rotations.shape)}")


def forward_kinematics(rotations: Tensor, rest_joints: Tensor, parents: Tensor,
                       translation: Optional[Tensor] = None) -> Tuple[Tensor, Tensor]:
    """Global joint transforms of a posed skeleton.

    Rotations are local, relative to the parent, in world-aligned rest axes
    (SMPL's convention): ``G_k = G_parent(k) [R_k | j_k - j_parent(k)]``.

    Args:
        rotations: ``[T, S, 3]`` axis-angle or ``[T, S, 3, 3]`` matrices.
        rest_joints: ``[S, 3]`` (or ``[T, S, 3]``) rest joint positions.
        parents: ``[S]`` parent indices, root ``-1``, parents before children.
        translation: ``[T, 3]`` root translation (default zero).

    Returns:
        ``(A, joints)``: ``A [T, S, 4, 4]`` maps rest-pose points to posed points
        for each joint (``G_k`` with the rest joint removed), and the posed joint
        positions ``[T, S, 3]``.
    """
    R = as_rotation_matrices(rotations)
    T, S = R.shape[0], R.shape[1]
    J = rest_joints.expand(T, S, 3) if rest_joints.dim() == 2 else rest_joints
    par = parents.tolist()
    rel = J.clone()
    rel[:, 1:] = J[:, 1:] - J[:, par[1:]]
    rot, pos = [R[:, 0]], [rel[:, 0]]
    for k in range(1, S):
        p = par[k]
        rot.append(rot[p] @ R[:, k])
        pos.append(pos[p] + (rot[p] @ rel[:, k].unsqueeze(-1)).squeeze(-1))
    G_R = torch.stack(rot, 1)  # [T, S, 3, 3]
    G_t = torch.stack(pos, 1)  # [T, S, 3]
    if translation is not None:
        G_t = G_t + translation.unsqueeze(1)
    # A_k x = G_R (x - j_k) + G_t
    A = torch.zeros(T, S, 4, 4, dtype=R.dtype, device=R.device)
    A[..., :3, :3] = G_R
    A[..., :3, 3] = G_t - (G_R @ J.unsqueeze(-1)).squeeze(-1)
    A[..., 3, 3] = 1.0
    return A, G_t


def blend_transforms(weights: Tensor, transforms: Tensor) -> Tensor:
    """Each vertex's blended skinning transform ``M_i = sum_k w_ik A_k`` (Eq. 1).

    Args:
        weights: ``[V, S]`` (or ``[T, V, S]``) skinning weights, rows summing to 1.
        transforms: ``[T, S, 4, 4]`` from :func:`forward_kinematics`.

    Returns:
        ``[T, V, 4, 4]``: ``M_i`` maps vertex ``i``'s rest position to its skinned one.
    """
    eq = "vs,tsij->tvij" if weights.dim() == 2 else "tvs,tsij->tvij"
    return torch.einsum(eq, weights, transforms)


def linear_blend_skinning(vertices: Tensor, weights: Tensor, transforms: Tensor) -> Tensor:
    """``v'_i = sum_k w_ik A_k v_i`` (Eq. 1).

    Args:
        vertices: rest vertices ``[V, 3]`` or per-frame ``[T, V, 3]`` (e.g. with
            blend shapes, Eq. 2).
        weights: ``[V, S]`` (or ``[T, V, S]``) skinning weights, rows summing to 1.
        transforms: ``[T, S, 4, 4]`` from :func:`forward_kinematics`.
    """
    T = transforms.shape[0]
    v = vertices.expand(T, *vertices.shape[-2:]) if vertices.dim() == 2 else vertices
    M = blend_transforms(weights, transforms)  # [T, V, 4, 4]
    return (M[..., :3, :3] @ v.unsqueeze(-1)).squeeze(-1) + M[..., :3, 3]
