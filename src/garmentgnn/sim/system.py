"""The cloth system of the implicit simulator: rest state, masses, the incremental
potential (energies of :mod:`garmentgnn.physics`), contact linearisation and the
PSD-projected sparse Hessian."""
from __future__ import annotations

from typing import Callable, NamedTuple, Optional, Sequence, Tuple

import numpy as np
import scipy.sparse as sp
import torch
from torch import Tensor

from garmentgnn.geometry import (closest_point_on_triangle, dihedral_angles, signed_distance,
                                 unique_edges)
from garmentgnn.geometry.mesh import FaceAdjacency
from garmentgnn.physics import (ClothRest, Material, bending_energy, collision_energy,
                                gravity_energy, inertia_energy, shear_energy, stretch_energy,
                                friction_energy, friction_hessian, stvk_energy)
from garmentgnn.sim.colliders import Collider
from garmentgnn.sim.settings import DTYPE, SimSettings


class Contact(NamedTuple):
    """Linearised contacts from :meth:`ClothSystem.contact_planes` (``C`` contacts).

    Attributes:
        idx: ``[C]`` cloth vertex of each contact.
        closest: ``[C, 3]`` closest collider point ``q``.
        normal: ``[C, 3]`` unit gradient ``n`` of the signed distance (``s ~ (p - q) . n``).
        distance: ``[V]`` true signed distance of every vertex (min over the colliders).
        force: ``[C]`` lagged normal force (the penalty force at the linearisation point).
        motion: ``[C, 3]`` the collider's displacement under the contact over the step.
    """
    idx: Tensor
    closest: Tensor
    normal: Tensor
    distance: Tensor
    force: Tensor
    motion: Tensor


def check_colliders(colliders) -> Tuple[Collider, ...]:
    """``colliders`` as a tuple of :class:`~garmentgnn.sim.colliders.Collider`
    (``TypeError`` otherwise); a single collider is accepted."""
    if isinstance(colliders, Collider):
        colliders = (colliders,)
    if colliders is None:
        return ()
    if not isinstance(colliders, (tuple, list)) or not all(isinstance(c, Collider)
                                                           for c in colliders):
        raise TypeError(f"`colliders`: expected Sphere/Plane colliders (garmentgnn.sim.colliders)"
                        f", got {colliders!r}")
    return tuple(colliders)


def _local_rest(faces: Tensor, **kw) -> ClothRest:
    dummy = torch.zeros(1, dtype=DTYPE)
    base = dict(faces=faces, uv_inverse=torch.zeros(1, 1, 2, 2, dtype=DTYPE), uv_area=dummy,
                valid=torch.ones(1, dtype=torch.bool),
                adjacency=FaceAdjacency(torch.zeros(0, 2, dtype=torch.long),
                                        torch.zeros(0, 2, dtype=torch.long),
                                        torch.zeros(0, 2, dtype=torch.long)),
                rest_angle=dummy, hinge_length=dummy, hinge_area=dummy)
    base.update(kw)
    return ClothRest(**base)


def _element_hessians(fn: Callable[[Tensor], Tensor], X: Tensor) -> Tensor:
    """Block-diagonal Hessians ``[N, 3k, 3k]`` of ``fn(X).sum()`` for ``X [N, k, 3]``
    whose elements are independent (``fn`` returns one energy per element)."""
    X = X.detach().requires_grad_(True)
    N, k, _ = X.shape
    n = 3 * k
    with torch.enable_grad():
        g = torch.autograd.grad(fn(X).sum(), X, create_graph=True)[0].reshape(N, n)
        try:  # all rows in one vmapped backward pass
            eye = torch.eye(n, dtype=X.dtype).unsqueeze(1).expand(n, N, n)
            H = torch.autograd.grad(g, X, grad_outputs=eye, is_grads_batched=True,
                                    retain_graph=True)[0].reshape(n, N, n).transpose(0, 1)
        except RuntimeError:  # an op without a batching rule: one pass per row
            rows = [torch.autograd.grad(g[:, j].sum(), X, retain_graph=True,
                                        allow_unused=True)[0] for j in range(n)]
            rows = [torch.zeros_like(X) if r is None else r for r in rows]
            H = torch.stack([r.reshape(N, n) for r in rows], 1)
    return 0.5 * (H + H.transpose(1, 2))


