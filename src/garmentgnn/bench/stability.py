"""Stability suite: hard inputs for a garment predictor, each scored stable / degraded /
failed.

A predictor is any callable ``predict(sequence: BenchSequence) -> positions``, where
``positions`` is a ``[T, V, 3]`` tensor or an object with ``.positions`` (and
optionally ``.ok``, ``.message``, ``.converged [T]``) such as a
:class:`garmentgnn.sim.SimResult`.  The reference simulator is wrapped by
:func:`simulator_predictor`; a learned model is plugged in by wrapping its rollout the
same way.

Cases (on any generated item: the bench's small garment on the capsule body for the
simulator, a test sequence of the learned methods' dataset for them, see
:meth:`garmentgnn.bench.learned.LearnedRunner.stability_record`):

=================  ==============================================================
``baseline``       the unmodified case (reference point for the others)
``stiff_x1000``    material stiffness x1000 (``Material.scaled(1000)``)
``extreme_pose``   every limited joint driven over the sequence to (beyond, then
                   clamped back to) its limits of :mod:`garmentgnn.motion.limits`
``fast_x5``        the motion at 5x speed
``long_1000``      the motion generated over 1000 frames (:data:`LONG_FRAMES`)
``sliver_face``    one interior triangle squashed to 1/1000 of its area (a vertex
                   moved 99.9% of the way to its opposite edge, in 3D and UV alike)
``zero_area_face`` the same vertex moved onto the edge (3D), the face's UV collapsed to
                   exactly zero area (``ClothRest.valid`` False)
=================  ==============================================================

Measured per case: non-finite coordinates, the largest vertex speed (finite
differences between frames), energy growth, the deepest body penetration (from
:func:`garmentgnn.geometry.signed_distance`), frames whose solve did not converge.
The verdict thresholds are in :class:`Thresholds`.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from typing import Any, Callable, Dict, Optional, Tuple

import torch
from torch import Tensor

from garmentgnn.bench.records import failure
from garmentgnn.bench.sequences import BenchSequence, make_sequence
from garmentgnn.garments import Garment
from garmentgnn.geometry import boundary_vertex_mask, signed_distance
from garmentgnn.geometry.rotations import euler_to_matrix, matrix_to_axis_angle
from garmentgnn.metrics import physics_energy
from garmentgnn.models.inputs import skin
from garmentgnn.motion import (Motion, clamp_to_limits, joint_limits, limit_violation,
                              slerp_rotations)
from garmentgnn.sim import SimSettings, simulate

Predictor = Callable[[BenchSequence], Any]


@dataclass(frozen=True)
class Thresholds:
    """Verdict rules (``failed`` is checked first, then ``degraded``; else ``stable``).

    failed when any of: the predictor raised or reported ``ok=False``; any non-finite
    coordinate; max vertex speed > ``fail_speed`` (m/s); energy growth >
    ``fail_growth``; penetration deeper than ``fail_penetration`` (m).

    degraded when any of: max vertex speed > ``speed_factor`` x the body's max vertex
    speed + ``speed_slack`` (m/s); energy growth > ``degrade_growth``; penetration
    deeper than ``degrade_penetration`` (m); a frame's solve did not converge.

    Energy growth is ``max_t E(t) / max(E(0), E(1), max_t E_LBS(t), energy_floor)`` with
    ``E`` the elastic (stretch + shear + bending) plus kinetic energy (gravity, whose zero
    is arbitrary, is left out) and ``E_LBS`` that of the LBS garment on the same case:
    the energy the body's own motion gives a garment that follows it.  A rollout that
    starts at rest (zero energy at frames 0 and 1) is measured against that scale, not
    against its start; LBS itself grows by at most 1.  The body does work on the garment,
    so moderate growth is physical and only large factors count.
    """

    fail_speed: float = 50.0
    fail_growth: float = 1e3
    fail_penetration: float = 0.03
    speed_factor: float = 2.0
    speed_slack: float = 2.0
    degrade_growth: float = 10.0
    degrade_penetration: float = 0.005
    energy_floor: float = 1e-6


THRESHOLDS = Thresholds()


# --------------------------------------------------------------------------- cases
def _extreme_pose(seq: BenchSequence) -> Tuple[Motion, Dict[str, Any]]:
    """Every limited joint driven from the motion's pose towards a target 10 deg beyond
    its larger-magnitude bound on each Euler axis (slerp, smoothstep from 0 at frame 0
    to 1 at the last frame), then clamped to the limits: the last frames hold every
    joint at its limits."""
    m = seq.motion
    skel = seq.body.skeleton
    lims = joint_limits(skel)
    rot = m.rotations.double()
    T = rot.shape[0]
    target = rot[-1].clone()
    for k, lim in enumerate(lims):
        if lim is None:
            continue
        lo, hi = lim.in_order()
        ang = [(h if abs(h) >= abs(lo_) else lo_) for lo_, h in zip(lo, hi)]
        ang = [a + (10.0 if a > 0 else -10.0 if a < 0 else 0.0) for a in ang]
        R = euler_to_matrix(torch.deg2rad(torch.tensor(ang, dtype=torch.float64)), lim.order)
        target[k] = matrix_to_axis_angle(R)
    u = torch.linspace(0.0, 1.0, T, dtype=torch.float64) if T > 1 else torch.ones(1).double()
    w = (u * u * (3 - 2 * u)).view(T, 1, 1)
    wild = slerp_rotations(rot, target.expand_as(rot), w)
    clamped = int((limit_violation(wild, skel) > 1e-3).sum())
    out = clamp_to_limits(wild, skel).to(m.rotations.dtype)
    return Motion(out, m.translation, m.joint_names, m.fps), {"joint_frames_clamped": clamped}


def _degenerate(seq: BenchSequence, fraction: float) -> Tuple[Garment, Dict[str, Any]]:
    """Move an interior, unpinned vertex ``fraction`` of the way to the midpoint of the
    opposite edge of one of its faces, in 3D and in every UV corner referencing it."""
    g = seq.garment
    V = g.num_vertices
    free = ~boundary_vertex_mask(g.faces, V)
    if g.pinned is not None:
        free &= ~g.pinned
    if not bool(free.any()):
        raise ValueError("`garment`: no interior, unpinned vertex to degrade")
    # the spread of each vertex's UV corners: 0 off the seams of a pattern whose panels are
    # flat; a garment whose face_uv is laid flat per face (templates.build_pattern on a
    # non-developable panel) has none at 0, so the vertices of the smallest spread are used
    flat, fu0 = g.faces.flatten(), g.face_uv.reshape(-1, 2)
    idx = flat[:, None].expand(-1, 2)
    hi = torch.full((V, 2), -float("inf"), dtype=fu0.dtype).scatter_reduce(0, idx, fu0, "amax")
    lo = torch.full((V, 2), float("inf"), dtype=fu0.dtype).scatter_reduce(0, idx, fu0, "amin")
    spread = (hi - lo).amax(-1)
    free &= spread <= max(1e-7, float(spread[free].min()))
    cand = torch.nonzero(free[g.faces], as_tuple=False)  # [K, 2]: (face, corner)
    f, c = (int(i) for i in cand[cand.shape[0] // 2])
    order = [c, (c + 1) % 3, (c + 2) % 3]  # the chosen corner first, winding kept
    v, a, b = (int(g.faces[f, k]) for k in order)
    verts = g.vertices.clone()
    def move(p, q):  # exactly q at fraction 1 (no float round-off: a true zero area)
        return q.clone() if fraction >= 1.0 else p + fraction * (q - p)

    verts[v] = move(verts[v], 0.5 * (verts[a] + verts[b]))
    uv = g.uv.clone()
    uv[v] = move(uv[v], 0.5 * (uv[a] + uv[b]))
    face_uv = g.face_uv.clone()
    fu = face_uv.view(-1, 2)
    corners = torch.nonzero(flat == v, as_tuple=False).flatten()
    tri = face_uv[f, order]
    target = 0.5 * (tri[1] + tri[2])
    fu[corners] += move(tri[0], target) - tri[0]  # every corner of v by the same UV step
    if fraction >= 1.0:
        # the float32 midpoint is collinear only up to round-off (ClothRest would still
        # call the face valid): collapse this face's UV corner onto a neighbour instead,
        # an exactly zero-area UV face (3D: the vertex lies on the edge)
        face_uv[f, c] = face_uv[f, order[1]]
    new = Garment(verts, g.faces.clone(), uv, face_uv, name=g.name + "-degenerate", kind=g.kind,
                  pinned=g.pinned, panel=g.panel, info=dict(g.info))
    # in Python floats (IEEE double, no BLAS): float32 corners' differences and their
    # products are exact there, so two equal corners give exactly 0 on any CPU (a LAPACK
    # determinant gave 2e-20 m^2 on one MKL code path and 0 on another)
    (u0, v0), (u1, v1), (u2, v2) = face_uv[f].double().tolist()
    area = 0.5 * abs((u1 - u0) * (v2 - v0) - (u2 - u0) * (v1 - v0))
    return new, {"face": f, "vertex": v, "uv_area_m2": float(area),
                 "uv_corner_spread_m": float(spread[v])}


def stability_sequence(case: str, item: Dict[str, Any], seed: int
                       ) -> Tuple[BenchSequence, Dict[str, Any]]:
    """The :class:`BenchSequence` of stability ``case`` built on ``item`` (a
    :func:`garmentgnn.bench.sequences.case_item`), and facts about the perturbation."""
    if case not in CASES:
        raise ValueError(f"`case`: unknown stability case {case!r}; choose one of {sorted(CASES)}")
    item = dict(item, name=case)
    base = make_sequence(item, seed)
    if case == "baseline":
        return base, {}
    if case == "stiff_x1000":
        return (make_sequence(item, seed, material=base.material.scaled(1000.0)),
                {"stiffness": 1000.0})
    if case == "extreme_pose":
        motion, info = _extreme_pose(base)
        return make_sequence(item, seed, motion=motion), info
    if case == "long_1000":
        it = dict(item, motion=dict(item["motion"], num_frames=LONG_FRAMES))
        return make_sequence(it, seed), {"num_frames": LONG_FRAMES}
    if case == "fast_x5":
        it = dict(item, motion=dict(item["motion"], speed=5.0 * item["motion"]["speed"]))
        return make_sequence(it, seed), {"speed": it["motion"]["speed"]}
    garment, info = _degenerate(base, 0.999 if case == "sliver_face" else 1.0)
    return make_sequence(item, seed, garment=garment), info


#: frames of the ``long_1000`` case
LONG_FRAMES = 1000

CASES: Dict[str, str] = {
    "baseline": "unmodified",
    "stiff_x1000": "material stiffness x1000",
    "extreme_pose": "joints driven to their limits (clamped)",
    "fast_x5": "motion at 5x speed",
    "long_1000": "the motion over 1000 frames",
    "sliver_face": "one face squashed to 1/1000 of its area (3D + UV)",
    "zero_area_face": "one face of zero area (vertex on the edge in 3D, UV exactly 0)",
}


# --------------------------------------------------------------------------- predictors
def simulator_predictor(**settings: Any) -> Predictor:
    """The reference simulator as a predictor; ``settings`` are :class:`SimSettings`
    keyword arguments (``fps`` is taken from the motion)."""
    def predict(seq: BenchSequence):
        st = SimSettings(**dict(settings, fps=float(seq.motion.fps)))
        return simulate(seq.garment, seq.body, seq.motion, seq.material, st,
                        body_frames=seq.body_frames)

    return predict


# --------------------------------------------------------------------------- scoring
def _unpack(out: Any) -> Tuple[Tensor, bool, str, Optional[Tensor]]:
    if isinstance(out, Tensor):
        return out, True, "ok", None
    pos = getattr(out, "positions", None)
    if not isinstance(pos, Tensor):
        raise ValueError("`predict`: must return a [T, V, 3] tensor or an object with "
                         f".positions, got {type(out).__name__}")
    conv = getattr(out, "converged", None)
    return pos, bool(getattr(out, "ok", True)), str(getattr(out, "message", "ok")), conv


def garment_energy(seq: BenchSequence, pos: Tensor) -> Tensor:
    """``[T]`` elastic (stretch + shear + bending) plus kinetic energy (J) of the
    garment positions ``pos [T, V, 3]`` (float64) of ``seq``."""
    T = pos.shape[0]
    e = physics_energy(pos, seq.rest, seq.material, seq.mass)
    kinetic = torch.zeros(T, dtype=pos.dtype)
    if T > 1:
        speed = (pos[1:] - pos[:-1]).norm(dim=-1) * float(seq.motion.fps)
        kinetic[1:] = 0.5 * (seq.mass.double() * speed ** 2).sum(-1)
    return e["stretch"] + e["shear"] + e["bending"] + kinetic


def lbs_energy(seq: BenchSequence, frames: Optional[int] = None) -> float:
    """The largest energy (:func:`garment_energy`) of the LBS garment of ``seq`` over its
    first ``frames`` frames: the rest garment skinned with the simulator's weights."""
    m = seq.motion
    T = m.num_frames if frames is None else min(frames, m.num_frames)
    with torch.no_grad():
        pos, _ = skin(seq.scene, m.rotations[:T].to(seq.scene.rest_pos.dtype),
                      m.translation[:T].to(seq.scene.rest_pos.dtype))
    e = garment_energy(seq, pos.double())
    return float(e[torch.isfinite(e)].max()) if bool(torch.isfinite(e).any()) else 0.0


