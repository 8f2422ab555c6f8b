"""Body measurements for sizing garments, and a small structured-mesh builder."""
from __future__ import annotations

import weakref
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
from scipy.spatial import ConvexHull, cKDTree

from garmentgnn.garments._distance import BodyDistance

TORSO, HEAD, L_ARM, R_ARM, L_LEG, R_LEG = range(6)
REQUIRED_ROLES = ("pelvis", "spine", "chest", "neck", "l_hip", "l_knee", "l_ankle", "r_hip",
                  "r_knee", "r_ankle", "l_shoulder", "l_elbow", "l_wrist", "r_shoulder",
                  "r_elbow", "r_wrist")

_CACHE: Dict[int, "BodyFit"] = {}


class BodyFit:
    """What the templates need to know about a rest body.

    * ``J[role]``: joint positions (float64) by semantic role;
    * ``samples`` / ``label``: points covering the body surface (spacing <= ``h``), each
      labelled with the body part whose bone is nearest (torso, head+neck, arms, legs);
    * ``dist``: exact distance to the body mesh (see :mod:`._distance`).
    """

    def __init__(self, body, h: float = 0.01) -> None:
        roles = body.skeleton.roles
        missing = [r for r in REQUIRED_ROLES if r not in roles]
        if missing:
            raise ValueError(f"`body`: the skeleton lacks the role(s) {missing} the garment "
                             f"templates need to measure the body")
        J = body.joints.detach().double().cpu().numpy()
        self.J = {r: J[body.skeleton.index(r)] for r in roles}
        if "head" not in self.J:
            self.J["head"] = self.J["neck"] + np.array([0.0, 0.0, 0.1])
        V = body.vertices.detach().double().cpu().numpy()
        F = body.faces.detach().cpu().numpy().astype(np.int64)
        self.vertices, self.faces = V, F
        self.dist = BodyDistance(V, F, h)
        self.samples = self.dist.samples
        self.height = float(V[:, 2].max() - V[:, 2].min())
        self.label = self._labels()
        self._trees: Dict[tuple, cKDTree] = {}
        self._z_order = np.argsort(self.samples[:, 2])
        self._z_sorted = self.samples[self._z_order, 2]

    @classmethod
    def of(cls, body) -> "BodyFit":
        key = id(body)
        fit = _CACHE.get(key)
        if fit is None or fit._body() is not body:
            fit = cls(body)
            fit._body = weakref.ref(body)
            _CACHE[key] = fit
            weakref.finalize(body, _CACHE.pop, key, None)
        return fit

    # -- segmentation ------------------------------------------------------------------
    def bones(self) -> List[Tuple[np.ndarray, np.ndarray, int, bool]]:
        """``(start, end, label, extension)`` per bone; extension bones (past the head
        joint, the wrists and the ankles) stand for the top of the head, hands and feet."""
        J = self.J
        out = [(J["pelvis"], J["spine"], TORSO, False), (J["spine"], J["chest"], TORSO, False),
               (J["chest"], J["neck"], TORSO, False), (J["pelvis"], J["l_hip"], TORSO, False),
               (J["pelvis"], J["r_hip"], TORSO, False), (J["neck"], J["head"], HEAD, False),
               (J["head"], 2 * J["head"] - J["neck"], HEAD, True)]
        for s, lab in (("l", L_ARM), ("r", R_ARM)):
            sh, el, wr = J[f"{s}_shoulder"], J[f"{s}_elbow"], J[f"{s}_wrist"]
            out += [(sh, el, lab, False), (el, wr, lab, False),
                    (wr, wr + 0.45 * (wr - el), lab, True)]
        for s, lab in (("l", L_LEG), ("r", R_LEG)):
            hp, kn, an = J[f"{s}_hip"], J[f"{s}_knee"], J[f"{s}_ankle"]
            foot = an + np.array([0.0, -0.12, -0.05]) * self.height / 1.75
            out += [(hp, kn, lab, False), (kn, an, lab, False), (an, foot, lab, True)]
        return out

    def _labels(self) -> np.ndarray:
        """Nearest bone, measured as distance minus the bone's typical radius (the median
        distance of the samples nearest to it), so the torso's surface next to the
        shoulder is not taken for the arm whose bone happens to be closer.  Also sets
        ``core``: False for samples of the hands, feet and top of the head (limb radii
        ignore them)."""
        P = self.samples
        bones = self.bones()
        D = np.stack([_point_segment_distance(P, a, b) for a, b, _, _ in bones], 1)
        near = D.argmin(1)
        radius = np.array([np.median(D[near == k, k]) if (near == k).any() else 0.0
                           for k in range(len(bones))])
        near = (D - radius).argmin(1)
        self.core = ~np.array([e for _, _, _, e in bones])[near]
        return np.array([label for _, _, label, _ in bones])[near]

    # -- queries -----------------------------------------------------------------------
    def select(self, labels: Sequence[int], z_lo: float = -np.inf, z_hi: float = np.inf
               ) -> np.ndarray:
        """Samples with one of ``labels`` and ``z_lo <= z <= z_hi``."""
        i0 = np.searchsorted(self._z_sorted, z_lo, side="left")
        i1 = np.searchsorted(self._z_sorted, z_hi, side="right")
        idx = self._z_order[i0:i1]
        idx = idx[np.isin(self.label[idx], list(labels))]
        return self.samples[idx]

    def tree(self, labels: Sequence[int]) -> cKDTree:
        key = tuple(sorted(labels))
        if key not in self._trees:
            self._trees[key] = cKDTree(self.samples[np.isin(self.label, list(key))])
        return self._trees[key]

    def limb_radius(self, a: np.ndarray, b: np.ndarray, label: int, t: np.ndarray,
                    window: float) -> np.ndarray:
        """Largest distance from segment ``a -> b``'s line of the ``label`` samples whose
        projection lies within ``window`` (metres) of each arc position ``t`` (metres)."""
        P = self.samples[(self.label == label) & self.core]
        d = b - a
        L = np.linalg.norm(d)
        d = d / L
        s = (P - a) @ d
        r = np.linalg.norm(P - a - s[:, None] * d, axis=1)
        out = np.zeros(len(t))
        for k, tk in enumerate(t):
            m = np.abs(s - tk) <= window
            out[k] = r[m].max() if m.any() else (out[k - 1] if k else 0.0)
        return out