def _baraff_witkin_hessians(X: Tensor, inverse: Tensor, area: Tensor, k_stretch: float,
                            k_shear: float, project: bool = True) -> Tensor:
    """Closed-form ``[F, 9, 9]`` Hessians of Eqs. 12-13 (stretch + shear) per face.

    With ``W = (x1 - x0, x2 - x0) Dm^-1 = sum_i x_i b_i^T`` (Eq. 14, ``b_i`` the rows
    of ``B = [[-1, -1], [1, 0], [0, 1]] Dm^-1``) the energy is a function of the six
    numbers ``w = (W^u, W^v)``, whose Hessian is

    * stretch, per column ``c``: ``2 k_s a (n n^T + (1 - 1/|W^c|) (I - n n^T))``,
      ``n = W^c / |W^c|``;
    * shear, ``s = W^u . W^v``, ``g = (W^v, W^u)``: ``2 k_h a (g g^T + s [[0, I], [I, 0]])``.

    ``project=True`` makes every block PSD the cheap way: the transverse stretch
    coefficient ``1 - 1/|W^c|`` is clamped at 0 (compressed faces -- exactly the
    eigenvalue clamp of that block) and the indefinite ``s`` term of the shear is
    dropped (Gauss-Newton).  ``project=False`` gives the exact Hessian (tested
    against autograd of :func:`garmentgnn.physics.stretch_energy` / ``shear_energy``).
    Then ``H_x[i, j] = sum_{c, d} B[i, c] B[j, d] H_w[c, d]``.
    """
    B = torch.tensor([[-1.0, -1.0], [1.0, 0.0], [0.0, 1.0]], dtype=X.dtype) @ inverse  # [F,3,2]
    W = torch.einsum("fic,fia->fac", B, X)  # [F, 3, 2]: columns W^u, W^v
    eye = torch.eye(3, dtype=X.dtype)
    norm = W.norm(dim=1).clamp_min(1e-12)  # [F, 2]
    n = W / norm.unsqueeze(1)
    coef = 1.0 - 1.0 / norm
    if project:
        coef = coef.clamp_min(0.0)
    ks, kh = 2.0 * k_stretch * area, 2.0 * k_shear * area  # [F]
    Hw = X.new_zeros(X.shape[0], 2, 3, 2, 3)
    for c in range(2):
        nn = n[:, :, c, None] * n[:, None, :, c]
        Hw[:, c, :, c, :] = ks.view(-1, 1, 1) * (nn + coef[:, c].view(-1, 1, 1) * (eye - nn))
    g = torch.stack([W[..., 1], W[..., 0]], 1)  # [F, 2, 3]
    Hw = Hw + kh.view(-1, 1, 1, 1, 1) * g[:, :, :, None, None] * g[:, None, None, :, :]
    if not project:
        s_ = (W[..., 0] * W[..., 1]).sum(-1)
        off = (kh * s_).view(-1, 1, 1) * eye
        Hw[:, 0, :, 1, :] += off
        Hw[:, 1, :, 0, :] += off
    return torch.einsum("fic,fjd,fcadb->fiajb", B, B, Hw).reshape(-1, 9, 9)


def _project_psd(H: Tensor) -> Tensor:
    if H.shape[0] == 0:
        return H
    w, Q = torch.linalg.eigh(H)
    return (Q * w.clamp_min(0.0).unsqueeze(-2)) @ Q.transpose(-1, -2)