def stability_metrics(seq: BenchSequence, positions: Tensor,
                      thresholds: Thresholds = THRESHOLDS) -> Dict[str, float]:
    """Numbers of one predicted sequence ``[T', V, 3]`` (``T' <= T``: a predictor that
    stopped early is scored on what it produced)."""
    pos = positions.detach().double()
    T = pos.shape[0]
    nonfinite = int((~torch.isfinite(pos)).sum())
    out: Dict[str, float] = {"frames": float(T), "nonfinite": float(nonfinite)}
    body = seq.body_frames.detach().double()[:T]
    fps = float(seq.motion.fps)
    body_speed = float(((body[1:] - body[:-1]).norm(dim=-1) * fps).max()) if T > 1 else 0.0
    out["body_max_speed"] = body_speed
    if nonfinite:
        return out
    speed = (pos[1:] - pos[:-1]).norm(dim=-1) * fps  # [T-1, V]
    out["max_speed"] = float(speed.max()) if T > 1 else 0.0
    total = garment_energy(seq, pos)
    lbs = lbs_energy(seq, T)
    out["lbs_max_energy_J"] = lbs
    ref = max(float(total[: min(T, 2)].max()), lbs, thresholds.energy_floor)
    out["energy_growth"] = float(total.max()) / ref
    out["max_energy_J"] = float(total.max())
    # one frame at a time: the distance query's memory grows with frames x vertices x
    # body faces (100 frames of a 420-vertex garment on anny took 9 GB at once)
    deepest = min(float(signed_distance(pos[t], body[t], seq.body.faces).distance.min())
                  for t in range(T))
    out["max_penetration_m"] = max(0.0, -deepest)
    return out


