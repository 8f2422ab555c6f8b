"""Cloth energy terms: the one definition used by the simulator and the training losses.

Every term takes positions ``pos [..., V, 3]`` (any leading batch dims, e.g.
frames) and returns the energy per batch element ``[...]`` in joules, or per
element with ``reduce="none"``.  All are differentiable in ``pos``.

=================  =======================================================  ===========
term               formula                                                  source
=================  =======================================================  ===========
stretch            ``k_s sum_f a_f ((|W^u_f| - 1)^2 + (|W^v_f| - 1)^2)``    Eq. 12
shear              ``k_h sum_f a_f (W^u_f . W^v_f)^2``                      Eq. 13
StVK membrane      ``sum_f a_f (mu tr(G^2) + lambda/2 tr(G)^2)``,           HOOD
                   ``G = (F^T F - I) / 2``, ``F = (W^u W^v)``
bending            ``k_b sum_e l_e^2 / (4 A_e) (theta_e - theta0_e)^2 / 2``  HOOD
gravity            ``-sum_i m_i p_i . g``                                    Eq. 11
inertia            ``sum_i m_i |p_i - p~_i|^2 / (2 dt^2)``                   HOOD
collision          ``k sum_i max(eps - s(p_i), 0)^q``; q = 1 is Eq. 10,      Eq. 10 /
                   q = 3 HOOD's smooth penalty                               HOOD
=================  =======================================================  ===========

``(W^u W^v)`` is the per-face deformation gradient of Eq. 14
(:func:`garmentgnn.geometry.deformation_gradient`), ``a_f`` the rest (UV) area,
``s(p)`` the signed distance to the body (:func:`garmentgnn.geometry.signed_distance`).
Note the paper's weights ``k_s, k_h, k_c, k_g`` are *loss* weights; here the
stiffnesses come from a :class:`~garmentgnn.physics.Material` in SI units, and the
losses multiply the energies by their weights.
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Optional, Sequence

import torch
from torch import Tensor
from torch_geometric.utils import scatter

from garmentgnn.geometry import (FaceAdjacency, deformation_gradient, dihedral_angles,
                                 face_adjacency, flat_triangles, signed_distance,
                                 uv_rest_frame)

GRAVITY = (0.0, 0.0, -9.81)


def _reduce(per_element: Tensor, reduce: str) -> Tensor:
    if reduce == "sum":
        return per_element.sum(-1)
    if reduce == "none":
        return per_element
    raise ValueError(f"`reduce`: expected 'sum' or 'none', got {reduce!r}")


def _safe_norm(v: Tensor) -> Tensor:
    return (v * v).sum(-1).clamp_min(1e-20).sqrt()


def _move(v, device, non_blocking: bool):
    """``v`` (a tensor, or a named tuple of them: FaceAdjacency) on ``device``."""
    if isinstance(v, Tensor):
        return v.to(device, non_blocking=non_blocking)
    return type(v)(*(_move(t, device, non_blocking) for t in v))


@dataclass
class ClothRest:
    """Rest-state quantities of a cloth mesh, computed once per garment.

    Attributes:
        faces: ``[F, 3]``.
        uv_inverse: ``[F, 2, 2]`` inverse UV edge matrices (Eq. 14), 0 for zero-area UV faces.
        uv_area: ``[F]`` rest UV areas ``a_f``.
        valid: ``[F]`` False for zero-area UV faces (they carry no membrane energy).
        adjacency: interior hinges.
        rest_angle: ``[A]`` rest dihedral angles ``theta0``.
        hinge_length: ``[A]`` rest hinge edge lengths ``l``.
        hinge_area: ``[A]`` summed rest areas of the two hinge faces ``A``.
    """

    faces: Tensor
    uv_inverse: Tensor
    uv_area: Tensor
    valid: Tensor
    adjacency: FaceAdjacency
    rest_angle: Tensor
    hinge_length: Tensor
    hinge_area: Tensor

    def to(self, device, non_blocking: bool = False) -> "ClothRest":
        """A copy with every tensor on ``device`` (this one is left where it is)."""
        return replace(self, **{f.name: _move(getattr(self, f.name), device, non_blocking)
                                for f in fields(self)})

    @classmethod
    def from_mesh(cls, rest_pos: Tensor, faces: Tensor, face_uv: Optional[Tensor] = None,
                  flat_rest: bool = False) -> "ClothRest":
        """Build from rest positions ``[V, 3]``, ``faces [F, 3]`` and per-corner material
        coordinates ``face_uv [F, 3, 2]`` (metres; default: each rest triangle laid
        flat with its first edge along u, so the rest shape is stress-free but the
        u/v directions -- which matter for the anisotropic Eqs. 12-13 -- vary from
        face to face; pass a real sewing pattern for warp/weft behaviour).
        ``flat_rest=True`` sets the rest dihedral angles to 0 (a garment sewn from flat
        panels) instead of the rest mesh's angles."""
        faces = faces.long()
        F = faces.size(0)
        if face_uv is None:
            face_uv = flat_triangles(rest_pos[faces])
        if face_uv.shape != (F, 3, 2):
            raise ValueError(f"`face_uv`: expected [{F}, 3, 2] per-corner coordinates, got "
                             f"{tuple(face_uv.shape)}")
        corner_faces = torch.arange(3 * F, device=faces.device).view(F, 3)
        frame = uv_rest_frame(face_uv.reshape(-1, 2).to(rest_pos.dtype), corner_faces)
        adj = face_adjacency(faces, rest_pos.size(0))
        theta0 = (torch.zeros(adj.faces.size(0), dtype=rest_pos.dtype, device=rest_pos.device)
                  if flat_rest
                  else dihedral_angles(rest_pos, faces, adj))
        e = rest_pos[adj.edges[:, 1]] - rest_pos[adj.edges[:, 0]]
        return cls(faces=faces, uv_inverse=frame.inverse, uv_area=frame.area, valid=frame.valid,
                   adjacency=adj, rest_angle=theta0, hinge_length=_safe_norm(e),
                   hinge_area=frame.area[adj.faces].sum(-1).clamp_min(1e-12))

    def vertex_masses(self, density: float, num_vertices: int) -> Tensor:
        """``m_i = density * sum of a third of the adjacent faces' rest areas`` (kg)."""
        third = (self.uv_area / 3.0).repeat_interleave(3)
        return density * scatter(third, self.faces.reshape(-1), dim=0, dim_size=num_vertices,
                                 reduce="sum")