class ClothSystem:
    """Rest state, masses and solver helpers of one cloth mesh (float64 internally).

    Args:
        rest_pos: ``[V, 3]`` rest positions.
        faces: ``[F, 3]``.
        material: the fabric.
        face_uv: ``[F, 3, 2]`` material coordinates (metres), see :class:`ClothRest`.
        pinned: ``[V]`` bool mask of vertices driven kinematically.
        body_faces: ``[Fb, 3]`` body triangles (``None``: no body).
        settings: :class:`SimSettings`.
        colliders: rigid colliders (:mod:`garmentgnn.sim.colliders`), besides or instead
            of the body.
    """

    def __init__(self, rest_pos: Tensor, faces: Tensor, material: Material,
                 face_uv: Optional[Tensor] = None, pinned: Optional[Tensor] = None,
                 body_faces: Optional[Tensor] = None, settings: Optional[SimSettings] = None,
                 colliders: Sequence[Collider] = ()):
        self.settings = settings or SimSettings()
        self.colliders = check_colliders(colliders)
        self.material = material
        rest_pos = rest_pos.detach().to(DTYPE)
        self.V = rest_pos.shape[0]
        self.faces = faces.long()
        self.rest = ClothRest.from_mesh(rest_pos, self.faces,
                                        None if face_uv is None else face_uv.to(DTYPE),
                                        flat_rest=self.settings.flat_rest)
        mass = self.rest.vertex_masses(material.density, self.V).to(DTYPE)
        if (mass <= 0).any():  # isolated / zero-area vertices: give them a tiny mass
            pos_m = mass[mass > 0]
            mass = mass.clamp_min(1e-3 * (float(pos_m.min()) if pos_m.numel() else 1e-6))
        self.mass = mass
        self.pinned = (torch.zeros(self.V, dtype=torch.bool) if pinned is None
                       else pinned.to(torch.bool).clone())
        self.free = ~self.pinned
        self.free_dofs = torch.nonzero(self.free.repeat_interleave(3)).squeeze(1).numpy()
        self.body_faces = None if body_faces is None else body_faces.long()
        self.body_edges = (None if body_faces is None
                           else unique_edges(self.body_faces, int(self.body_faces.max()) + 1))
        self._build_local()

    # -- per-element rests, used for the Hessian blocks ------------------------
    def _build_local(self) -> None:
        r = self.rest
        self.face_rest = _local_rest(torch.tensor([[0, 1, 2]]),
                                     uv_inverse=r.uv_inverse.to(DTYPE).unsqueeze(1),
                                     uv_area=r.uv_area.to(DTYPE).unsqueeze(1))
        adj = r.adjacency
        a, b = adj.edges[:, 0], adj.edges[:, 1]
        o1, o2 = adj.opposite[:, 0], adj.opposite[:, 1]
        self.hinge_verts = torch.stack([a, b, o1, o2], 1)  # [A, 4]
        # face 1 traverses a -> b, so it is (a, b, o1) up to a cyclic shift; face 2 is
        # (b, a, o2) when consistently oriented, (a, b, o2) otherwise.
        f2 = self.faces[adj.faces[:, 1]]
        f2_ab = ((f2 == a.unsqueeze(1)) & (f2.roll(-1, 1) == b.unsqueeze(1))).any(1)
        self.hinge_groups = []
        for same, local_f2 in ((False, [1, 0, 3]), (True, [0, 1, 3])):
            idx = torch.nonzero(f2_ab == same).squeeze(1)
            if idx.numel() == 0:
                continue
            lr = _local_rest(torch.tensor([[0, 1, 2], local_f2]),
                             adjacency=FaceAdjacency(torch.tensor([[0, 1]]), torch.tensor([[0, 1]]),
                                                     torch.tensor([[2, 3]])),
                             rest_angle=r.rest_angle.to(DTYPE)[idx].unsqueeze(1),
                             hinge_length=r.hinge_length.to(DTYPE)[idx].unsqueeze(1),
                             hinge_area=r.hinge_area.to(DTYPE)[idx].unsqueeze(1))
            self.hinge_groups.append((idx, lr))

    # -- energies ----------------------------------------------------------------
    def membrane(self, pos: Tensor, rest: ClothRest) -> Tensor:
        m = self.material
        if self.settings.membrane == "stvk":
            return stvk_energy(pos, rest, m.lame_mu, m.lame_lambda)
        return stretch_energy(pos, rest, m.stretch) + shear_energy(pos, rest, m.shear)

    def bending(self, pos: Tensor, rest: ClothRest) -> Tensor:
        if self.material.bending == 0 or rest.adjacency.faces.shape[0] == 0:
            return pos.new_zeros(pos.shape[:-2])
        return bending_energy(pos, rest, self.material.bending)

    def internal_energy(self, x: Tensor) -> Tensor:
        """Membrane + bending + gravity (no inertia, no collision)."""
        return (self.membrane(x, self.rest) + self.bending(x, self.rest)
                + gravity_energy(x, self.mass, self.settings.gravity))

    def contact_planes(self, x: Tensor, body_pos: Optional[Tensor] = None,
                       radius: Optional[float] = None, frame: float = 0.0,
                       body_prev: Optional[Tensor] = None,
                       frame_prev: Optional[float] = None) -> Contact:
        """Linearised contacts for the vertices of ``x`` within ``margin + radius``
        (default ``settings.contact_radius``) of the body (``body_pos``, when given) and
        of every rigid collider (at fractional motion frame ``frame``), as a
        :class:`Contact`: ``s(p) ~ (p - q) . n`` near ``x`` for each contact.  A vertex
        near several colliders has one contact per collider.

        The lagged normal force of each contact is the penalty force at ``x``,
        ``k q max(eps - s, 0)^(q - 1)``; the collider motion under the contact runs from
        ``body_prev`` / ``frame_prev`` to ``body_pos`` / ``frame`` (zero when not given).
        """
        radius = self.settings.contact_radius if radius is None else radius
        reach = self.material.collision_margin + radius
        parts = []
        if body_pos is not None:
            with torch.no_grad():
                sd = signed_distance(x, body_pos, self.body_faces,
                                     candidates=self.settings.distance_candidates,
                                     body_edges=self.body_edges)
            idx = torch.nonzero(sd.distance < reach).squeeze(1)
            diff = x[idx] - sd.closest[idx]
            dist = diff.norm(dim=-1, keepdim=True)
            pseudo = sd.normal[idx]
            sign = torch.where(sd.distance[idx] < 0, -1.0, 1.0).to(x.dtype).unsqueeze(-1)
            n = torch.where(dist > 1e-9, sign * diff / dist.clamp_min(1e-30), pseudo)
            q = x[idx] - sd.distance[idx].unsqueeze(-1) * n
            if body_prev is None:
                motion = torch.zeros_like(q)
            else:  # the body point under the contact: same barycentrics, previous pose
                tri = self.body_faces[sd.face[idx]]
                _, bary, _ = closest_point_on_triangle(
                    sd.closest[idx], body_pos[tri[:, 0]], body_pos[tri[:, 1]],
                    body_pos[tri[:, 2]])
                motion = (bary.unsqueeze(-1) * (body_pos[tri] - body_prev.to(x.dtype)[tri])).sum(1)
            parts.append((idx, q, n, sd.distance, motion))
        for collider in self.colliders:
            with torch.no_grad():
                sd = collider.distance(x, frame)
            idx = torch.nonzero(sd.distance < reach).squeeze(1)
            motion = (torch.zeros(idx.shape[0], 3, dtype=x.dtype) if frame_prev is None
                      else collider.motion(sd.closest[idx], frame_prev, frame))
            parts.append((idx, sd.closest[idx], sd.normal[idx], sd.distance, motion))
        if not parts:
            raise ValueError("`body_pos`: no body and no colliders to build contacts with")
        idx = torch.cat([p[0] for p in parts])
        s_contact = torch.cat([p[3][p[0]] for p in parts])
        distance = torch.stack([p[3] for p in parts]).min(0).values
        st = self.settings
        force = st.collision_stiffness * st.collision_power * (
            self.material.collision_margin - s_contact).clamp_min(0.0) ** (st.collision_power - 1)
        return Contact(idx, torch.cat([p[1] for p in parts]), torch.cat([p[2] for p in parts]),
                       distance, force, torch.cat([p[4] for p in parts]))

    def friction(self, x: Tensor, x_start: Tensor, contact: Contact, h: float) -> Tensor:
        """Lagged friction potential (:func:`garmentgnn.physics.friction_energy`) of the
        contacts over a step of ``h`` seconds from ``x_start``."""
        idx = contact.idx
        rel = x[idx] - x_start[idx] - contact.motion
        return friction_energy(rel, contact.normal, contact.force, self.material.friction,
                               self.settings.friction_velocity * h)

    def friction_blocks(self, x: Tensor, x_start: Tensor, contact: Contact, h: float
                        ) -> Tuple[Tensor, Tensor]:
        """``(verts [C], [C, 3, 3] PSD Hessian blocks)`` of :meth:`friction`."""
        idx = contact.idx
        rel = x[idx] - x_start[idx] - contact.motion
        return idx, friction_hessian(rel, contact.normal, contact.force, self.material.friction,
                                     self.settings.friction_velocity * h)

    def has_friction(self, contact: Optional[Contact]) -> bool:
        """Whether friction acts: ``settings.friction``, ``mu > 0`` and some contact
        carries a normal force."""
        return (self.settings.friction and self.material.friction > 0 and contact is not None
                and contact.idx.numel() > 0 and bool((contact.force > 0).any()))

    def energy(self, x: Tensor, x_tilde: Tensor, h: float, body_pos: Optional[Tensor],
               contact: Optional[Contact], x_start: Optional[Tensor] = None
               ) -> Tuple[Tensor, Optional[Tensor]]:
        """Incremental potential; returns ``(E, s)`` with ``s`` the (linearised) signed
        distances of the contact vertices.  With ``x_start`` (the positions at the start
        of the step) and ``mu > 0`` it includes the lagged friction potential.
        ``body_pos`` is not used (the contacts carry the linearised collider)."""
        E = inertia_energy(x, x_tilde, self.mass, h) + self.internal_energy(x)
        s = None
        if contact is not None and contact[0].numel():
            idx, q, n = contact[:3]
            p = x[idx]
            s = ((p - q) * n).sum(-1)
            E = E + collision_energy(p, body_pos, self.body_faces, self.material.collision_margin,
                                     self.settings.collision_stiffness,
                                     power=self.settings.collision_power, distance=s)
            if x_start is not None and self.has_friction(contact):
                E = E + self.friction(x, x_start, contact, h)
        return E, s

    def hessian(self, x: Tensor, h: float, pen_grad: Optional[Tuple[Tensor, Tensor, Tensor]],
                friction: Optional[Tuple[Tensor, Tensor]] = None) -> sp.csr_matrix:
        """PSD-projected sparse Hessian of the incremental potential, ``[3V, 3V]``;
        ``friction``: ``(verts, blocks)`` of :meth:`friction_blocks`."""
        x = x.detach()
        rows, cols, vals = [], [], []

        def add(blocks: Tensor, verts: Tensor) -> None:
            N, k = verts.shape
            dof = (verts.unsqueeze(-1) * 3 + torch.arange(3)).reshape(N, 3 * k)
            rows.append(dof.unsqueeze(2).expand(N, 3 * k, 3 * k).reshape(-1).numpy())
            cols.append(dof.unsqueeze(1).expand(N, 3 * k, 3 * k).reshape(-1).numpy())
            vals.append(blocks.detach().reshape(-1).numpy())

        m, fr = self.material, self.face_rest
        fast = self.settings.hessian == "analytic"
        if fast and self.settings.membrane == "baraff_witkin":
            Hf = _baraff_witkin_hessians(x[self.faces], fr.uv_inverse[:, 0], fr.uv_area[:, 0],
                                         m.stretch, m.shear)
        else:
            Hf = _project_psd(_element_hessians(self._membrane_per_element, x[self.faces]))
        add(Hf, self.faces)
        if m.bending > 0:
            for idx, lr in self.hinge_groups:
                verts = self.hinge_verts[idx]
                if fast:  # Gauss-Newton: k w grad(theta) grad(theta)^T, PSD by construction
                    X = x[verts].requires_grad_(True)
                    with torch.enable_grad():
                        dtheta = torch.autograd.grad(
                            dihedral_angles(X, lr.faces, lr.adjacency).sum(), X)[0]
                    w = m.bending * lr.hinge_length[:, 0] ** 2 / (4.0 * lr.hinge_area[:, 0])
                    dtheta = dtheta.reshape(-1, 12)
                    Hb = w.view(-1, 1, 1) * dtheta.unsqueeze(2) * dtheta.unsqueeze(1)
                else:
                    Hb = _project_psd(_element_hessians(
                        lambda X, lr=lr: bending_energy(X, lr, m.bending, reduce="none").sum(-1),
                        x[verts]))
                add(Hb, verts)
        diag = (self.mass / (h * h)).repeat_interleave(3)
        n = 3 * self.V
        ar = np.arange(n)
        rows.append(ar)
        cols.append(ar)
        vals.append(diag.numpy())
        if pen_grad is not None:
            verts, coef, normal = pen_grad
            blocks = coef.view(-1, 1, 1) * normal.unsqueeze(-1) * normal.unsqueeze(-2)
            add(blocks, verts.unsqueeze(1))
        if friction is not None:
            add(friction[1], friction[0].unsqueeze(1))
        H = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(n, n)).tocsr()
        return H

    def _membrane_per_element(self, X: Tensor) -> Tensor:
        m, fr = self.material, self.face_rest
        if self.settings.membrane == "stvk":
            e = stvk_energy(X, fr, m.lame_mu, m.lame_lambda, reduce="none")
        else:
            e = (stretch_energy(X, fr, m.stretch, reduce="none")
                 + shear_energy(X, fr, m.shear, reduce="none"))
        return e.sum(-1)