def verdict(metrics: Dict[str, float], ok: bool, nonconverged: int,
            thresholds: Thresholds = THRESHOLDS) -> Tuple[str, str]:
    """``(verdict, reason)`` per :class:`Thresholds`."""
    th = thresholds
    if not ok:
        return "failed", "predictor reported failure"
    if metrics.get("nonfinite", 0) > 0:
        return "failed", f"{int(metrics['nonfinite'])} non-finite coordinates"
    fails = [(metrics["max_speed"] > th.fail_speed, f"max speed {metrics['max_speed']:.3g} m/s"),
             (metrics["energy_growth"] > th.fail_growth,
              f"energy growth x{metrics['energy_growth']:.3g}"),
             (metrics["max_penetration_m"] > th.fail_penetration,
              f"penetration {1e3 * metrics['max_penetration_m']:.3g} mm")]
    bad = [r for c, r in fails if c]
    if bad:
        return "failed", "; ".join(bad)
    speed_limit = th.speed_factor * metrics["body_max_speed"] + th.speed_slack
    degr = [(metrics["max_speed"] > speed_limit,
             f"max speed {metrics['max_speed']:.3g} > {speed_limit:.3g} m/s"),
            (metrics["energy_growth"] > th.degrade_growth,
             f"energy growth x{metrics['energy_growth']:.3g}"),
            (metrics["max_penetration_m"] > th.degrade_penetration,
             f"penetration {1e3 * metrics['max_penetration_m']:.3g} mm"),
            (nonconverged > 0, f"{nonconverged} frame(s) not converged")]
    bad = [r for c, r in degr if c]
    if bad:
        return "degraded", "; ".join(bad)
    return "stable", ""


