"""Procedural garments sized from the body they are made for.

Every template builds one connected, consistently oriented, manifold triangle mesh
around the rest body (Z up, facing -Y, metres) out of structured quad strips:

* tubes are stacks of rings of vertices; a ring can *split* (trousers: the ring at the
  crotch is cut by a crotch seam into the two leg openings) and the front/back panels of
  a top rise from the armpit ring to the shoulder seams, leaving a neck hole and two
  armholes; a sleeve's first ring *is* its armhole loop -- parts always share the seam
  vertices, so there are no T-junctions;
* sizes come from the body: horizontal cross-sections (convex hull of the torso surface
  in a height band, grown by ``ease``), limb radii around the bones, the armpit height
  (highest ring that clears the arms), the crotch height (highest level where the legs
  are far enough apart), the neck (narrowest level between the neck and head joints) --
  so one template fits thin, regular and fat bodies;
* placement: after building, every vertex closer than ``margin`` to the body (or inside)
  is moved out along the direction away from its closest body point (repeated), using an
  exact point-to-mesh distance (:mod:`garmentgnn.garments._distance`).  The design
  itself keeps about ``ease`` of room, so pushes are rare;
* material coordinates: see :mod:`garmentgnn.garments._flatten` and
  :class:`~garmentgnn.garments.Garment`.  Each panel (pattern piece) is flattened with
  ARAP into a sewing pattern; ``face_uv`` is every rest triangle laid flat and rigidly
  fitted to that pattern, so the rest stretch/shear of Eq. 12-14 is exactly zero and,
  wherever the panel is developable, ``face_uv`` *is* the pattern (continuous across
  edges).  Skirts are stacks of cones over the waist section with one panel per cone
  (yoke above the hips, skirt below), i.e. exactly developable: their pattern is the
  unrolled annular sectors.  Doubly curved transitions (sleeve caps, the crotch, the
  shoulders) cannot be flattened exactly; there ``face_uv`` stays exact per face and is
  discontinuous across edges by up to a few millimetres.
* panels: skirt -- cones, cut at the centre back; trousers -- waist tube and one panel
  per leg (cut along the inseam); tops -- front, back (side seams, shoulder seams) and
  one per sleeve (cut along the underarm); dress with straps -- skirt cones, bodice,
  one per strap.  ``Garment.panel`` holds the panel id of every face.

``resolution``: ``"low"`` (~1,000 vertices), ``"medium"`` (~4,000), ``"high"``
(~16,000, i.e. at least the 14K of the paper's largest garments) or an int target
vertex count.  The mesh spacing ``h`` is chosen as ``h = h0 * sqrt(V0 / target)`` from a
coarse trial build (vertex count ~ area / h^2), so the count lands within ~10% of the
target.
"""
from __future__ import annotations

import logging
from typing import Callable, Dict, Optional, Union

import numpy as np
import torch

from garmentgnn.garments._fit import (HEAD, L_ARM, L_LEG, R_ARM, R_LEG, TORSO, BodyFit,
                                      MeshBuilder, grid_uv, hull_polygon, polar_radius,
                                      quarter_ring)
from garmentgnn.garments._flatten import build_pattern
from garmentgnn.garments.garment import Garment

log = logging.getLogger(__name__)

RESOLUTIONS: Dict[str, int] = {"low": 1000, "medium": 4000, "high": 16000}
#: skirt flare presets: horizontal growth of the radius per metre of length
FLARES: Dict[str, float] = {"pencil": 0.0, "straight": 0.0, "a-line": 0.25, "flared": 0.5,
                            "full": 0.9}
SLEEVES = ("none", "short", "elbow", "long")
#: sleeves: fraction of the armhole-to-arm turn done by rotating the armhole loop (the
#: rest happens while its shape morphs into the sleeve's circles over MORPH metres)
HINGE, MORPH = 0.5, 0.12

Length = Union[str, float]


def _target(resolution: Union[str, int]) -> int:
    if isinstance(resolution, str):
        if resolution not in RESOLUTIONS:
            raise ValueError(f"`resolution`: unknown preset {resolution!r}; use one of "
                             f"{list(RESOLUTIONS)} or a target vertex count")
        return RESOLUTIONS[resolution]
    n = int(resolution)
    if n < 200 or n > 200_000:
        raise ValueError(f"`resolution`: target vertex count must lie in [200, 200000], got {n}")
    return n


def _check_common(ease: float, margin: float) -> None:
    if not np.isfinite(ease) or ease < 0:
        raise ValueError(f"`ease`: must be a non-negative number of metres, got {ease}")
    if not np.isfinite(margin) or margin < 0:
        raise ValueError(f"`margin`: must be a non-negative number of metres, got {margin}")


def _smooth_step(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


# ---------------------------------------------------------------------------------------
# measurements
# ---------------------------------------------------------------------------------------
def _waist_z(fit: BodyFit) -> float:
    return float(fit.J["pelvis"][2] + 0.35 * (fit.J["chest"][2] - fit.J["pelvis"][2]))


def _section(fit: BodyFit, z_lo: float, z_hi: float, labels, ease: float):
    pts = fit.select(labels, z_lo, z_hi)
    if len(pts) < 3:  # widen the band until the body is hit
        mid, half = 0.5 * (z_lo + z_hi), 0.5 * (z_hi - z_lo)
        for k in range(1, 20):
            pts = fit.select(labels, mid - half - 0.01 * k, mid + half + 0.01 * k)
            if len(pts) >= 3:
                break
    poly = hull_polygon(pts[:, :2], ease)
    # area centroid of the polygon
    x, y = poly[:, 0], poly[:, 1]
    xs, ys = np.roll(x, -1), np.roll(y, -1)
    cr = x * ys - xs * y
    A = cr.sum() / 2
    centre = np.array([((x + xs) * cr).sum(), ((y + ys) * cr).sum()]) / (6 * A)
    return poly, centre


def _ring(poly: np.ndarray, centre: np.ndarray, Q: int, z: float) -> np.ndarray:
    th, r = quarter_ring(lambda a: polar_radius(poly, centre, a), Q)
    xy = centre + r[:, None] * np.stack([np.cos(th), np.sin(th)], 1)
    return np.concatenate([xy, np.full((len(xy), 1), z)], 1)


def _perimeter(ring: np.ndarray) -> float:
    return float(np.linalg.norm(ring - np.roll(ring, -1, 0), axis=1).sum())


def _arc_samples(ts: np.ndarray, ys: np.ndarray, h: float, min_n: int = 1) -> np.ndarray:
    """Parameters ``t`` spaced ~``h`` apart along the polyline ``(ts, ys)``."""
    s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(ts), np.diff(ys)))])
    n = max(min_n, int(np.ceil(s[-1] / h)))
    return np.interp(np.linspace(0.0, s[-1], n + 1), s, ts)


