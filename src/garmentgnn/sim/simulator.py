"""Reference implicit cloth simulator (incremental-potential Newton solver).

Every substep solves ``x_{n+1} = argmin_x E_inertia(x; x_n + h v_n) + E_membrane(x)
+ E_bending(x) + E_gravity(x) + E_collision(x, body(t_{n+1})) + D_friction(x)`` and sets
``v_{n+1} = (x_{n+1} - x_n) / h`` (backward Euler).  All energies are the ones of
:mod:`garmentgnn.physics`; the solver lives in the sibling modules:

* :mod:`garmentgnn.sim.settings` -- :class:`SimSettings`, :class:`SimResult`;
* :mod:`garmentgnn.sim.system` -- :class:`ClothSystem` (energies, contact planes,
  PSD-projected sparse Hessian);
* :mod:`garmentgnn.sim.newton` -- :func:`step` (Newton + line search);
* :mod:`garmentgnn.sim.trajectory` -- :func:`trajectories` (skinning, pre-roll);
* :mod:`garmentgnn.sim.colliders` -- rigid :class:`Sphere` / :class:`Plane` colliders.

This module holds :func:`simulate` (a whole sequence, with frame retries) and re-exports
the names above.  See ``docs/simulator.md``.
"""
from __future__ import annotations

import time
from typing import Callable, List, Optional, Sequence, Union

import torch
from torch import Tensor

from garmentgnn.body.body import Body
from garmentgnn.geometry import penetration_depth
from garmentgnn.physics import Material
from garmentgnn.sim.colliders import Collider, Plane, Sphere
from garmentgnn.sim.newton import step
from garmentgnn.sim.settings import DTYPE, SimResult, SimSettings, StepResult
from garmentgnn.sim.system import ClothSystem, Contact, check_colliders
from garmentgnn.sim.trajectory import check_finite, trajectories

__all__ = ["ClothSystem", "Collider", "Contact", "DTYPE", "Plane", "SimResult", "Sphere",
           "SimSettings", "StepResult", "simulate", "step", "trajectories"]


def simulate(garment, body: Optional[Body], motion, material: Material,
             settings: Optional[SimSettings] = None,
             progress: Optional[Callable[[int, int], None]] = None,
             body_frames: Optional[Tensor] = None,
             colliders: Union[Collider, Sequence[Collider]] = ()) -> SimResult:
    """Simulate ``garment`` on ``body`` following ``motion``; one output per motion frame.

    The garment starts at its rest shape skinned (weights from
    :func:`garmentgnn.garments.skinning.transfer_skinning_weights`) to the motion's first
    frame with zero velocity; pinned vertices follow their skinned positions.  The body
    is interpolated linearly between frames for the substeps.  ``body=None`` simulates
    without a body (``motion`` then only sets the number of frames; pinned vertices stay
    at rest).  ``body_frames [T, Vb, 3]`` may replace the posed body vertices.
    ``progress(frame, num_frames)`` is called after each frame.

    ``colliders`` (:class:`~garmentgnn.sim.colliders.Sphere`,
    :class:`~garmentgnn.sim.colliders.Plane`) are rigid obstacles besides or instead of
    the body ("cloth drapes on a sphere" needs ``body=None, colliders=Sphere(...)``);
    moving colliders are interpolated between frames like the body.  Contacts with the
    body and the colliders get Coulomb friction with ``material.friction`` as ``mu``
    (lagged IPC friction, :mod:`garmentgnn.physics.friction`).  ``SimResult.penetration``
    is the exact depth inside the body or any collider.
    """
    t0 = time.time()
    st = settings or SimSettings()
    st.validate()
    if not isinstance(material, Material):
        raise ValueError(f"`material`: expected a Material, got {type(material).__name__}")
    verts = garment.vertices
    if not isinstance(verts, Tensor) or verts.dim() != 2 or verts.shape[-1] != 3:
        raise ValueError("`garment.vertices`: expected a [V, 3] tensor")
    check_finite(verts, "garment.vertices")
    check_finite(garment.face_uv, "garment.face_uv")
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
    colliders = check_colliders(colliders)
    system = ClothSystem(verts, garment.faces, material, garment.face_uv, pinned, body_faces, st,
                         colliders)
    touching = body is not None or bool(colliders)

    x = skinned[0].clone()
    v = torch.zeros_like(x)
    frame_dt = 1.0 / st.fps
    margin = material.collision_margin

    def run_frame(x, v, b0, b1, p0, p1, f0, f1, substeps, accept_penetration=False):
        h = frame_dt / substeps
        iters, res, conv, note = 0, 0.0, True, ""
        # the body moves |b1 - b0| / substeps per substep: vertices that close must be in
        # the contact set from the start, or a fast limb passes through them
        radius = st.contact_radius if b0 is None else max(
            st.contact_radius, 2.0 * float((b1 - b0).norm(dim=-1).max()) / substeps)
        for c in colliders:  # likewise for a moving collider
            moved = float(c.motion(x.new_zeros(1, 3), f0, f1).norm())
            radius = max(radius, 2.0 * moved / substeps)
        for s in range(1, substeps + 1):
            w = s / substeps
            w_prev = (s - 1) / substeps
            bp = None if b0 is None else (1 - w) * b0 + w * b1
            bq = None if b0 is None else (1 - w_prev) * b0 + w_prev * b1
            pp = (1 - w) * p0 + w * p1
            fp, fq = (1 - w) * f0 + w * f1, (1 - w_prev) * f0 + w_prev * f1

            def planes(y: Tensor) -> Contact:
                return system.contact_planes(y, bp, radius, fp, bq, fq)

            contact = planes(x) if touching else None
            for _ in range(3):
                r = step(system, x, v, h, bp, pp, contact)
                if not r.ok or not touching:
                    break
                # the planes are a linearisation: check the true distance, refresh if needed
                new = planes(r.x)
                d = new[3]
                known = torch.zeros(system.V, dtype=torch.bool)
                known[contact[0]] = True
                if not ((d < 0).any() or ((d < margin) & ~known).any()):
                    break
                contact = new
            if r.ok and touching and float(d.min()) < -st.max_penetration:
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

    def advance(x, v, b0, b1, p0, p1, label, f0=0.0, f1=0.0):
        sub = st.substeps
        msg = ""
        for k in range(st.max_refinements + 1):
            out = run_frame(x, v, b0, b1, p0, p1, f0, f1, sub,
                            accept_penetration=k == st.max_refinements)
            if out[0] is not None and (out[4] or not st.retry_unconverged):
                return out + (sub,)
            msg = out[5] or "Newton did not converge"
            sub *= 2
        why = f"{label}: {msg} (also with {sub // 2} substeps)"
        return None, None, out[2], out[3], False, why, sub

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
        d = 0.0
        if body_frames is not None:
            d = float(penetration_depth(x, body_frames[P + t], body_faces).max())
        for c in colliders:
            d = max(d, float((-c.distance(x, float(t)).distance).max()))
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
                      f"frame {t}", float(t - 1), float(t))
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
