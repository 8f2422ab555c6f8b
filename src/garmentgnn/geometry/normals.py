"""Face normals, face areas and vertex normals of batched triangle meshes.

Positions are ``[V, 3]`` or ``[..., V, 3]``; faces are one ``[F, 3]`` long tensor shared
by the whole batch.  Everything is differentiable in the positions; degenerate
(zero-area) faces give zero normals and isolated vertices zero vertex normals, never
NaN (the norm is computed with a floor, see ``_validate.safe_norm``).
"""
from __future__ import annotations

from typing import Tuple

import torch
from torch import Tensor

from ._index import gather_rows, scatter_rows
from ._validate import check_mesh, safe_norm

__all__ = ["face_vertices", "face_cross", "face_normals", "face_areas", "face_angles",
           "face_angles_unchecked",
           "vertex_normals", "scatter_faces_to_vertices"]


def face_vertices(pos: Tensor, faces: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
    """Corner positions ``(p0, p1, p2)``, each ``[..., F, 3]`` (no validation; batched:
    strided views of one vertex-major gather, :func:`~garmentgnn.geometry._index.gather_rows`)."""
    return gather_rows(pos, faces).unbind(-2)


def face_cross(pos: Tensor, faces: Tensor) -> Tensor:
    """Un-normalised face normals ``(p1 - p0) x (p2 - p0)``, ``[..., F, 3]``.

    Their norm is twice the face area; their direction follows the right-hand rule of
    the face winding (counter-clockwise seen from the normal side).
    """
    p0, p1, p2 = face_vertices(pos, faces)
    return torch.linalg.cross(p1 - p0, p2 - p0, dim=-1)


def _unit(v: Tensor) -> Tensor:
    return v / safe_norm(v, keepdim=True)


def face_normals(pos: Tensor, faces: Tensor) -> Tensor:
    """Unit face normals ``n_f = c_f / |c_f|`` with ``c_f = (p1 - p0) x (p2 - p0)``.

    Args:
        pos: ``[..., V, 3]`` vertex positions.
        faces: ``[F, 3]`` long.

    Returns:
        ``[..., F, 3]``; zero for zero-area faces.
    """
    pos, faces = check_mesh(pos, faces)
    return _unit(face_cross(pos, faces))


def face_areas(pos: Tensor, faces: Tensor) -> Tensor:
    """Triangle areas ``A_f = |(p1 - p0) x (p2 - p0)| / 2``, ``[..., F]``."""
    pos, faces = check_mesh(pos, faces)
    return 0.5 * safe_norm(face_cross(pos, faces))


def face_angles(pos: Tensor, faces: Tensor) -> Tensor:
    """Interior corner angles ``[..., F, 3]``; column ``k`` is the angle at ``faces[:, k]``.

    ``theta_k = atan2(|e1 x e2|, e1 . e2)`` with ``e1, e2`` the two edges leaving the
    corner (robust for nearly flat angles, unlike ``acos``).
    """
    pos, faces = check_mesh(pos, faces)
    return face_angles_unchecked(pos, faces)


def face_angles_unchecked(pos: Tensor, faces: Tensor) -> Tensor:
    """:func:`face_angles` without validation, for callers that have checked the mesh."""
    p = face_vertices(pos, faces)
    out = []
    for k in range(3):
        e1 = p[(k + 1) % 3] - p[k]
        e2 = p[(k + 2) % 3] - p[k]
        out.append(torch.atan2(safe_norm(torch.linalg.cross(e1, e2, dim=-1)),
                               (e1 * e2).sum(-1)))
    return torch.stack(out, -1)


def scatter_faces_to_vertices(values: Tensor, faces: Tensor, num_vertices: int) -> Tensor:
    """Sum per-corner values ``[..., F, 3, C]`` onto the vertices: ``[..., V, C]``.

    ``out[..., v, :] = sum over (f, k) with faces[f, k] == v of values[..., f, k, :]``
    (for per-corner scalars pass ``values.unsqueeze(-1)``).
    """
    if values.dim() < 3 or values.shape[-3:-1] != (faces.size(0), 3):
        raise ValueError(f"`values`: expected shape [..., {faces.size(0)}, 3, C] (one "
                         f"entry per face corner), got {tuple(values.shape)}")
    return scatter_rows(values, faces, num_vertices)


def vertex_normals(pos: Tensor, faces: Tensor, weighting: str = "area") -> Tensor:
    """Unit vertex normals ``n_v = s_v / |s_v|`` from the incident faces.

    * ``weighting="area"`` (default): ``s_v = sum_{f ni v} c_f`` with ``c_f`` the
      un-normalised face normal, i.e. face normals weighted by twice the face area.
    * ``weighting="angle"``: ``s_v = sum_{f ni v} theta_{f,v} n_f`` (corner-angle
      weights, Thuermer & Wuethrich 1998; this is trimesh's ``vertex_normals`` and the
      vertex pseudo-normal of Baerentzen & Aanaes 2005 used for inside/outside tests).

    Isolated vertices (and vertices whose incident normals cancel) get a zero vector.

    Returns:
        ``[..., V, 3]``.
    """
    pos, faces = check_mesh(pos, faces)
    if weighting == "area":
        c = face_cross(pos, faces)
    elif weighting == "angle":
        c = _unit(face_cross(pos, faces))
        c = c.unsqueeze(-2) * face_angles_unchecked(pos, faces).unsqueeze(-1)  # [..., F, 3, 3]
        return _unit(scatter_faces_to_vertices(c, faces, pos.size(-2)))
    else:
        raise ValueError(f"`weighting`: expected 'area' or 'angle', got {weighting!r}")
    c = c.unsqueeze(-2).expand(*c.shape[:-1], 3, 3)
    return _unit(scatter_faces_to_vertices(c, faces, pos.size(-2)))