def _armpit_z(fit: BodyFit, ease: float, margin: float) -> float:
    """Highest height whose torso ring (grown by ``ease``) clears both arms by a little
    more than ``margin`` (a deep armhole makes a big sleeve cap)."""
    need = max(margin + 0.003, 0.6 * ease)
    arms = fit.tree([L_ARM, R_ARM])
    top = min(fit.J["l_shoulder"][2], fit.J["r_shoulder"][2])
    bottom = fit.J["chest"][2] - 0.1 * fit.height / 1.75
    for z in np.arange(top, bottom, -0.005):
        poly, c = _section(fit, z - 0.02, z + 0.02, [TORSO], ease)
        ring = _ring(poly, c, 12, z)
        if arms.query(ring)[0].min() >= need:
            return float(z)
    return float(bottom)


def _crotch_z(fit: BodyFit, ease: float, margin: float, centre_x: float) -> float:
    """Highest level below the pelvis where a crotch seam fits between the legs."""
    allp = fit.tree(range(6))
    top = min(fit.J["l_hip"][2], fit.J["r_hip"][2])
    bottom = 0.25 * (fit.J["l_knee"][2] + fit.J["r_knee"][2] + fit.J["l_ankle"][2]
                     + fit.J["r_ankle"][2])
    z_floor = 0.5 * (fit.J["l_ankle"][2] + fit.J["r_ankle"][2])
    for z in np.arange(top, bottom, -0.005):
        # the legs must stay apart everywhere below the seam, not only at it
        band = fit.select([L_LEG], z_floor, z + 0.01)
        bandr = fit.select([R_LEG], z_floor, z + 0.01)
        if len(band) == 0 or len(bandr) == 0:
            continue
        gap_l = band[:, 0].min() - centre_x
        gap_r = centre_x - bandr[:, 0].max()
        if min(gap_l, gap_r) < margin + 0.004:
            continue
        poly, c = _section(fit, z - 0.02, z + 0.02, [TORSO, L_LEG, R_LEG], ease)
        ys = np.linspace(-1, 1, 21)
        r_b = polar_radius(poly, np.array([centre_x, c[1]]), np.array([np.pi / 2, -np.pi / 2]))
        seam = np.stack([np.full(21, centre_x), c[1] + 0.5 * (r_b[0] - r_b[1])
                         + 0.5 * (r_b[0] + r_b[1]) * ys, np.full(21, z)], 1)
        if allp.query(seam)[0].min() >= min(ease, margin + 0.004):
            return float(z)
    return float(bottom)


def _neck(fit: BodyFit):
    """``(z, radius, centre_xy)`` of the narrowest level between the neck and head joints."""
    c = fit.J["neck"][:2]
    best = None
    z0, z1 = fit.J["neck"][2] - 0.03, fit.J["head"][2] + 0.03
    for z in np.arange(z0, z1, 0.005):
        pts = fit.select([TORSO, HEAD], z - 0.005, z + 0.005)
        if len(pts) == 0:
            continue
        r = np.linalg.norm(pts[:, :2] - c, axis=1).max()
        if best is None or r < best[1]:
            best = (float(z), float(r))
    if best is None:
        best = (float(fit.J["neck"][2]), 0.06)
    return best[0], best[1], c


def _envelope(fit: BodyFit, O: np.ndarray, dirs: np.ndarray, labels, z_max: float,
              cone: float = 0.06) -> np.ndarray:
    """Largest extent of the body (``labels``, below ``z_max``) along rays from ``O``."""
    P = fit.select(labels, -np.inf, z_max) - O
    rho = np.linalg.norm(P, axis=1)
    ok = rho > 1e-9
    P, rho = P[ok], rho[ok]
    from scipy.spatial import cKDTree
    tree = cKDTree(P / rho[:, None])
    lists = tree.query_ball_point(dirs, 2 * np.sin(cone / 2))
    out = np.zeros(len(dirs))
    for k, lst in enumerate(lists):
        if lst:
            out[k] = (P[lst] @ dirs[k]).max()
    return out


def _inflate(fit: BodyFit, O: np.ndarray, P: np.ndarray, ease: float, labels,
             z_max: float) -> np.ndarray:
    """Move points outward along rays from ``O`` until they are ``ease`` beyond the body."""
    shape = P.shape
    P = P.reshape(-1, 3)
    d = P - O
    r = np.linalg.norm(d, axis=1)
    d = d / r[:, None]
    env = _envelope(fit, O, d, labels, z_max)
    r = np.maximum(r, env + ease)
    return (O + r[:, None] * d).reshape(shape)


def _length_z(fit: BodyFit, length: Length, z_top: float, what: str,
              presets: Dict[str, Callable[[BodyFit], float]]) -> float:
    if isinstance(length, str):
        if length not in presets:
            raise ValueError(f"`length`: unknown {what} length {length!r}; use one of "
                             f"{list(presets)} or metres")
        return float(presets[length](fit))
    L = float(length)
    if not np.isfinite(L) or L <= 0.05:
        raise ValueError(f"`length`: must be more than 0.05 m, got {length}")
    return z_top - L


def _lerp_j(fit, a, b, t):
    return 0.5 * ((1 - t) * (fit.J["l_" + a][2] + fit.J["r_" + a][2])
                  + t * (fit.J["l_" + b][2] + fit.J["r_" + b][2]))


SKIRT_LENGTHS = {
    "mini": lambda f: _lerp_j(f, "hip", "knee", 0.45),
    "knee": lambda f: _lerp_j(f, "knee", "ankle", 0.0) + 0.02,
    "midi": lambda f: _lerp_j(f, "knee", "ankle", 0.5),
    "long": lambda f: _lerp_j(f, "knee", "ankle", 0.85),
}
TROUSER_LENGTHS = {
    "shorts": lambda f: _lerp_j(f, "hip", "knee", 0.55),
    "knee": lambda f: _lerp_j(f, "knee", "ankle", 0.05),
    "capri": lambda f: _lerp_j(f, "knee", "ankle", 0.5),
    "long": lambda f: _lerp_j(f, "knee", "ankle", 0.9),
}