def _point_segment_distance(P: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    t = np.clip(((P - a) @ ab) / max(ab @ ab, 1e-300), 0.0, 1.0)
    return np.linalg.norm(P - (a + t[:, None] * ab), axis=1)


# -- 2D cross-sections ------------------------------------------------------------------
def hull_polygon(xy: np.ndarray, ease: float) -> np.ndarray:
    """Convex hull of ``xy`` grown by ``ease`` (Minkowski sum with a disc), CCW ``[m, 2]``."""
    if len(xy) < 3:
        raise ValueError("not enough body samples to measure a cross-section")
    h = ConvexHull(xy)
    pts = xy[h.vertices]
    if ease > 0:
        ang = np.linspace(0, 2 * np.pi, 33)[:-1]
        circ = ease * np.stack([np.cos(ang), np.sin(ang)], 1)
        pts = (pts[:, None, :] + circ[None]).reshape(-1, 2)
        pts = pts[ConvexHull(pts).vertices]
    return pts


def polar_radius(poly: np.ndarray, centre: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Distance from ``centre`` (inside the convex ``poly``) to its border along ``angles``."""
    d = np.stack([np.cos(angles), np.sin(angles)], 1)  # [A, 2]
    p = poly - centre
    q = np.roll(p, -1, axis=0)
    e = q - p  # [E, 2]
    # centre + t d = p + s e  ->  t d - s e = p
    det = d[:, None, 0] * (-e[None, :, 1]) - d[:, None, 1] * (-e[None, :, 0])
    safe = np.where(np.abs(det) > 1e-15, det, np.nan)
    t = (p[None, :, 0] * (-e[None, :, 1]) - p[None, :, 1] * (-e[None, :, 0])) / safe
    s = (d[:, None, 0] * p[None, :, 1] - d[:, None, 1] * p[None, :, 0]) / safe
    ok = (s >= -1e-9) & (s <= 1 + 1e-9) & (t > 0)
    t = np.where(ok, t, np.inf)
    return t.min(1)


def quarter_ring(radius_fn, Q: int, dense: int = 256) -> Tuple[np.ndarray, np.ndarray]:
    """``4Q`` angles and radii of a closed star-shaped curve resampled uniformly in arc
    length within each quarter, so that indices ``0, Q, 2Q, 3Q`` lie on the +x (body's
    left), +y (back), -x (right) and -y (front) rays exactly."""
    th_all, r_all = [], []
    for q in range(4):
        th = q * np.pi / 2 + np.linspace(0.0, np.pi / 2, dense + 1)
        r = radius_fn(th)
        xy = r[:, None] * np.stack([np.cos(th), np.sin(th)], 1)
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
        target = np.linspace(0.0, s[-1], Q + 1)[:-1]
        tq = np.interp(target, s, th)
        th_all.append(tq)
        r_all.append(np.interp(tq, th, r))
    return np.concatenate(th_all), np.concatenate(r_all)


# -- structured mesh builder ------------------------------------------------------------
class MeshBuilder:
    """Accumulates vertices and quad-grid parts (two triangles per cell) with a panel id
    and initial pattern coordinates per face corner."""

    def __init__(self) -> None:
        self.pos: List[np.ndarray] = []
        self.n = 0
        self.faces: List[np.ndarray] = []
        self.panel: List[np.ndarray] = []
        self.init_uv: List[np.ndarray] = []
        self.part: List[np.ndarray] = []
        self._nparts = 0

    def add(self, P: np.ndarray) -> np.ndarray:
        P = np.asarray(P, dtype=np.float64)
        shape = P.shape[:-1]
        P = P.reshape(-1, 3)
        idx = np.arange(self.n, self.n + len(P))
        self.pos.append(P)
        self.n += len(P)
        return idx.reshape(shape)

    def positions(self) -> np.ndarray:
        return np.concatenate(self.pos) if self.pos else np.zeros((0, 3))

    def grid(self, idx: np.ndarray, uv: np.ndarray, panel: int, wrap: bool = False,
             flip: bool = False) -> int:
        """Faces of a vertex grid ``idx [R, C]`` (rows x columns).  ``uv`` is
        ``[R, C + wrap, 2]``: with ``wrap`` the grid closes column ``C-1`` onto column 0
        and ``uv[:, C]`` are the pattern coordinates of column 0 seen from that side.
        Returns the part id."""
        idx = np.asarray(idx)
        R, C = idx.shape
        cols = C if wrap else C - 1
        r, c = np.meshgrid(np.arange(R - 1), np.arange(cols), indexing="ij")
        r, c = r.ravel(), c.ravel()
        c1 = (c + 1) % C
        a, b, cc, d = idx[r, c], idx[r, c1], idx[r + 1, c1], idx[r + 1, c]
        ua, ub, uc, ud = uv[r, c], uv[r, c + 1], uv[r + 1, c + 1], uv[r + 1, c]
        f = np.concatenate([np.stack([a, b, cc], 1), np.stack([a, cc, d], 1)])
        fu = np.concatenate([np.stack([ua, ub, uc], 1), np.stack([ua, uc, ud], 1)])
        keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
        f, fu = f[keep], fu[keep]
        if flip:
            f, fu = f[:, ::-1], fu[:, ::-1]
        self.faces.append(f)
        self.init_uv.append(fu)
        self.panel.append(np.full(len(f), panel))
        pid = self._nparts
        self.part.append(np.full(len(f), pid))
        self._nparts += 1
        return pid

    def arrays(self):
        return (self.positions(), np.concatenate(self.faces), np.concatenate(self.panel),
                np.concatenate(self.init_uv), np.concatenate(self.part))


def grid_uv(P: np.ndarray, centre_col: Optional[int] = None, wrap: bool = False) -> np.ndarray:
    """Initial pattern coordinates of a grid of positions ``P [R, C, 3]``: ``u`` = arc
    length along each row (zero at ``centre_col``), ``v`` = arc length along each column
    from row 0.  With ``wrap`` the row is closed and an extra column (the first one seen
    from the other side of the cut) is appended."""
    if wrap:
        P = np.concatenate([P, P[:, :1]], 1)
    du = np.linalg.norm(np.diff(P, axis=1), axis=2)
    u = np.concatenate([np.zeros((P.shape[0], 1)), np.cumsum(du, 1)], 1)
    if centre_col is not None:
        u = u - u[:, centre_col:centre_col + 1]
    dv = np.linalg.norm(np.diff(P, axis=0), axis=2)
    v = np.concatenate([np.zeros((1, P.shape[1])), np.cumsum(dv, 0)], 0)
    if wrap and P.shape[0] > 2:
        # a closed tube whose perimeter changes linearly along it is a cone: start from
        # its unrolling (an annular sector) rather than a rectangle
        per = u[:, -1] - u[:, 0]
        vm = v.mean(1)
        b, a = np.polyfit(vm, per, 1)
        if abs(b) * (vm[-1] - vm[0]) > 0.02 * per.mean():
            v_apex = -a / b
            rho = v - v_apex  # signed distance from the apex
            phi = u / (vm - v_apex)[:, None]  # arc length / row radius
            return np.stack([rho * np.sin(phi), rho * np.cos(phi) + v_apex], -1)
    return np.stack([u, v], -1)