def _grad(pos: Tensor, rest: ClothRest) -> Tensor:
    return deformation_gradient(pos, rest.faces, rest.uv_inverse.to(pos.dtype))


def stretch_energy(pos: Tensor, rest: ClothRest, stiffness: float, reduce: str = "sum") -> Tensor:
    """Eq. 12: ``k_s sum_f a_f ((|W^u| - 1)^2 + (|W^v| - 1)^2)``."""
    W = _grad(pos, rest)
    e = (_safe_norm(W[..., 0]) - 1.0) ** 2 + (_safe_norm(W[..., 1]) - 1.0) ** 2
    return _reduce(stiffness * rest.uv_area.to(pos.dtype) * e, reduce)


def shear_energy(pos: Tensor, rest: ClothRest, stiffness: float, reduce: str = "sum") -> Tensor:
    """Eq. 13: ``k_h sum_f a_f (W^u . W^v)^2``."""
    W = _grad(pos, rest)
    e = (W[..., 0] * W[..., 1]).sum(-1) ** 2
    return _reduce(stiffness * rest.uv_area.to(pos.dtype) * e, reduce)


def stvk_energy(pos: Tensor, rest: ClothRest, mu: float, lam: float,
                reduce: str = "sum") -> Tensor:
    """St. Venant-Kirchhoff membrane: ``a (mu tr(G^2) + lambda/2 tr(G)^2)``,
    ``G = (F^T F - I) / 2`` with ``F = (W^u W^v)`` (HOOD's stretching term)."""
    W = _grad(pos, rest)
    C = W.transpose(-1, -2) @ W
    G = 0.5 * (C - torch.eye(2, dtype=pos.dtype, device=pos.device))
    tr = G[..., 0, 0] + G[..., 1, 1]
    e = mu * (G * G).sum((-1, -2)) + 0.5 * lam * tr * tr
    return _reduce(rest.uv_area.to(pos.dtype) * e, reduce)


def bending_energy(pos: Tensor, rest: ClothRest, stiffness: float, reduce: str = "sum") -> Tensor:
    """Discrete-shell bending: ``k_b sum_e l_e^2 / (4 A_e) (theta_e - theta0_e)^2 / 2`` over
    interior edges (``l`` rest hinge length, ``A`` summed rest area of its two faces)."""
    theta = dihedral_angles(pos, rest.faces, rest.adjacency)
    w = rest.hinge_length.to(pos.dtype) ** 2 / (4.0 * rest.hinge_area.to(pos.dtype))
    return _reduce(stiffness * w * 0.5 * (theta - rest.rest_angle.to(pos.dtype)) ** 2, reduce)


def gravity_energy(pos: Tensor, mass: Tensor, gravity: Sequence[float] = GRAVITY,
                   reduce: str = "sum") -> Tensor:
    """Eq. 11: ``-sum_i m_i p_i . g``."""
    g = torch.as_tensor(gravity, dtype=pos.dtype, device=pos.device)
    return _reduce(-mass.to(pos.dtype) * (pos @ g), reduce)


def inertia_energy(pos: Tensor, predicted: Tensor, mass: Tensor, dt: float,
                   reduce: str = "sum") -> Tensor:
    """``sum_i m_i |p_i - p~_i|^2 / (2 dt^2)`` with ``p~ = p_prev + dt v_prev`` (the
    inertial prediction): the kinetic part of the incremental potential."""
    if not dt > 0:
        raise ValueError(f"`dt` must be positive, got {dt}")
    d = pos - predicted
    return _reduce(mass.to(pos.dtype) * (d * d).sum(-1) / (2.0 * dt * dt), reduce)


def collision_energy(pos: Tensor, body_pos: Tensor, body_faces: Tensor, margin: float,
                     stiffness: float, power: int = 1, reduce: str = "sum",
                     distance: Optional[Tensor] = None,
                     candidates: Optional[int] = None, compiled: bool = False) -> Tensor:
    """``k sum_i max(eps - s(p_i), 0)^q``: ``q = 1`` is the paper's Eq. 10,
    ``q = 3`` HOOD's smooth penalty (used by the simulator).  ``distance`` may pass a
    precomputed ``s(p)`` (it must have been computed from ``pos`` to carry gradients);
    ``candidates`` and ``compiled`` are passed to
    :func:`garmentgnn.geometry.signed_distance` (``candidates=None``: exact brute force
    over all body faces)."""
    if power not in (1, 2, 3):
        raise ValueError(f"`power` must be 1, 2 or 3, got {power}")
    s = (signed_distance(pos, body_pos, body_faces, candidates=candidates,
                         compiled=compiled).distance
         if distance is None else distance)
    pen = torch.relu(margin - s)
    return _reduce(stiffness * pen ** power, reduce)