# ---------------------------------------------------------------------------------------
# parts
# ---------------------------------------------------------------------------------------
def _skirt_rings(fit: BodyFit, z_w: float, z_hem: float, flare: float, ease: float, h: float,
                 Q: Optional[int] = None):
    """Rings (hem first, waist last) of a stack of cones over the waist section.

    The waist section is scaled about its centre by a profile ``s(t)`` (``t`` = depth
    below the waist): the concave upper hull of what the hips/legs require and the
    flare line, made non-decreasing -- piecewise linear, so every strip is a frustum of
    a cone (exactly developable)."""
    poly, c = _section(fit, z_w - 0.03, z_w + 0.03, [TORSO], ease)
    dense = np.linspace(0, 2 * np.pi, 721)
    rw = polar_radius(poly, c, dense)
    rbar = rw.mean()
    L = z_w - z_hem
    pts = fit.select([TORSO, L_LEG, R_LEG], z_hem - 0.02, z_w)
    t = z_w - pts[:, 2]
    dxy = pts[:, :2] - c
    th = np.mod(np.arctan2(dxy[:, 1], dxy[:, 0]), 2 * np.pi)
    s_req = (np.linalg.norm(dxy, axis=1) + ease) / np.interp(th, dense, rw)
    keep = t > 1e-3
    cand_t = np.concatenate([[0.0], t[keep], np.linspace(0, L, 20)])
    cand_s = np.concatenate([[1.0], s_req[keep], 1.0 + flare / rbar * np.linspace(0, L, 20)])
    # bin by t to keep the hull small
    bins = np.clip((cand_t / max(L, 1e-6) * 200).astype(int), 0, 200)
    bs = np.full(201, -np.inf)
    np.maximum.at(bs, bins, cand_s)
    bt = np.linspace(0, L, 201)
    okb = np.isfinite(bs)
    bt, bs = bt[okb], bs[okb]
    bs[0] = max(bs[0], 1.0)
    # concave upper hull (monotone chain), then running max
    hull = []
    for p in zip(bt, bs):
        while len(hull) >= 2:
            (x1, y1), (x2, y2) = hull[-2], hull[-1]
            if (x2 - x1) * (p[1] - y1) - (y2 - y1) * (p[0] - x1) >= 0:
                hull.pop()
            else:
                break
        hull.append(p)
    ht, hs = np.array(hull).T
    if ht[0] > 0:
        ht, hs = np.concatenate([[0.0], ht]), np.concatenate([[1.0], hs])
    hs = np.maximum.accumulate(hs)
    if ht[-1] < L:
        ht, hs = np.append(ht, L), np.append(hs, hs[-1])
    hs[0] = 1.0
    ht, hs = _simplify_profile(ht, hs, 0.002 / rbar)
    if Q is None:
        Q = max(3, int(round(rbar * hs.mean() * 2 * np.pi / 4 / h)))
    ring_w = _ring(poly, c, Q, z_w)
    # ring depths spaced ~h along each straight piece of the slanted profile, the
    # profile's corners exactly on rings
    ts = [0.0]
    for k in range(len(ht) - 1):
        seg = np.hypot(ht[k + 1] - ht[k], rbar * (hs[k + 1] - hs[k]))
        n = max(1, int(round(seg / h)))
        ts += list(np.linspace(ht[k], ht[k + 1], n + 1)[1:])
    ts = np.array(ts)
    ss = np.interp(ts, ht, hs)
    rings = []
    for tk, sk in zip(ts[::-1], ss[::-1]):  # hem first
        xy = c + sk * (ring_w[:, :2] - c)
        rings.append(np.concatenate([xy, np.full((len(xy), 1), z_w - tk)], 1))
    # ring indices (hem first) where the profile bends: a seam between two cones
    corners = [len(ts) - 1 - int(np.argmin(np.abs(ts - t))) for t in ht[1:-1]]
    return np.stack(rings), Q, c, sorted(corners)


def _simplify_profile(t: np.ndarray, s: np.ndarray, tol: float):
    """Douglas-Peucker on the piecewise-linear profile (deviation in ``s`` units)."""
    keep = np.zeros(len(t), bool)
    keep[[0, -1]] = True
    stack = [(0, len(t) - 1)]
    while stack:
        a, b = stack.pop()
        if b <= a + 1:
            continue
        line = s[a] + (s[b] - s[a]) * (t[a + 1:b] - t[a]) / max(t[b] - t[a], 1e-12)
        dev = np.abs(s[a + 1:b] - line)
        k = int(np.argmax(dev))
        if dev[k] > tol:
            m = a + 1 + k
            keep[m] = True
            stack += [(a, m), (m, b)]
    return t[keep], s[keep]


def _torso_rings(fit: BodyFit, z_lo: float, z_hi: float, Q: int, h: float, ease: float,
                 labels, loose: bool, exclude_top: bool = False) -> np.ndarray:
    """Rings from ``z_lo`` up to ``z_hi`` of fitted body sections.  ``loose``: a ring
    encloses everything of the body between its height and ``z_hi`` (hangs straight down
    from the widest part above)."""
    n = max(1, int(np.ceil((z_hi - z_lo) / h)))
    zs = np.linspace(z_lo, z_hi, n + 1)
    if exclude_top:
        zs = zs[:-1]
    rings = []
    for z in zs:
        top = z_hi + 0.02 if loose else z + 0.025
        poly, c = _section(fit, z - 0.025, top, labels, ease)
        rings.append(_ring(poly, c, Q, z))
    return np.stack(rings)


def _tube_grid(B: MeshBuilder, rings_idx: np.ndarray, rings_pos: np.ndarray, panel: int,
               seam: int) -> None:
    """Closed tube from rings (rows bottom -> top, each CCW from above): outward normals,
    pattern cut at ring index ``seam``."""
    N = rings_idx.shape[1]
    order = (np.arange(N) + seam) % N
    idx = rings_idx[:, order]
    uv = grid_uv(rings_pos[:, order], centre_col=N // 2, wrap=True)
    B.grid(idx, uv, panel, wrap=True)


def _limb_frames(points: np.ndarray, s: np.ndarray):
    """Centres and unit tangents at arc positions ``s`` along a polyline."""
    seg = np.diff(points, axis=0)
    L = np.linalg.norm(seg, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(L)])
    s = np.asarray(s, dtype=np.float64)
    k = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(L) - 1)
    a = (s - cum[k]) / L[k]
    centres = points[k] + a[:, None] * seg[k]
    tang = seg[k] / L[k][:, None]
    return centres, tang


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    x, y, z = axis
    K = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * (K @ K)


