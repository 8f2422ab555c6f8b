"""Body measurements for the garment templates (:mod:`garmentgnn.garments.templates`):
horizontal sections of the torso, the armpit / crotch / neck heights, inflated envelopes
and the garment length presets."""
from __future__ import annotations

from typing import Callable, Dict, Union

import numpy as np
from scipy.spatial import cKDTree

from garmentgnn.garments._fit import (HEAD, L_ARM, L_LEG, R_ARM, R_LEG, TORSO, BodyFit,
                                      hull_polygon, polar_radius, quarter_ring)

Length = Union[str, float]


def waist_height(fit: BodyFit) -> float:
    return float(fit.J["pelvis"][2] + 0.35 * (fit.J["chest"][2] - fit.J["pelvis"][2]))


def torso_section(fit: BodyFit, z_lo: float, z_hi: float, labels, ease: float):
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


def section_ring(poly: np.ndarray, centre: np.ndarray, Q: int, z: float) -> np.ndarray:
    th, r = quarter_ring(lambda a: polar_radius(poly, centre, a), Q)
    xy = centre + r[:, None] * np.stack([np.cos(th), np.sin(th)], 1)
    return np.concatenate([xy, np.full((len(xy), 1), z)], 1)


def ring_perimeter(ring: np.ndarray) -> float:
    return float(np.linalg.norm(ring - np.roll(ring, -1, 0), axis=1).sum())


def armpit_height(fit: BodyFit, ease: float, margin: float) -> float:
    """Highest height whose torso ring (grown by ``ease``) clears both arms by a little
    more than ``margin`` (a deep armhole makes a big sleeve cap)."""
    need = max(margin + 0.003, 0.6 * ease)
    arms = fit.tree([L_ARM, R_ARM])
    top = min(fit.J["l_shoulder"][2], fit.J["r_shoulder"][2])
    bottom = fit.J["chest"][2] - 0.1 * fit.height / 1.75
    for z in np.arange(top, bottom, -0.005):
        poly, c = torso_section(fit, z - 0.02, z + 0.02, [TORSO], ease)
        ring = section_ring(poly, c, 12, z)
        if arms.query(ring)[0].min() >= need:
            return float(z)
    return float(bottom)


def crotch_height(fit: BodyFit, ease: float, margin: float, centre_x: float) -> float:
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
        poly, c = torso_section(fit, z - 0.02, z + 0.02, [TORSO, L_LEG, R_LEG], ease)
        ys = np.linspace(-1, 1, 21)
        r_b = polar_radius(poly, np.array([centre_x, c[1]]), np.array([np.pi / 2, -np.pi / 2]))
        seam = np.stack([np.full(21, centre_x), c[1] + 0.5 * (r_b[0] - r_b[1])
                         + 0.5 * (r_b[0] + r_b[1]) * ys, np.full(21, z)], 1)
        if allp.query(seam)[0].min() >= min(ease, margin + 0.004):
            return float(z)
    return float(bottom)


def neck_level(fit: BodyFit):
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


def _envelope(fit: BodyFit, O: np.ndarray, dirs: np.ndarray, labels, z_max: float,  # noqa: E741
              cone: float = 0.06) -> np.ndarray:
    """Largest extent of the body (``labels``, below ``z_max``) along rays from ``O``."""
    P = fit.select(labels, -np.inf, z_max) - O
    rho = np.linalg.norm(P, axis=1)
    ok = rho > 1e-9
    P, rho = P[ok], rho[ok]
    tree = cKDTree(P / rho[:, None])
    lists = tree.query_ball_point(dirs, 2 * np.sin(cone / 2))
    out = np.zeros(len(dirs))
    for k, lst in enumerate(lists):
        if lst:
            out[k] = (P[lst] @ dirs[k]).max()
    return out


def inflate_envelope(fit: BodyFit, O: np.ndarray, P: np.ndarray, ease: float, labels,  # noqa: E741
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


def hem_height(fit: BodyFit, length: Length, z_top: float, what: str,
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