def run_case(case: str, item: Dict[str, Any], seed: int, predict: Predictor,
             method: str = "sim", thresholds: Thresholds = THRESHOLDS) -> Dict[str, Any]:
    """Build stability ``case`` on ``item``, run ``predict`` and score it; a record for
    :mod:`garmentgnn.bench.report` (``kind="stability"``).  Exceptions from the predictor
    (or from building the case) give ``status="failed"`` with the message."""
    rec: Dict[str, Any] = {"kind": "stability", "method": method, "case": case, "seed": seed,
                           "description": CASES.get(case, ""),
                           "thresholds": asdict(thresholds)}
    t0 = time.perf_counter()
    try:
        seq, info = stability_sequence(case, item, seed)
        rec["info"] = info
        rec["num_vertices"] = seq.garment.num_vertices
        positions, ok, message, conv = _unpack(predict(seq))
        if positions.dim() != 3 or positions.shape[1:] != (seq.garment.num_vertices, 3):
            raise ValueError(f"`predict`: returned positions of shape {tuple(positions.shape)}")
        nonconv = 0 if conv is None else int((~conv.bool()).sum())
        m = stability_metrics(seq, positions, thresholds)
        m["nonconverged_frames"] = float(nonconv)
        v, reason = verdict(m, ok, nonconv, thresholds)
        rec.update(status="ok", metrics=m, verdict=v, reason=reason,
                   message=message if not ok else "ok")
    except Exception as err:  # a crash is a result of this suite, not an error of it
        rec.update(failure(err), verdict="failed", metrics={}, reason=f"raised: {err}")
    rec["seconds"] = time.perf_counter() - t0
    return rec
