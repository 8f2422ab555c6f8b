"""Per-face deformation gradient with respect to the garment's UV (sewing-pattern) space.

GarTrans Eq. 14: for face ``(i, j, k)``::

    (W^u  W^v) = (dp1  dp2) @ | du1  du2 |^-1 ,   dp1 = p_j - p_i, dp2 = p_k - p_i,
                              | dv1  dv2 |        du1 = u_j - u_i, ...

``W^u`` / ``W^v`` are the world-space images of the unit u / v directions; their norms
are the stretch ratios of Eq. 12 and their dot product the shear of Eq. 13, each
weighted by the face's rest UV area ``a_i``.  (HOOD's StVK uses the same quantity:
``F = Ds Dm^-1``.)
"""
from __future__ import annotations

from typing import NamedTuple, Optional

import torch
from torch import Tensor

from ._index import gather_rows
from ._validate import check_faces, check_mesh, check_points

__all__ = ["flat_triangles", "UVFrame", "DeformationGradient", "uv_rest_frame",
           "uv_deformation_gradient", "deformation_gradient"]


class UVFrame(NamedTuple):
    """Rest-state quantities of the UV parametrisation, per face.

    Attributes:
        inverse: ``[..., F, 2, 2]``, ``Dm^-1 = [[du1, du2], [dv1, dv2]]^-1``; zeros
            where ``valid`` is False.
        area: ``[..., F]``, unsigned UV triangle area ``|det Dm| / 2``.
        valid: ``[..., F]`` bool, False for (numerically) zero-area UV triangles.
    """
    inverse: Tensor
    area: Tensor
    valid: Tensor


class DeformationGradient(NamedTuple):
    """Result of :func:`uv_deformation_gradient`.

    Attributes:
        grad: ``[..., F, 3, 2]``, columns ``W^u`` and ``W^v`` (Eq. 14); zeros for
            invalid faces.
        uv_area: ``[..., F]``, rest UV area per face (the ``a_i`` of Eqs. 12-13).
        valid: ``[..., F]`` bool, False for zero-area UV triangles.
    """
    grad: Tensor
    uv_area: Tensor
    valid: Tensor


def uv_rest_frame(uv: Tensor, faces: Tensor, eps: float = 1e-10) -> UVFrame:
    """Invert the per-face UV edge matrix ``Dm = [[du1, du2], [dv1, dv2]]``.

    A face is *valid* when ``|det Dm| > eps * (du1^2 + du2^2 + dv1^2 + dv2^2)``, a
    scale-free test (it bounds ``sin`` of the UV corner angle from below, roughly).
    Invalid faces get ``inverse = 0`` and ``area = |det| / 2`` (~0) and contribute
    nothing; gradients through them are zero, never NaN.

    Args:
        uv: ``[..., Vuv, 2]`` UV coordinates.
        faces: ``[F, 3]`` long indices into ``uv``.
        eps: relative degeneracy threshold (see above).
    """
    uv = check_points(uv, "uv", dim=2)
    faces = check_faces(faces, uv.size(-2), "faces")
    u0, u1, u2 = gather_rows(uv, faces).unbind(-2)
    d1, d2 = u1 - u0, u2 - u0  # [..., F, 2] = (du, dv) of each edge
    a, b, c, d = d1[..., 0], d2[..., 0], d1[..., 1], d2[..., 1]  # Dm = [[a, b], [c, d]]
    det = a * d - b * c
    scale = a * a + b * b + c * c + d * d
    valid = det.abs() > eps * scale
    safe = torch.where(valid, det, torch.ones_like(det))
    inv = torch.stack([d, -b, -c, a], -1) / safe.unsqueeze(-1)
    inv = torch.where(valid.unsqueeze(-1), inv, torch.zeros_like(inv))
    return UVFrame(inv.reshape(*inv.shape[:-1], 2, 2), 0.5 * det.abs(), valid)