def _loft_tube(fit: BodyFit, B: MeshBuilder, loop_idx: np.ndarray, path: np.ndarray,
               s_end: float, radius_fn: Callable[[np.ndarray, np.ndarray], np.ndarray],
               h: float, panel: int, offset_fn=None, pivot_gap: float = 0.03,
               morph: float = 0.08, hinge: float = 1.0) -> np.ndarray:
    """A tube from an existing closed vertex loop down a limb ``path``.

    1. *Hinge*: if the loop's plane is tilted with respect to the limb, the loop is
       rotated rigidly, ring by ring, about an axis outside the tube on the inner side of
       the bend (``pivot_gap`` beyond the loop) until its plane is perpendicular to the
       limb -- like a sleeve cap turning down from the armhole: the inner (underarm) side
       stays short, the outer side (the cap) takes the length, nothing folds.
    2. *Morph*: the rings then advance along the limb, their shape blending over
       ``morph`` metres from the (rotated) loop into circles of radius
       ``radius_fn(s, centres)`` about the limb axis, each vertex keeping its polar
       angle, so the tube neither twists nor pinches; circles continue to ``s_end``.
    Returns the grid of vertex indices (rows from the loop)."""
    P = B.positions()
    loop = P[loop_idx]
    M = len(loop)
    c0 = loop.mean(0)
    _, _, vt = np.linalg.svd(loop - c0)
    nL = vt[2]
    d = path[1] - path[0]
    d /= np.linalg.norm(d)
    if nL @ d < 0:
        nL = -nL
    theta = float(np.arccos(np.clip(nL @ d, -1, 1)))
    rings = []
    cur = loop
    if theta > np.radians(10):
        axis = np.cross(nL, d)
        axis /= np.linalg.norm(axis)
        inner = d - (d @ nL) * nL
        inner /= np.linalg.norm(inner)
        pivot = c0 + inner * (((loop - c0) @ inner).max() + pivot_gap)
        mean_r = np.linalg.norm((loop - pivot) - ((loop - pivot) @ axis)[:, None] * axis,
                                axis=1).mean()
        turn = hinge * theta  # the rest of the turn happens in the morph below
        n_b = max(2, int(np.ceil(mean_r * turn / h)))
        for i in range(1, n_b + 1):
            Rm = _rotation(axis, turn * i / n_b)
            rings.append(pivot + (loop - pivot) @ Rm.T)
        cur = rings[-1]
    # morph + circles along the limb
    ccur = cur.mean(0)
    seg = np.diff(path, axis=0)
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(seg, axis=1))])
    s_b = float(np.clip((ccur - path[0]) @ d, 0.0, cum[-1]))
    s_end = max(s_end, s_b + 2 * h)
    n_c = max(2, int(np.ceil((s_end - s_b) / h)))
    sc = np.linspace(s_b, s_end, n_c + 1)[1:]
    centres, tang = _limb_frames(path, sc)
    radii = radius_fn(sc, centres)
    rel = cur - ccur
    rel = rel - (rel @ d)[:, None] * d
    f1 = rel[0] / np.linalg.norm(rel[0])
    f2 = np.cross(d, f1)
    a_m, b_m = rel @ f1, rel @ f2
    sgn = 1.0
    psi = np.unwrap(np.arctan2(b_m, a_m))
    if psi[-1] < psi[0]:
        sgn, b_m = -1.0, -b_m
        psi = np.unwrap(np.arctan2(b_m, a_m))
    psi -= psi[0]
    along0 = (cur - ccur) @ d
    w = _smooth_step((sc - s_b) / max(morph, 1e-6))
    for i in range(len(sc)):
        t = tang[i]
        # transport the frame (rotation-minimising, by projection)
        f1 = f1 - (f1 @ t) * t
        f1 /= np.linalg.norm(f1)
        f2 = np.cross(t, f1)
        loop_part = (a_m[:, None] * f1 + sgn * b_m[:, None] * f2 + along0[:, None] * t)
        circ = radii[i] * (np.cos(psi)[:, None] * f1 + sgn * np.sin(psi)[:, None] * f2)
        # the loop's own centre drifts onto the limb axis as the morph proceeds
        lc = ccur + (sc[i] - s_b) * d
        ring = (1 - w[i]) * (lc + loop_part) + w[i] * (centres[i] + circ)
        if offset_fn is not None:
            ring = offset_fn(ring, centres[i], sc[i])
        rings.append(ring)
    new = np.stack(rings)
    idx = np.concatenate([loop_idx[None], B.add(new)], 0)
    allpos = np.concatenate([loop[None], new], 0)
    uv = grid_uv(allpos, centre_col=M // 2, wrap=True)
    B.grid(idx, uv, panel, wrap=True)
    return idx


def _upper_body(fit: BodyFit, B: MeshBuilder, ring_idx: np.ndarray, Q: int, h: float,
                ease: float, panels, stack_front=None, stack_back=None, neckline: str = "crew"):
    """Front and back panels from the armpit ring (last row of the stacks) up to the
    shoulder seams; returns the left and right armhole loops (vertex indices)."""
    P = B.positions()
    ring = P[ring_idx]
    z_a = ring[0, 2]
    cxy = ring[:, :2].mean(0)
    O = np.array([cxy[0], cxy[1], z_a - 0.05])
    C = 2 * Q
    front_cols = np.concatenate([np.arange(2 * Q, 4 * Q), [0]])  # right side -> CF -> left side
    back_cols = np.arange(0, 2 * Q + 1)  # left side -> CB -> right side
    z_neck, r_neck, nc = _neck(fit)
    # what the shoulders and neckline must clear: torso and neck up to the neck's
    # narrowest level (not the chin or jaw above it)
    z_head = min(fit.J["head"][2], z_neck + 0.01)
    labels = [TORSO, HEAD]
    X = r_neck + ease + (0.015 if neckline == "crew" else 0.04)
    depth_f = 0.05 if neckline == "crew" else 0.12
    depth_b = 0.015
    z_ns = z_neck - 0.01
    tips, nsides, arm_r = {}, {}, {}
    for s, sign in (("l", 1.0), ("r", -1.0)):
        sh, el = fit.J[f"{s}_shoulder"], fit.J[f"{s}_elbow"]
        lab = L_ARM if s == "l" else R_ARM
        arm_r[s] = float(fit.limb_radius(sh, el, lab, np.array([0.03]), 0.03)[0])
        tips[s] = sh + np.array([0.0, 0.0, arm_r[s] + ease])
        nsides[s] = np.array([nc[0] + sign * X, nc[1], z_ns])
    a = max(1, int(round(np.linalg.norm(tips["l"] - nsides["l"]) / h)))
    a = min(a, Q - 1)
    # top rows
    def top_front(k):
        if k <= a:
            return tips["r"] + (nsides["r"] - tips["r"]) * (k / a)
        if k >= C - a:
            return tips["l"] + (nsides["l"] - tips["l"]) * ((C - k) / a)
        phi = np.pi + np.pi * (k - a) / (C - 2 * a)
        return np.array([nc[0] + X * np.cos(phi), nc[1] + X * np.sin(phi),
                         z_ns - depth_f * abs(np.sin(phi))])

    def top_back(k):
        if k <= a:
            return tips["l"] + (nsides["l"] - tips["l"]) * (k / a)
        if k >= C - a:
            return tips["r"] + (nsides["r"] - tips["r"]) * ((C - k) / a)
        phi = np.pi * (k - a) / (C - 2 * a)
        return np.array([nc[0] + X * np.cos(phi), nc[1] + X * np.sin(phi),
                         z_ns - depth_b * abs(np.sin(phi))])

    Tf = np.stack([top_front(k) for k in range(C + 1)])
    Tb = np.stack([top_back(k) for k in range(C + 1)])
    Af, Ab = ring[front_cols], ring[back_cols]
    # rows: from the Bezier length of the centre column
    w = {s: 2.2 * (arm_r[s] + ease) for s in ("l", "r")}

    def bezier(A, T, yshift, R):
        K = np.stack([A[:, 0], A[:, 1] + yshift, T[:, 2]], 1)
        t = (np.arange(1, R + 1) / R)[:, None, None]
        return (1 - t) ** 2 * A + 2 * t * (1 - t) * K + t ** 2 * T

    probe = bezier(Af[Q:Q + 1], Tf[Q:Q + 1], np.zeros(1), 50)[:, 0]
    Lc = np.linalg.norm(np.diff(np.concatenate([Af[Q:Q + 1], probe]), axis=0), axis=1).sum()
    R = max(3, int(round(Lc / h)))
    k = np.arange(C + 1)
    # y shift of the control points: armhole edges go around the arm (front: -y)
    near_r = np.clip(1 - k / max(a, 1), 0, 1)  # front k=0 is the right edge
    near_l = np.clip(1 - (C - k) / max(a, 1), 0, 1)
    shift_f = -(w["r"] * near_r + w["l"] * near_l)
    near_l_b = np.clip(1 - k / max(a, 1), 0, 1)  # back k=0 is the left edge
    near_r_b = np.clip(1 - (C - k) / max(a, 1), 0, 1)
    shift_b = w["l"] * near_l_b + w["r"] * near_r_b
    Ff = bezier(Af, Tf, shift_f, R)  # [R, C+1, 3], last row = top
    Fb = bezier(Ab, Tb, shift_b, R)
    Ff = _inflate(fit, O, Ff, ease, labels, z_head)
    Fb = _inflate(fit, O, Fb, ease, labels, z_head)
    # shared shoulder-seam vertices: back top row = front top row mirrored at the seams
    for m in range(a + 1):
        Fb[-1, m] = Ff[-1, C - m]
        Fb[-1, C - m] = Ff[-1, m]
    idx_f = np.zeros((R, C + 1), dtype=np.int64)
    idx_b = np.zeros((R, C + 1), dtype=np.int64)
    idx_f[:] = B.add(Ff)
    idx_b[:-1] = B.add(Fb[:-1])
    top_b = B.add(Fb[-1, a + 1:C - a])
    idx_b[-1, a + 1:C - a] = top_b
    for m in range(a + 1):
        idx_b[-1, m] = idx_f[-1, C - m]
        idx_b[-1, C - m] = idx_f[-1, m]
    # grids: the stack rows below (front/back halves) + these rows
    for (stack, cols, idx_up, pos_up, panel) in (
            (stack_front, front_cols, idx_f, Ff, panels[0]),
            (stack_back, back_cols, idx_b, Fb, panels[1])):
        s_idx, s_pos = stack
        gi = np.concatenate([s_idx[:, cols], idx_up], 0)
        gp = np.concatenate([s_pos[:, cols], B.positions()[idx_up]], 0)
        B.grid(gi, grid_uv(gp, centre_col=Q), panel)
    # armhole loops: armpit, up the front edge, down the back edge
    loop_l = np.concatenate([[ring_idx[0]], idx_f[:, C], idx_b[-2::-1, 0]])
    loop_r = np.concatenate([[ring_idx[2 * Q]], idx_f[:, 0], idx_b[-2::-1, C]])
    return loop_l, loop_r


def _sleeve(fit: BodyFit, B: MeshBuilder, loop: np.ndarray, side: str, length: str, h: float,
            ease: float, panel: int) -> None:
    sh, el, wr = (fit.J[f"{side}_{j}"] for j in ("shoulder", "elbow", "wrist"))
    lab = L_ARM if side == "l" else R_ARM
    path = np.stack([sh, el, wr])
    Lu, Lf = np.linalg.norm(el - sh), np.linalg.norm(wr - el)
    along = (B.positions()[loop] - sh) @ ((el - sh) / Lu)
    s_end = {"short": max(0.5 * Lu, along.max() + 0.25 * Lu), "elbow": Lu + 0.1 * Lf,
             "long": Lu + 0.92 * Lf}[length]
    s_end = max(s_end, along.max() + 3 * h)
    t_u = np.linspace(0, Lu, 12)
    r_u = fit.limb_radius(sh, el, lab, t_u, 0.04)
    t_f = np.linspace(0, Lf, 12)
    r_f = fit.limb_radius(el, wr, lab, t_f, 0.04)
    ts = np.concatenate([t_u, Lu + t_f])
    rs = np.maximum.accumulate(np.concatenate([r_u, r_f])[::-1])[::-1]  # never narrower above

    def radius(s, centres):
        return np.interp(s, ts, rs) + ease

    _loft_tube(fit, B, loop, path, s_end, radius, h, panel, hinge=HINGE, morph=MORPH)


def _polyline_from_height(points: np.ndarray, z: float) -> np.ndarray:
    """The part of a downward polyline below height ``z`` (starting exactly at ``z``)."""
    for k in range(len(points) - 1):
        a, b = points[k], points[k + 1]
        if b[2] < z <= a[2] or (k == 0 and z > a[2]):
            t = np.clip((a[2] - z) / max(a[2] - b[2], 1e-9), 0.0, 1.0)
            start = a + t * (b - a)
            rest = points[k + 1:]
            if np.linalg.norm(rest[0] - start) < 1e-6:
                rest = rest[1:]
            return np.concatenate([start[None], rest])
    return points[-2:].copy()


def _legs(fit: BodyFit, B: MeshBuilder, ring_idx: np.ndarray, Q: int, z_c: float, z_hem: float,
          h: float, ease: float, panels, centre_x: float) -> None:
    P = B.positions()
    ring = P[ring_idx]
    fcp, bcp = ring[3 * Q], ring[Q]
    K = max(1, int(round(np.linalg.norm(fcp - bcp) / h)) - 1)
    t = np.linspace(0, 1, K + 2)[1:-1]
    seam = bcp + t[:, None] * (fcp - bcp)  # back -> front, at the centre line
    seam[:, 0] = centre_x
    seam_idx = B.add(seam)
    loops = {
        "l": np.concatenate([ring_idx[np.r_[3 * Q:4 * Q, 0:Q + 1]], seam_idx]),
        "r": np.concatenate([ring_idx[Q:3 * Q + 1], seam_idx[::-1]]),
    }
    for side, panel in zip(("l", "r"), panels):
        hp, kn, an = (fit.J[f"{side}_{j}"] for j in ("hip", "knee", "ankle"))
        lab = L_LEG if side == "l" else R_LEG
        # path: the leg axis from the crotch height down
        path = _polyline_from_height(np.stack([hp, kn, an]), z_c)
        cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
        s_end = float(np.interp(-z_hem, -path[:, 2], cum))
        s_grid = np.linspace(0, cum[-1], 24)
        cen, _ = _limb_frames(path, s_grid)
        rad = np.zeros(len(s_grid))
        Pl = fit.samples[(fit.label == lab) & fit.core]
        for k, (s, c) in enumerate(zip(s_grid, cen)):
            m = np.abs(Pl[:, 2] - c[2]) <= 0.04
            rad[k] = np.linalg.norm(Pl[m, :2] - c[:2], axis=1).max() if m.any() else rad[k - 1]
        rad = np.maximum.accumulate(rad[::-1])[::-1] * 0.3 + rad * 0.7
        sign = 1.0 if side == "l" else -1.0

        def radius(s, centres):
            return np.interp(s, s_grid, rad) + ease

        def offset(ringp, c, s, sign=sign):
            # keep the inner side of the leg tube off the centre plane
            inner = sign * (ringp[:, 0] - centre_x)
            lack = 0.003 - inner.min()
            if lack > 0:
                ringp = ringp + np.array([sign * lack, 0.0, 0.0])
            return ringp

        # rotate the loop so the pattern seam is the inseam (middle of the crotch seam)
        loop = loops[side]
        n = len(loop)
        start_i = n - K + K // 2 if K > 0 else 0
        loop = np.roll(loop, -start_i)
        # rings run down the leg, i.e. reversed w.r.t. the (CCW) loop for outward normals
        loop = loop[::-1]
        loop = np.roll(loop, 1)
        _loft_tube(fit, B, loop, path, s_end, radius, h, panel, offset_fn=offset)


# ---------------------------------------------------------------------------------------
# assembly
# ---------------------------------------------------------------------------------------
def _finish(fit: BodyFit, B: MeshBuilder, margin: float, kind: str, name: str,
            pinned: Optional[np.ndarray] = None, info: Optional[dict] = None) -> Garment:
    V, F, panel, init_uv, part = B.arrays()
    _orient(V, F, init_uv, part, fit)
    used = np.zeros(len(V), bool)
    used[F.reshape(-1)] = True
    if not used.all():  # should not happen; keep the mesh clean anyway
        remap = np.cumsum(used) - 1
        V, F = V[used], remap[F]
        if pinned is not None:
            pinned = pinned[used]
    V, moved = _place(fit, V, F, margin)
    uv, face_uv, _ = build_pattern(V, F, panel, init_uv)
    inf = dict(info or {})
    inf["pushed_vertices"] = moved
    return Garment(vertices=torch.tensor(V, dtype=torch.float32),
                   faces=torch.tensor(F, dtype=torch.long),
                   uv=torch.tensor(uv, dtype=torch.float32),
                   face_uv=torch.tensor(face_uv, dtype=torch.float32),
                   name=name, kind=kind,
                   pinned=None if pinned is None else torch.tensor(pinned),
                   panel=torch.tensor(panel, dtype=torch.long), info=inf)


def _orient(V, F, init_uv, part, fit: BodyFit) -> None:
    """Make the winding consistent across parts (a part sharing an edge with an earlier
    part in the same direction is flipped), then make the normals point away from the
    body overall.  In place."""
    done: Dict[tuple, int] = {}
    for p in np.unique(part):
        m = np.nonzero(part == p)[0]
        E = np.concatenate([F[m][:, [0, 1]], F[m][:, [1, 2]], F[m][:, [2, 0]]])
        same = sum(1 for e in map(tuple, E) if e in done)
        opp = sum(1 for e in E[:, ::-1] if tuple(e) in done)
        if same > opp:
            F[m] = F[m][:, ::-1]
            init_uv[m] = init_uv[m][:, ::-1]
            E = E[:, ::-1]
        for e in map(tuple, E):
            done[e] = p
    cen = V[F].mean(1)
    nrm = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    _, near = fit.tree(range(6)).query(cen)
    if np.einsum("ij,ij->i", nrm, cen - fit.samples[near]).sum() < 0:
        F[:] = F[:, ::-1]
        init_uv[:] = init_uv[:, ::-1]


def _place(fit: BodyFit, V: np.ndarray, F: np.ndarray, margin: float, rounds: int = 3):
    """Push vertices out to ``margin`` from the body; pushed vertices are then relaxed
    towards their neighbours (removes kinks and vertices pushed onto one spot) and the
    push repeated."""
    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    E = np.concatenate([E, E[:, ::-1]])
    deg = np.bincount(E[:, 0], minlength=len(V)).astype(np.float64)
    ever = np.zeros(len(V), bool)
    for r in range(rounds):
        V2, _ = fit.dist.push_out(V, margin)
        moved = np.linalg.norm(V2 - V, axis=1) > 0
        V = V2
        ever |= moved
        if not moved.any() or r == rounds - 1:
            break
        # relax the pushed vertices and their neighbours a little
        zone = moved.copy()
        zone[E[np.isin(E[:, 0], np.nonzero(moved)[0]), 1]] = True
        avg = np.zeros_like(V)
        np.add.at(avg, E[:, 0], V[E[:, 1]])
        avg /= np.maximum(deg, 1)[:, None]
        V[zone] = 0.5 * V[zone] + 0.5 * avg[zone]
    return V, int(ever.sum())


def _at_resolution(build: Callable[[float], MeshBuilder], target: int):
    h0 = 0.05
    b = build(h0)
    h = h0 * np.sqrt(b.n / target)
    for _ in range(2):
        b = build(h)
        ratio = b.n / target
        if abs(ratio - 1) < 0.08:
            break
        h *= np.sqrt(ratio)
    return b, h


def _flare_value(flare) -> float:
    if isinstance(flare, str):
        if flare not in FLARES:
            raise ValueError(f"`flare`: unknown preset {flare!r}; use one of {list(FLARES)} "
                             "or a non-negative number (radius growth per metre of length)")
        return FLARES[flare]
    f = float(flare)
    if not np.isfinite(f) or f < 0:
        raise ValueError(f"`flare`: must be >= 0, got {flare}")
    return f


def skirt(body, length: Length = "knee", flare: Union[str, float] = "a-line",
          resolution: Union[str, int] = "medium", ease: float = 0.02, margin: float = 0.01,
          name: str = "skirt") -> Garment:
    """A skirt hanging from the natural waist.

    Args:
        body: a rest :class:`~garmentgnn.body.Body` with the standard roles.
        length: ``"mini" | "knee" | "midi" | "long"`` (hem height from the leg joints) or
            metres from the waist down.
        flare: ``"pencil"/"straight" (0) | "a-line" (0.25) | "flared" (0.5) | "full" (0.9)``
            or a number: growth of the radius per metre of length; the skirt is always at
            least as wide as the hips/legs need (plus ``ease``).
        resolution: see the module doc.
        ease: room between body and garment by design (metres).
        margin: minimum clearance enforced after building (metres).

    The waistband ring is ``pinned``.
    """
    _check_common(ease, margin)
    fit = BodyFit.of(body)
    f = _flare_value(flare)
    z_w = _waist_z(fit)
    z_hem = _length_z(fit, length, z_w, "skirt", SKIRT_LENGTHS)
    if z_hem >= z_w - 0.05:
        raise ValueError(f"`length`: hem at {z_hem:.3f} m is not below the waist ({z_w:.3f} m)")
    top_n = {}

    def build(h):
        B = MeshBuilder()
        rings, Q, _, corners = _skirt_rings(fit, z_w, z_hem, f, ease, h)
        idx = B.add(rings)
        # one panel per cone of the profile (a yoke above the hips, the skirt below),
        # each cut at the centre back
        cuts = [0] + corners + [len(rings) - 1]
        for p, (a, b) in enumerate(zip(cuts[:-1], cuts[1:])):
            _tube_grid(B, idx[a:b + 1], rings[a:b + 1], p, seam=Q)
        top_n["top"] = idx[-1]
        return B

    B, h = _at_resolution(build, _target(resolution))
    pinned = np.zeros(B.n, bool)
    pinned[top_n["top"]] = True
    return _finish(fit, B, margin, "skirt", name, pinned,
                   {"spacing": h, "waist_z": z_w, "hem_z": z_hem, "flare": f})


def trousers(body, length: Length = "long", resolution: Union[str, int] = "medium",
             ease: float = 0.02, margin: float = 0.01, name: str = "trousers") -> Garment:
    """Trousers: a waist tube down to the crotch, where its last ring splits (the crotch
    seam) into the two leg openings, then one tube per leg.

    ``length``: ``"shorts" | "knee" | "capri" | "long"`` or metres from the waist.  The
    crotch is placed at the highest level where a seam fits between the legs with
    ``margin`` (on bodies whose thighs touch, that is low: the garment stays
    collision-free rather than pretending).  The waistband ring is ``pinned``.
    """
    _check_common(ease, margin)
    fit = BodyFit.of(body)
    z_w = _waist_z(fit)
    z_hem = _length_z(fit, length, z_w, "trouser", TROUSER_LENGTHS)
    cx = float(fit.J["pelvis"][0])
    z_c = _crotch_z(fit, ease, margin, cx)
    if z_hem >= z_c - 0.05:
        raise ValueError(f"`length`: hem at {z_hem:.3f} m is not below the crotch "
                         f"({z_c:.3f} m) on this body")
    top_n = {}

    def build(h):
        B = MeshBuilder()
        poly, c = _section(fit, z_w - 0.03, z_w + 0.03, [TORSO], ease)
        Q = max(3, int(round(_perimeter(_ring(poly, c, 8, z_w)) / 4 / h)))
        rings = _torso_rings(fit, z_c, z_w, Q, h, ease, [TORSO, L_LEG, R_LEG], loose=False)
        # a waist tube must not narrow downwards (it would cut under the buttocks)
        rings = _monotone_down(rings)
        idx = B.add(rings)
        _tube_grid(B, idx, rings, 0, seam=Q)
        _legs(fit, B, idx[0], Q, z_c, z_hem, h, ease, (1, 2), cx)
        top_n["top"] = idx[-1]
        return B

    B, h = _at_resolution(build, _target(resolution))
    pinned = np.zeros(B.n, bool)
    pinned[top_n["top"]] = True
    return _finish(fit, B, margin, "trousers", name, pinned,
                   {"spacing": h, "waist_z": z_w, "crotch_z": z_c, "hem_z": z_hem})


def _monotone_down(rings: np.ndarray) -> np.ndarray:
    """Make each ring (bottom first) at least as wide, per column and about its centre,
    as the ring above it."""
    out = rings.copy()
    for j in range(len(out) - 2, -1, -1):
        c = out[j, :, :2].mean(0)
        ca = out[j + 1, :, :2].mean(0)
        r = np.linalg.norm(out[j, :, :2] - c, axis=1)
        ra = np.linalg.norm(out[j + 1, :, :2] - ca, axis=1)
        s = np.maximum(r, ra) / np.maximum(r, 1e-9)
        out[j, :, :2] = c + (out[j, :, :2] - c) * s[:, None]
    return out


def tshirt(body, sleeves: str = "short", length: Length = "hip", neckline: str = "crew",
           resolution: Union[str, int] = "medium", ease: float = 0.02, margin: float = 0.01,
           name: str = "tshirt") -> Garment:
    """A T-shirt: a torso tube from the hem up to the armpits, front and back panels up to
    the shoulder seams (neck hole between them), sleeves sewn into the armholes.

    Args:
        sleeves: ``"short" | "elbow" | "long" | "none"`` (``"none"``: a tank top).
        length: ``"hip"`` (just below the hip joints), ``"waist"`` or metres below the
            armpit.
        neckline: ``"crew" | "scoop"``.
    """
    return _top(body, "tshirt", sleeves, length, neckline, resolution, ease, margin, name)


def _top(body, kind, sleeves, length, neckline, resolution, ease, margin, name,
         bottom: str = "hem", legs_length: Length = "long", skirt_args=None):
    _check_common(ease, margin)
    if sleeves not in SLEEVES:
        raise ValueError(f"`sleeves`: use one of {SLEEVES}, got {sleeves!r}")
    if neckline not in ("crew", "scoop"):
        raise ValueError(f"`neckline`: use 'crew' or 'scoop', got {neckline!r}")
    fit = BodyFit.of(body)
    z_a = _armpit_z(fit, ease, margin)
    z_w = _waist_z(fit)
    cx = float(fit.J["pelvis"][0])
    info = {"armpit_z": z_a}
    if bottom == "hem":
        presets = {"hip": lambda f: min(f.J["l_hip"][2], f.J["r_hip"][2]) - 0.03,
                   "waist": lambda f: _waist_z(f)}
        z_lo = _length_z(fit, length, z_a, "top", presets)
        if z_lo >= z_a - 0.05:
            raise ValueError(f"`length`: hem at {z_lo:.3f} m is not below the armpits")
    elif bottom == "legs":
        z_lo = _crotch_z(fit, ease, margin, cx)
        z_hem = _length_z(fit, legs_length, z_w, "trouser", TROUSER_LENGTHS)
        if z_hem >= z_lo - 0.05:
            raise ValueError(f"`length`: hem at {z_hem:.3f} m is not below the crotch")
        info.update(crotch_z=z_lo, hem_z=z_hem)
    else:  # skirt below the waist (dress)
        z_lo = z_w
    info["bottom_z"] = z_lo

    def build(h):
        B = MeshBuilder()
        poly, c = _section(fit, z_a - 0.03, z_a + 0.02, [TORSO], ease)
        Q = max(4, int(round(_perimeter(_ring(poly, c, 8, z_a)) / 4 / h)))
        if bottom == "skirt":
            z_hem, f = skirt_args
            srings, _, _, _ = _skirt_rings(fit, z_w, z_hem, f, ease, h, Q=Q)
            upper = _torso_rings(fit, z_w, z_a, Q, h, ease, [TORSO], loose=False)
            rings = np.concatenate([srings[:-1], upper], 0)
        else:
            labels = [TORSO, L_LEG, R_LEG] if bottom == "legs" else [TORSO]
            rings = _torso_rings(fit, z_lo, z_a, Q, h, ease, labels, loose=(bottom == "hem"))
            if bottom == "legs":
                rings = _monotone_down(rings)
        idx = B.add(rings)
        loops = _upper_body(fit, B, idx[-1], Q, h, ease, (0, 1), (idx, rings), (idx, rings),
                            neckline)
        if sleeves != "none":
            _sleeve(fit, B, loops[0], "l", sleeves, h, ease, 2)
            _sleeve(fit, B, loops[1], "r", sleeves, h, ease, 3)
        if bottom == "legs":
            _legs(fit, B, idx[0], Q, z_lo, info["hem_z"], h, ease, (4, 5), cx)
        return B

    B, h = _at_resolution(build, _target(resolution))
    info["spacing"] = h
    return _finish(fit, B, margin, kind, name, None, info)


def dress(body, length: Length = "knee", flare: Union[str, float] = "a-line",
          top: str = "straps", sleeves: str = "none", neckline: str = "scoop",
          resolution: Union[str, int] = "medium", ease: float = 0.02, margin: float = 0.01,
          name: str = "dress") -> Garment:
    """A dress: a fitted bodice from the armpits to the waist, continued by a skirt (as in
    :func:`skirt`) below.

    Args:
        top: ``"straps"`` (two shoulder straps), ``"strapless"`` or ``"sleeveless"``
            (front/back panels up to the shoulders, like a T-shirt; then ``sleeves`` may
            add sleeves).
        length, flare: as for :func:`skirt`.
    """
    _check_common(ease, margin)
    if top not in ("straps", "strapless", "sleeveless"):
        raise ValueError(f"`top`: use 'straps', 'strapless' or 'sleeveless', got {top!r}")
    fit = BodyFit.of(body)
    f = _flare_value(flare)
    z_w = _waist_z(fit)
    z_hem = _length_z(fit, length, z_w, "skirt", SKIRT_LENGTHS)
    if z_hem >= z_w - 0.05:
        raise ValueError(f"`length`: hem at {z_hem:.3f} m is not below the waist ({z_w:.3f} m)")
    if top == "sleeveless":
        return _top(body, "dress", sleeves, None, neckline, resolution, ease, margin, name,
                    bottom="skirt", skirt_args=(z_hem, f))
    if sleeves != "none":
        raise ValueError("`sleeves`: only a 'sleeveless' top can have sleeves")
    z_a = _armpit_z(fit, ease, margin)

    def build(h):
        B = MeshBuilder()
        poly, c = _section(fit, z_a - 0.03, z_a + 0.02, [TORSO], ease)
        Q = max(4, int(round(_perimeter(_ring(poly, c, 8, z_a)) / 4 / h)))
        Q += Q % 2
        srings, _, _, corners = _skirt_rings(fit, z_w, z_hem, f, ease, h, Q=Q)
        upper = _torso_rings(fit, z_w, z_a, Q, h, ease, [TORSO], loose=False)
        rings = np.concatenate([srings[:-1], upper], 0)
        idx = B.add(rings)
        # panels: the skirt's cones (as in `skirt`), the bodice; cut at the centre back
        cuts = [0] + corners + [len(srings) - 1, len(rings) - 1]
        for p, (a, b) in enumerate(zip(cuts[:-1], cuts[1:])):
            _tube_grid(B, idx[a:b + 1], rings[a:b + 1], p, seam=Q)
        if top == "straps":
            _straps(fit, B, idx[-1], Q, h, ease, (len(cuts) - 1, len(cuts)))
        return B

    B, h = _at_resolution(build, _target(resolution))
    return _finish(fit, B, margin, "dress", name, None,
                   {"spacing": h, "waist_z": z_w, "hem_z": z_hem, "armpit_z": z_a})


def _straps(fit: BodyFit, B: MeshBuilder, ring_idx: np.ndarray, Q: int, h: float, ease: float,
            panels, width: float = 0.035) -> None:
    """Two straps from the front edge of the bodice over the shoulders to the back edge."""
    P = B.positions()
    ring = P[ring_idx]
    z_a = ring[0, 2]
    cxy = ring[:, :2].mean(0)
    O = np.array([cxy[0], cxy[1], z_a - 0.05])
    z_head = min(fit.J["head"][2], _neck(fit)[0] + 0.01)
    N = 4 * Q
    W = max(1, int(round(width / h)))
    for side, sign, panel in (("l", 1.0, panels[0]), ("r", -1.0, panels[1])):
        sh = fit.J[f"{side}_shoulder"]
        xs = cxy[0] + sign * 0.55 * abs(sh[0] - cxy[0])  # strap centre line
        # front ring columns (indices 2Q..4Q) and back (0..2Q) closest to x = xs
        fr = np.arange(2 * Q, 4 * Q)
        bk = np.arange(0, 2 * Q)
        f0 = fr[np.argmin(np.abs(ring[fr, 0] - xs))]
        b0 = bk[np.argmin(np.abs(ring[bk, 0] - xs))]
        # front columns go +x with the index, back columns go -x
        fcols = (f0 - W // 2 + np.arange(W + 1)) % N
        bcols = (b0 + W // 2 - np.arange(W + 1)) % N
        A, Z = ring[fcols], ring[bcols]
        top_z = fit.select([TORSO], -np.inf, z_head)
        near = top_z[np.abs(top_z[:, 0] - xs) < 0.02]
        zt = (near[:, 2].max() if len(near) else sh[2]) + ease
        T = np.stack([np.full(W + 1, 0.0), np.full(W + 1, 0.0), np.full(W + 1, zt)], 1)
        T[:, :2] = 0.5 * (A[:, :2] + Z[:, :2])
        # path: front edge -> over the top -> back edge, a quadratic Bezier each half
        Lh = np.linalg.norm(T[0] - A[0]) + np.linalg.norm(Z[0] - T[0])
        S = max(4, int(round(1.3 * Lh / h)))
        t = np.linspace(0, 1, S + 1)[1:-1]
        K1 = np.stack([A[:, 0], A[:, 1], T[:, 2]], 1)
        K2 = np.stack([Z[:, 0], Z[:, 1], T[:, 2]], 1)
        # cubic Bezier A -> K1 -> K2 -> Z
        tt = t[:, None, None]
        pts = ((1 - tt) ** 3 * A + 3 * (1 - tt) ** 2 * tt * K1 + 3 * (1 - tt) * tt ** 2 * K2
               + tt ** 3 * Z)
        pts = _inflate(fit, O, pts, ease, [TORSO, HEAD], z_head)
        mid = B.add(pts)
        gi = np.concatenate([ring_idx[fcols][None], mid, ring_idx[bcols][None]], 0)
        gp = np.concatenate([A[None], pts, Z[None]], 0)
        B.grid(gi, grid_uv(gp, centre_col=W // 2), panel)


def jumpsuit(body, length: Length = "long", sleeves: str = "short",
             resolution: Union[str, int] = "medium", ease: float = 0.02, margin: float = 0.01,
             name: str = "jumpsuit") -> Garment:
    """A jumpsuit: the top of :func:`tshirt` (``sleeves`` may be ``"none"``) whose torso
    tube continues down to the crotch and splits into the legs of :func:`trousers`."""
    return _top(body, "jumpsuit", sleeves, None, "crew", resolution, ease, margin, name,
                bottom="legs", legs_length=length)


TEMPLATES = {"skirt": skirt, "dress": dress, "tshirt": tshirt, "trousers": trousers,
             "jumpsuit": jumpsuit}


def make_garment(kind: str, body, **kwargs) -> Garment:
    """Build a template by name (``TEMPLATES``)."""
    if kind not in TEMPLATES:
        raise ValueError(f"`kind`: unknown garment {kind!r}; use one of {list(TEMPLATES)}")
    return TEMPLATES[kind](body, **kwargs)
