"""Reference implicit cloth simulator (incremental-potential Newton solver).

Every substep solves ``x_{n+1} = argmin_x E_inertia(x; x_n + h v_n) + E_membrane(x)
+ E_bending(x) + E_gravity(x) + E_collision(x, body(t_{n+1}))`` and sets
``v_{n+1} = (x_{n+1} - x_n) / h`` (backward Euler).  All energies are the ones of
:mod:`garmentgnn.physics`; this module only adds the solver: autograd gradients,
PSD-projected per-element Hessians assembled into a scipy sparse matrix, a direct
sparse solve and a backtracking line search on the true energy.  See
``docs/simulator.md``.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, List, Optional, Tuple

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch
from torch import Tensor

from garmentgnn.body.body import Body
from garmentgnn.body.lbs import forward_kinematics, linear_blend_skinning
from garmentgnn.garments.placement import check_placement
from garmentgnn.geometry import (dihedral_angles, penetration_depth, signed_distance,
                                 unique_edges)
from garmentgnn.geometry.mesh import FaceAdjacency
from garmentgnn.motion.sequence import match_joints
from garmentgnn.physics import (GRAVITY, ClothRest, Material, bending_energy, collision_energy,
                                gravity_energy, inertia_energy, shear_energy, stretch_energy,
                                stvk_energy)

DTYPE = torch.float64


@dataclass
class SimSettings:
    """Simulator settings.

    Attributes:
        fps: frame rate of the output; must equal the motion's fps.
        substeps: implicit steps per frame (``h = 1 / (fps * substeps)``).
        max_newton: Newton iterations per substep.
        tol: convergence threshold on the Newton step, ``max_i |dx_i| / h < tol`` (m/s,
            IPC's criterion): the velocity error the remaining correction would make.
            (A force residual such as ``h^2 |dE/dx_i| / m_i`` is no use for cloth: the
            membrane stiffness is ~10^3 times ``m / h^2``, so a 1 um position error
            already reads as millimetres.)
        membrane: ``"baraff_witkin"`` (stretch Eq. 12 + shear Eq. 13) or ``"stvk"``.
        hessian: ``"analytic"`` (closed-form projected Baraff-Witkin blocks and
            Gauss-Newton bending blocks; StVK falls back to autograd) or ``"autograd"``
            (per-element double backward + eigenvalue clamping, ~5x slower per iteration;
            the reference the analytic blocks are tested against).
        collision_stiffness: ``k`` of the cubic penalty ``k max(eps - s, 0)^3`` (J/m^3).
        collision_power: penalty exponent (3, HOOD's smooth penalty).
        preroll_frames: frames simulated (not recorded) before frame 0 while the body and
            the pinned vertices move from the rest pose into the motion's first pose
            (joint rotations and root translation scaled by a smoothstep from 0 to 1);
            without it the garment starts as its rest shape *skinned* to frame 0, which
            for a walking or kicking pose strains silk by up to +-10% and costs the first
            frames a violent, slowly converging relaxation.
        settle_frames: frames simulated with the body frozen at frame 0 before frame 0
            is recorded (after the pre-roll).
        max_refinements: times a failing frame is retried with twice the substeps.
        retry_unconverged: also retry frames whose Newton solves ran out of iterations
            (by default those are accepted -- they are finite and lowered the energy --
            and reported in ``SimResult.converged``).
        contact_radius: vertices farther than ``margin + contact_radius`` from the body at
            the start of a substep skip the (expensive) distance query during Newton;
            the result is checked against the whole garment afterwards.
        max_penetration: a substep that ends with a vertex deeper than this inside the
            body (after the contact planes were refreshed) fails, so the frame is retried
            with twice the substeps (m); at the last refinement the frame is kept and
            flagged unconverged (a pinch between body parts, not tunnelling).  Every
            recorded frame is also measured exactly at its end (all body faces, winding
            number inside test: :func:`garmentgnn.geometry.penetration_depth`); frames
            deeper than this are flagged in ``SimResult.penetrating`` and the message.
        distance_candidates: ``candidates`` of :func:`garmentgnn.geometry.signed_distance`
            (``None`` = exact brute force).
        gravity: gravity vector (Z up).
        flat_rest: rest dihedral angles 0 (sewn from flat panels) instead of the rest mesh's.
        line_search_steps: maximum step halvings.
    """

    fps: float = 30.0
    substeps: int = 4
    max_newton: int = 30
    tol: float = 1e-3
    membrane: str = "baraff_witkin"
    hessian: str = "analytic"
    collision_stiffness: float = 1e6
    collision_power: int = 3
    preroll_frames: int = 0
    settle_frames: int = 0
    max_refinements: int = 3
    retry_unconverged: bool = False
    contact_radius: float = 0.02
    max_penetration: float = 1e-2
    distance_candidates: Optional[int] = 8
    gravity: Tuple[float, float, float] = GRAVITY
    flat_rest: bool = False
    line_search_steps: int = 30

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first invalid setting (run at construction
        and again by :func:`simulate`, in case a field was changed since)."""
        def number(name: str, lo: float, strict: bool) -> None:
            v = getattr(self, name)
            ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) \
                and (v > lo if strict else v >= lo)
            if not ok:
                raise ValueError(f"`settings.{name}`: must be a finite number "
                                 f"{'>' if strict else '>='} {lo}, got {v!r}")

        if not (isinstance(self.fps, (int, float)) and math.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"`settings.fps`: must be a positive finite number, got {self.fps!r}")
        for name in ("substeps", "max_newton"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise ValueError(f"`settings.{name}`: must be a positive int, got {v!r}")
        if not (self.tol > 0):
            raise ValueError(f"`settings.tol`: must be positive, got {self.tol!r}")
        if self.hessian not in ("analytic", "autograd"):
            raise ValueError(f"`settings.hessian`: 'analytic' or 'autograd', got {self.hessian!r}")
        if self.membrane not in ("baraff_witkin", "stvk"):
            raise ValueError(f"`settings.membrane`: 'baraff_witkin' or 'stvk', got {self.membrane!r}")
        if not (self.collision_stiffness >= 0):
            raise ValueError("`settings.collision_stiffness`: must be non-negative")
        if self.collision_power not in (2, 3):
            raise ValueError("`settings.collision_power`: 2 or 3 (needs a second derivative)")
        for name in ("settle_frames", "preroll_frames", "max_refinements"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise ValueError(f"`settings.{name}`: must be a non-negative int, got {v!r}")
        if not isinstance(self.line_search_steps, int) or self.line_search_steps < 1:
            raise ValueError(f"`settings.line_search_steps`: must be a positive int, got "
                             f"{self.line_search_steps!r}")
        number("tol", 0.0, True)
        number("collision_stiffness", 0.0, False)
        number("contact_radius", 0.0, False)
        number("max_penetration", 0.0, True)
        dc = self.distance_candidates
        if dc is not None and (not isinstance(dc, int) or isinstance(dc, bool) or dc < 1):
            raise ValueError(f"`settings.distance_candidates`: a positive int or None (exact), "
                             f"got {dc!r}")
        g = self.gravity
        if not (isinstance(g, (tuple, list)) and len(g) == 3
                and all(isinstance(c, (int, float)) and math.isfinite(c) for c in g)):
            raise ValueError(f"`settings.gravity`: three finite numbers (m/s^2, Z up), "
                             f"got {g!r}")
        for name in ("retry_unconverged", "flat_rest"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"`settings.{name}`: must be True or False, got "
                                 f"{getattr(self, name)!r}")


@dataclass
class SimResult:
    """Output of :func:`simulate` (one entry per motion frame that was simulated)."""

    positions: Tensor  # [T, V, 3] float32
    converged: Tensor  # [T] bool
    newton_iterations: Tensor  # [T] int
    residual: Tensor  # [T] float
    ok: bool
    message: str
    seconds: float
    substeps: Tensor = field(default_factory=lambda: torch.zeros(0, dtype=torch.long))  # [T]
    #: [T] exact depth (m) of the deepest garment vertex inside the body at the end of
    #: each frame (:func:`garmentgnn.geometry.penetration_depth`; zeros without a body)
    penetration: Tensor = field(default_factory=lambda: torch.zeros(0))
    #: the ``max_penetration`` the frames were checked against
    max_penetration: float = math.inf

    @property
    def penetrating(self) -> Tensor:
        """``[T]`` bool: frames whose exact penetration exceeds ``max_penetration``."""
        return self.penetration > self.max_penetration


@dataclass
class StepResult:
    x: Tensor
    v: Tensor
    converged: bool
    iterations: int
    residual: float
    ok: bool
    message: str = ""


# ---------------------------------------------------------------------------
# the cloth system: energies, gradient, sparse Hessian
# ---------------------------------------------------------------------------
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
    """

    def __init__(self, rest_pos: Tensor, faces: Tensor, material: Material,
                 face_uv: Optional[Tensor] = None, pinned: Optional[Tensor] = None,
                 body_faces: Optional[Tensor] = None, settings: Optional[SimSettings] = None):
        self.settings = settings or SimSettings()
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

    def contact_planes(self, x: Tensor, body_pos: Tensor, radius: Optional[float] = None
                       ) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
        """Linearised contacts for the vertices of ``x`` within ``margin + radius``
        (default ``settings.contact_radius``) of the body: ``(idx [C], q [C, 3] closest
        body points, n [C, 3] unit gradients of the signed distance, s [V] the true
        signed distances of all vertices)``, so ``s(p) ~ (p - q) . n`` near ``x``."""
        radius = self.settings.contact_radius if radius is None else radius
        with torch.no_grad():
            sd = signed_distance(x, body_pos, self.body_faces,
                                 candidates=self.settings.distance_candidates,
                                 body_edges=self.body_edges)
        idx = torch.nonzero(sd.distance < self.material.collision_margin
                            + radius).squeeze(1)
        diff = x[idx] - sd.closest[idx]
        dist = diff.norm(dim=-1, keepdim=True)
        pseudo = sd.normal[idx]
        sign = torch.where(sd.distance[idx] < 0, -1.0, 1.0).to(x.dtype).unsqueeze(-1)
        n = torch.where(dist > 1e-9, sign * diff / dist.clamp_min(1e-30), pseudo)
        return idx, (x[idx] - sd.distance[idx].unsqueeze(-1) * n), n, sd.distance

    def energy(self, x: Tensor, x_tilde: Tensor, h: float, body_pos: Optional[Tensor],
               contact: Optional[Tuple[Tensor, Tensor, Tensor]]) -> Tuple[Tensor, Optional[Tensor]]:
        """Incremental potential; returns ``(E, s)`` with ``s`` the (linearised) signed
        distances of the contact vertices."""
        E = inertia_energy(x, x_tilde, self.mass, h) + self.internal_energy(x)
        s = None
        if body_pos is not None and contact is not None and contact[0].numel():
            idx, q, n = contact[:3]
            p = x[idx]
            s = ((p - q) * n).sum(-1)
            E = E + collision_energy(p, body_pos, self.body_faces, self.material.collision_margin,
                                     self.settings.collision_stiffness,
                                     power=self.settings.collision_power, distance=s)
        return E, s

    def hessian(self, x: Tensor, h: float, pen_grad: Optional[Tuple[Tensor, Tensor, Tensor]]
                ) -> sp.csr_matrix:
        """PSD-projected sparse Hessian of the incremental potential, ``[3V, 3V]``."""
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


# ---------------------------------------------------------------------------
# one implicit step
# ---------------------------------------------------------------------------
def _solve_spd(A: sp.csc_matrix, b: np.ndarray) -> np.ndarray:
    """Solve the (PSD-projected + mass, so SPD) Newton system.  SuperLU in symmetric
    mode with a minimum-degree ordering of ``A + A^T`` and no pivoting is ~2x faster
    than ``spsolve``'s defaults on cloth Hessians (measured at 280 and 424 vertices);
    fall back to the pivoting solver if that factorisation fails."""
    try:
        lu = spla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                       options=dict(SymmetricMode=True))
        d = lu.solve(b)
        if np.all(np.isfinite(d)):
            return d
    except RuntimeError:
        pass
    return spla.spsolve(A, b)


def _finite_energy(system: ClothSystem, x: Tensor, *args) -> float:
    try:
        with torch.no_grad():
            E, _ = system.energy(x, *args)
        E = float(E)
    except ValueError:  # the geometry checks refuse NaN/inf positions
        return math.inf
    return E if math.isfinite(E) else math.inf


def step(system: ClothSystem, x: Tensor, v: Tensor, h: float,
         body_pos: Optional[Tensor] = None, pinned_pos: Optional[Tensor] = None,
         contact: Optional[Tuple[Tensor, Tensor, Tensor]] = None) -> StepResult:
    """One backward-Euler step of size ``h`` by Newton's method on the incremental potential.

    Args:
        system: the cloth (:class:`ClothSystem`).
        x, v: ``[V, 3]`` positions and velocities at ``t_n``.
        h: step in seconds.
        body_pos: ``[Vb, 3]`` body vertices at ``t_{n+1}`` (``None``: no collisions).
        pinned_pos: ``[V, 3]`` targets of the pinned vertices at ``t_{n+1}`` (rows of free
            vertices are ignored; default: pinned vertices stay at ``x``).
        contact: linearised contacts ``(idx, q, n)`` from :meth:`ClothSystem.contact_planes`
            (default: computed at ``x``).
    """
    st = system.settings
    x = x.detach().to(DTYPE)
    v = v.detach().to(DTYPE)
    if not (torch.isfinite(x).all() and torch.isfinite(v).all()):
        raise ValueError("`x`/`v`: contain NaN/inf")
    if not (h > 0 and math.isfinite(h)):
        raise ValueError(f"`h`: must be positive, got {h}")
    x_tilde = x + h * v
    xk = x_tilde.clone()
    if pinned_pos is not None and system.pinned.any():
        xk[system.pinned] = pinned_pos.to(DTYPE)[system.pinned]
        x_tilde[system.pinned] = xk[system.pinned]
    if body_pos is not None:
        body_pos = body_pos.detach().to(DTYPE)
        if system.body_faces is None:
            raise ValueError("`body_pos`: the system was built without body faces")
        if contact is None:
            contact = system.contact_planes(x, body_pos)
    else:
        contact = None
    if contact is not None and contact[0].numel():
        # start outside the moved body: push the inertial guess of contact vertices out
        # along the plane normals (otherwise the body moving into the cloth starts
        # Newton at a huge penalty force)
        idx, q_, n_ = contact[:3]
        depth = (system.material.collision_margin - ((xk[idx] - q_) * n_).sum(-1)).clamp_min(0)
        depth = depth * system.free[idx]
        xk[idx] = xk[idx] + depth.unsqueeze(-1) * n_
    args = (x_tilde, h, body_pos, contact)
    free_dofs = system.free_dofs
    margin, k, q = (system.material.collision_margin, st.collision_stiffness,
                    st.collision_power)
    res = math.inf
    for it in range(st.max_newton + 1):
        xr = xk.clone().requires_grad_(True)
        try:
            with torch.enable_grad():
                E, s = system.energy(xr, *args)
                grad = torch.autograd.grad(E, xr)[0]
        except ValueError as err:
            return StepResult(x, v, False, it, math.inf, False, f"energy evaluation failed: {err}")
        E = float(E.detach())
        if not (math.isfinite(E) and torch.isfinite(grad).all()):
            return StepResult(x, v, False, it, math.inf, False, "non-finite energy or gradient")
        if it == st.max_newton:
            break
        pen_grad = None
        if s is not None:
            pen = (margin - s.detach()).clamp_min(0.0)
            hit = pen > 0
            if hit.any():
                idx = torch.nonzero(hit).squeeze(1)
                coef = k * q * (q - 1) * pen[idx] ** (q - 2)
                pen_grad = (contact[0][idx], coef, contact[2][idx])
        H = system.hessian(xk, h, pen_grad)
        Hff = H[free_dofs][:, free_dofs].tocsc()
        g = grad.reshape(-1).numpy()[free_dofs]
        try:
            d = _solve_spd(Hff, -g)
        except Exception as err:  # singular matrix etc.
            return StepResult(x, v, False, it, res, False, f"linear solve failed: {err}")
        newton = bool(np.all(np.isfinite(d)) and float(d @ g) < 0)
        if not newton:
            d = -g / Hff.diagonal()  # fall back to a (diagonally scaled) gradient step
        slope = float(d @ g)
        dx = torch.zeros(3 * system.V, dtype=DTYPE)
        dx[torch.from_numpy(free_dofs)] = torch.from_numpy(d)
        dx = dx.view(-1, 3)
        res = float(dx.norm(dim=-1).max()) / h
        if newton and res < st.tol:  # converged: take the (tiny) step if it does not hurt
            if _finite_energy(system, xk + dx, *args) <= E:
                xk = xk + dx
            return StepResult(xk, (xk - x) / h, True, it + 1, res, True)
        alpha, accepted = 1.0, False
        for _ in range(st.line_search_steps):
            E_try = _finite_energy(system, xk + alpha * dx, *args)
            if E_try <= E + 1e-4 * alpha * slope:
                accepted = True
                break
            alpha *= 0.5
        if not accepted:
            # stalled at round-off: the predicted decrease is below what float64 resolves
            if -slope <= 1e-13 * max(abs(E), 1.0):
                return StepResult(xk, (xk - x) / h, res < 10 * st.tol, it, res, True,
                                  "line search stalled at round-off")
            return StepResult(x, v, False, it, res, False, "line search failed")
        xk = xk + alpha * dx
    return StepResult(xk, (xk - x) / h, False, st.max_newton, res, True,
                      "Newton did not converge within max_newton")


# ---------------------------------------------------------------------------
# a whole sequence
# ---------------------------------------------------------------------------
def _check_finite(t: Tensor, name: str) -> None:
    if not torch.isfinite(t).all():
        raise ValueError(f"`{name}`: contains NaN/inf")


def _smoothstep(P: int) -> Tensor:
    """``[P]`` weights ``3u^2 - 2u^3`` at ``u = k / P``, ``k = 0 .. P-1``."""
    u = torch.arange(P, dtype=DTYPE) / P
    return u * u * (3 - 2 * u)


def trajectories(garment, body: Optional[Body], motion, preroll_frames: int = 0,
                 body_frames: Optional[Tensor] = None) -> Tuple[Tensor, Optional[Tensor]]:
    """The garment's rest shape carried by the body, and the posed body, for every frame
    an engine steps through: ``preroll_frames`` frames that blend from the rest pose into
    the motion's first pose (joint rotations and root translation scaled by a smoothstep
    from 0 to 1, so the first is the rest pose itself), then the motion's frames.

    Returns ``(skinned [P + T, V, 3] float64, body_frames [P + T, Vb, 3] float64 or None)``.
    The skinned garment is the initial state and the pinned vertices' targets; its weights
    come from :func:`garmentgnn.garments.skinning.transfer_skinning_weights`.  Without a
    ``body`` the garment stays at rest (``preroll_frames`` must then be 0).
    ``body_frames [T, Vb, 3]`` may replace the posed body vertices."""
    from garmentgnn.garments.skinning import transfer_skinning_weights

    verts = garment.vertices
    T, V, P = int(motion.num_frames), verts.shape[0], int(preroll_frames)
    if body is None and P:
        raise ValueError("`preroll_frames`: needs a `body` (nothing to blend into)")
    check_placement(verts, None if body is None else body.vertices)
    if body is not None:
        rot = match_joints(motion, body.skeleton.joint_names)
        trans = motion.translation
        if P:  # pre-roll: rest pose -> first pose (axis-angle scaling = slerp from identity)
            w = _smoothstep(P).to(rot.dtype)
            rot = torch.cat([w.view(P, 1, 1) * rot[:1], rot])
            trans = torch.cat([w.view(P, 1) * trans[:1].to(w.dtype), trans.to(w.dtype)])
        A, _ = forward_kinematics(rot.to(body.vertices.dtype), body.joints, body.skeleton.parents,
                                  trans.to(body.vertices.dtype))
        if body_frames is None:
            body_frames = linear_blend_skinning(body.vertices, body.weights, A)
        elif P:
            _check_finite(body_frames, "body_frames")
            w = _smoothstep(P).to(body_frames.dtype).view(P, 1, 1)
            rest = body.vertices.to(body_frames.dtype)
            body_frames = torch.cat([(1 - w) * rest + w * body_frames[:1], body_frames])
        W = transfer_skinning_weights(verts.float(), garment.faces, body.vertices.float(),
                                      body.weights.float())
        skinned = linear_blend_skinning(verts.to(A.dtype), W.to(A.dtype), A).to(DTYPE)
    else:
        skinned = verts.to(DTYPE).unsqueeze(0).expand(T, V, 3)
        if body_frames is not None:
            raise ValueError("`body_frames`: given without a `body`")
    if body_frames is not None:
        if body_frames.dim() != 3 or body_frames.shape[0] != T + P:
            raise ValueError(f"`body_frames`: expected [{T}, Vb, 3] (one per motion frame), got "
                             f"{(body_frames.shape[0] - P,) + tuple(body_frames.shape[1:])}")
        _check_finite(body_frames, "body_frames")
        body_frames = body_frames.detach().to(DTYPE)
    return skinned, body_frames


def simulate(garment, body: Optional[Body], motion, material: Material,
             settings: Optional[SimSettings] = None,
             progress: Optional[Callable[[int, int], None]] = None,
             body_frames: Optional[Tensor] = None) -> SimResult:
    """Simulate ``garment`` on ``body`` following ``motion``; one output per motion frame.

    The garment starts at its rest shape skinned (weights from
    :func:`garmentgnn.garments.skinning.transfer_skinning_weights`) to the motion's first
    frame with zero velocity; pinned vertices follow their skinned positions.  The body
    is interpolated linearly between frames for the substeps.  ``body=None`` simulates
    without a body (``motion`` then only sets the number of frames; pinned vertices stay
    at rest).  ``body_frames [T, Vb, 3]`` may replace the posed body vertices.
    ``progress(frame, num_frames)`` is called after each frame.
    """
    t0 = time.time()
    st = settings or SimSettings()
    st.validate()
    if not isinstance(material, Material):
        raise ValueError(f"`material`: expected a Material, got {type(material).__name__}")
    verts = garment.vertices
    if not isinstance(verts, Tensor) or verts.dim() != 2 or verts.shape[-1] != 3:
        raise ValueError("`garment.vertices`: expected a [V, 3] tensor")
    _check_finite(verts, "garment.vertices")
    _check_finite(garment.face_uv, "garment.face_uv")
    fps_m = float(getattr(motion, "fps", st.fps))
    if not fps_m > 0:
        raise ValueError(f"`motion.fps`: must be positive, got {fps_m}")
    if abs(fps_m - st.fps) > 1e-6 * st.fps:
        raise ValueError(f"`settings.fps` ({st.fps}) differs from `motion.fps` ({fps_m}); "
                         f"use motion.resample({st.fps}) or set settings.fps")
    T = int(motion.num_frames)
    if T < 1:
        raise ValueError("`motion`: has no frames")
    V = verts.shape[0]
    pinned = garment.pinned if garment.pinned is not None else torch.zeros(V, dtype=torch.bool)
    P = st.preroll_frames if body is not None else 0
    skinned, body_frames = trajectories(garment, body, motion, P, body_frames)
    body_faces = None if body is None else body.faces
    system = ClothSystem(verts, garment.faces, material, garment.face_uv, pinned, body_faces, st)

    x = skinned[0].clone()
    v = torch.zeros_like(x)
    frame_dt = 1.0 / st.fps
    margin = material.collision_margin

    def run_frame(x, v, b0, b1, p0, p1, substeps, accept_penetration=False):
        h = frame_dt / substeps
        iters, res, conv, note = 0, 0.0, True, ""
        # the body moves |b1 - b0| / substeps per substep: vertices that close must be in
        # the contact set from the start, or a fast limb passes through them
        radius = st.contact_radius if b0 is None else max(
            st.contact_radius, 2.0 * float((b1 - b0).norm(dim=-1).max()) / substeps)
        for s in range(1, substeps + 1):
            w = s / substeps
            bp = None if b0 is None else (1 - w) * b0 + w * b1
            pp = (1 - w) * p0 + w * p1
            contact = None if bp is None else system.contact_planes(x, bp, radius)
            for _ in range(3):
                r = step(system, x, v, h, bp, pp, contact)
                if not r.ok or bp is None:
                    break
                # the planes are a linearisation: check the true distance, refresh if needed
                new = system.contact_planes(r.x, bp, radius)
                d = new[3]
                known = torch.zeros(system.V, dtype=torch.bool)
                known[contact[0]] = True
                if not ((d < 0).any() or ((d < margin) & ~known).any()):
                    break
                contact = new
            if r.ok and bp is not None and float(d.min()) < -st.max_penetration:
                depth = (f"penetration {-float(d.min()) * 1e3:.1f} mm > max_penetration "
                         f"{st.max_penetration * 1e3:.1f} mm")
                if accept_penetration:
                    # the finest substeps cannot resolve it either: a pinch between body
                    # parts (arm against torso), not tunnelling -- keep it, flagged
                    r = StepResult(r.x, r.v, False, r.iterations, r.residual, True, depth)
                    note = depth
                else:  # maybe tunnelled: retry the frame with smaller substeps
                    r = StepResult(x, v, False, r.iterations, r.residual, False, depth)
            iters += r.iterations
            res = max(res, r.residual)
            conv = conv and r.converged
            if not r.ok:
                return None, None, iters, res, False, r.message
            x, v = r.x, r.v
        return x, v, iters, res, conv, note

    def advance(x, v, b0, b1, p0, p1, label):
        sub = st.substeps
        msg = ""
        for k in range(st.max_refinements + 1):
            out = run_frame(x, v, b0, b1, p0, p1, sub,
                            accept_penetration=k == st.max_refinements)
            if out[0] is not None and (out[4] or not st.retry_unconverged):
                return out + (sub,)
            msg = out[5] or "Newton did not converge"
            sub *= 2
        return None, None, out[2], out[3], False, f"{label}: {msg} (also with {sub // 2} substeps)", sub

    bf = (lambda t: None) if body_frames is None else (lambda t: body_frames[t])
    warmup = [(t - 1, t, f"pre-roll frame {t}") for t in range(1, P + 1)] \
        + [(P, P, f"settle frame {i}") for i in range(st.settle_frames)]
    for a, b, label in warmup:
        out = advance(x, v, bf(a), bf(b), skinned[a], skinned[b], label)
        if out[0] is None:
            return SimResult(torch.zeros(0, V, 3), torch.zeros(0, dtype=torch.bool),
                             torch.zeros(0, dtype=torch.long), torch.zeros(0), False, out[5],
                             time.time() - t0)
        x, v = out[0], out[1]
    flagged: List[str] = []

    def exact_depth(t: int, x: Tensor) -> float:
        """Exact penetration at the end of frame ``t`` (flagged over the limit)."""
        if body_frames is None:
            return 0.0
        d = float(penetration_depth(x, body_frames[P + t], body_faces).max())
        if d > st.max_penetration:
            flagged.append(f"frame {t}: exact penetration {d * 1e3:.1f} mm > max_penetration "
                           f"{st.max_penetration * 1e3:.1f} mm")
        return d

    positions: List[Tensor] = [x.float()]
    converged, iterations, residual, substeps = [True], [0], [0.0], [0]
    penetration = [exact_depth(0, x)]
    ok, message = True, "ok"
    for t in range(1, T):
        out = advance(x, v, bf(P + t - 1), bf(P + t), skinned[P + t - 1], skinned[P + t],
                      f"frame {t}")
        if out[0] is None:
            ok, message = False, out[5]
            break
        x, v = out[0], out[1]
        if not torch.isfinite(x).all():  # cannot happen (energies refuse NaN), but never emit it
            ok, message = False, f"frame {t}: non-finite positions"
            break
        positions.append(x.float())
        converged.append(bool(out[4]))
        iterations.append(int(out[2]))
        residual.append(float(out[3]))
        substeps.append(int(out[6]))
        if out[5]:
            flagged.append(f"frame {t}: {out[5]}")
        penetration.append(exact_depth(t, x))
        if progress is not None:
            progress(t, T)
    if ok and flagged:
        message = f"ok; {len(flagged)} frame(s) kept with flags, first: {flagged[0]}"
    return SimResult(torch.stack(positions), torch.tensor(converged),
                     torch.tensor(iterations, dtype=torch.long),
                     torch.tensor(residual, dtype=torch.float32), ok, message, time.time() - t0,
                     torch.tensor(substeps, dtype=torch.long),
                     torch.tensor(penetration, dtype=torch.float32), float(st.max_penetration))
