"""Pattern construction for the garment templates (:mod:`garmentgnn.garments.templates`):
each part -- skirt cones, torso tubes, the upper body with its armholes and neck, sleeves,
legs, straps -- is added to a :class:`~garmentgnn.garments._fit.MeshBuilder` as
structured quad strips sharing their seam vertices."""
from __future__ import annotations

from typing import Callable, Optional

import numpy as np

from garmentgnn.garments._fit import (HEAD, L_ARM, L_LEG, R_ARM, R_LEG, TORSO, BodyFit,
                                      MeshBuilder, grid_uv, polar_radius)
from garmentgnn.garments._measure import inflate_envelope, neck_level, section_ring, torso_section

#: sleeves: fraction of the armhole-to-arm turn done by rotating the armhole loop (the
#: rest happens while its shape morphs into the sleeve's circles over MORPH metres)
HINGE, MORPH = 0.5, 0.12


def _smooth_step(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)



def skirt_rings(fit: BodyFit, z_w: float, z_hem: float, flare: float, ease: float, h: float,
                 Q: Optional[int] = None):
    """Rings (hem first, waist last) of a stack of cones over the waist section.

    The waist section is scaled about its centre by a profile ``s(t)`` (``t`` = depth
    below the waist): the concave upper hull of what the hips/legs require and the
    flare line, made non-decreasing -- piecewise linear, so every strip is a frustum of
    a cone (exactly developable)."""
    poly, c = torso_section(fit, z_w - 0.03, z_w + 0.03, [TORSO], ease)
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
    ring_w = section_ring(poly, c, Q, z_w)
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


def torso_rings(fit: BodyFit, z_lo: float, z_hi: float, Q: int, h: float, ease: float,
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
        poly, c = torso_section(fit, z - 0.025, top, labels, ease)
        rings.append(section_ring(poly, c, Q, z))
    return np.stack(rings)


def tube_grid(B: MeshBuilder, rings_idx: np.ndarray, rings_pos: np.ndarray, panel: int,
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


def add_upper_body(fit: BodyFit, B: MeshBuilder, ring_idx: np.ndarray, Q: int, h: float,
                ease: float, panels, stack_front=None, stack_back=None, neckline: str = "crew"):
    """Front and back panels from the armpit ring (last row of the stacks) up to the
    shoulder seams; returns the left and right armhole loops (vertex indices)."""
    P = B.positions()
    ring = P[ring_idx]
    z_a = ring[0, 2]
    cxy = ring[:, :2].mean(0)
    O = np.array([cxy[0], cxy[1], z_a - 0.05])  # noqa: E741
    C = 2 * Q
    front_cols = np.concatenate([np.arange(2 * Q, 4 * Q), [0]])  # right side -> CF -> left side
    back_cols = np.arange(0, 2 * Q + 1)  # left side -> CB -> right side
    z_neck, r_neck, nc = neck_level(fit)
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
    Ff = inflate_envelope(fit, O, Ff, ease, labels, z_head)
    Fb = inflate_envelope(fit, O, Fb, ease, labels, z_head)
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


def add_sleeve(fit: BodyFit, B: MeshBuilder, loop: np.ndarray, side: str, length: str, h: float,
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


def add_legs(fit: BodyFit, B: MeshBuilder, ring_idx: np.ndarray, Q: int, z_c: float, z_hem: float,
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



def add_straps(fit: BodyFit, B: MeshBuilder, ring_idx: np.ndarray, Q: int, h: float, ease: float,
            panels, width: float = 0.035) -> None:
    """Two straps from the front edge of the bodice over the shoulders to the back edge."""
    P = B.positions()
    ring = P[ring_idx]
    z_a = ring[0, 2]
    cxy = ring[:, :2].mean(0)
    O = np.array([cxy[0], cxy[1], z_a - 0.05])  # noqa: E741
    z_head = min(fit.J["head"][2], neck_level(fit)[0] + 0.01)
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
        pts = inflate_envelope(fit, O, pts, ease, [TORSO, HEAD], z_head)
        mid = B.add(pts)
        gi = np.concatenate([ring_idx[fcols][None], mid, ring_idx[bcols][None]], 0)
        gp = np.concatenate([A[None], pts, Z[None]], 0)
        B.grid(gi, grid_uv(gp, centre_col=W // 2), panel)