def deformation_gradient(pos: Tensor, faces: Tensor, inverse: Tensor) -> Tensor:
    """``F = (dp1 dp2) @ Dm^-1`` (Eq. 14) from a precomputed :class:`UVFrame` ``inverse``.

    Args:
        pos: ``[..., V, 3]`` world positions.
        faces: ``[F, 3]`` long.
        inverse: ``[..., F, 2, 2]`` (broadcast against the batch of ``pos``).

    Returns:
        ``[..., F, 3, 2]``.
    """
    pos, faces = check_mesh(pos, faces)
    if inverse.shape[-3:] != (faces.size(0), 2, 2):
        raise ValueError(f"`inverse`: expected shape [..., {faces.size(0)}, 2, 2] (from "
                         f"uv_rest_frame), got {tuple(inverse.shape)}")
    p0, p1, p2 = gather_rows(pos, faces).unbind(-2)
    ds = torch.stack([p1 - p0, p2 - p0], -1)  # [..., F, 3, 2]
    return ds @ inverse.to(ds.dtype)


def uv_deformation_gradient(pos: Tensor, faces: Tensor, uv: Tensor,
                            uv_faces: Optional[Tensor] = None,
                            eps: float = 1e-10) -> DeformationGradient:
    """Per-face deformation gradient of world positions w.r.t. UV coordinates (Eq. 14).

    ``(W^u W^v) = (dp1 dp2) (Dm)^-1`` with ``Dm = [[du1, du2], [dv1, dv2]]``.  If the
    mesh maps the rest triangle by an affine map ``p = M (u, v)^T + t``, the result is
    exactly ``M`` (``[3, 2]``).

    Zero-area UV triangles (``|det Dm| <= eps * |Dm|_F^2``) are masked: their gradient
    is zero and ``valid`` is False (no NaN/inf in values or gradients).

    Args:
        pos: ``[..., V, 3]``.
        faces: ``[F, 3]`` long, indices into ``pos``.
        uv: ``[..., Vuv, 2]`` UV coordinates (broadcast against the batch of ``pos``).
        uv_faces: ``[F, 3]`` indices into ``uv`` when the UV layout has its own
            vertices (seams, OBJ ``vt``); defaults to ``faces``.
        eps: relative degeneracy threshold of :func:`uv_rest_frame`.
    """
    pos, faces = check_mesh(pos, faces)
    uvf = faces if uv_faces is None else uv_faces
    uv = check_points(uv, "uv", dim=2)
    if uv_faces is not None:
        uvf = check_faces(uv_faces, uv.size(-2), "uv_faces")
        if uvf.size(0) != faces.size(0):
            raise ValueError(f"`uv_faces`: must have one row per face ({faces.size(0)}), "
                             f"got {uvf.size(0)}")
    elif uv.size(-2) != pos.size(-2):
        raise ValueError(f"`uv`: has {uv.size(-2)} vertices but `pos` has {pos.size(-2)}; "
                         f"pass `uv_faces` when the UV layout has its own vertices")
    frame = uv_rest_frame(uv, uvf, eps)
    grad = deformation_gradient(pos, faces, frame.inverse)
    valid = frame.valid
    return DeformationGradient(grad, frame.area.to(grad.dtype), valid)


def flat_triangles(tri: Tensor) -> Tensor:
    """Isometric 2D copies ``[..., F, 3, 2]`` of 3D triangles ``[..., F, 3, 3]``: corner 0
    at the origin, corner 1 on +u, corner 2 above (counter-clockwise w.r.t. the face
    normal).  Used as stress-free material coordinates when a mesh has no pattern."""
    e1 = tri[..., 1, :] - tri[..., 0, :]
    e2 = tri[..., 2, :] - tri[..., 0, :]
    l1 = (e1 * e1).sum(-1).sqrt().clamp_min(torch.finfo(tri.dtype).tiny)
    x2 = (e1 * e2).sum(-1) / l1
    cr = torch.linalg.cross(e1, e2, dim=-1)
    y2 = (cr * cr).sum(-1).clamp_min(0.0).sqrt() / l1
    zero = torch.zeros_like(l1)
    return torch.stack([torch.stack([zero, zero], -1), torch.stack([l1, zero], -1),
                        torch.stack([x2, y2], -1)], -2)
