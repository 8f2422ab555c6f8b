"""Minimal exact point-to-body-mesh distance used to place garments (numpy/scipy only).

Kept private to :mod:`garmentgnn.garments` on purpose: the placement code needs only
"how far is this point from the body, and which way is out", and this helper answers it
exactly (up to float64) for any triangle soup -- including the capsule body, whose
pieces overlap and whose long cylinder triangles defeat nearest-vertex shortcuts.

Method: the body surface is covered by a set of sample points (per-face barycentric
grids) whose covering radius is at most ``h``.  For a query ``p`` with nearest sample at
``d_s``, the true distance ``d`` satisfies ``d_s - h <= d <= d_s``; points with
``d_s - h`` above the threshold of interest are *certified* far without further work.
For the others, the exact closest triangle is among the faces owning a sample within
``d_s + h`` of ``p`` (its nearest sample is within ``h`` of the closest point), and an
exact point-triangle test (Ericson) on those candidates gives the distance.

The sign: when every edge of the body mesh has exactly two faces (closed pieces, possibly
overlapping like the capsule body's), a point is inside when the winding number of the
mesh around it is non-zero (counted along a vertical ray, faces bucketed on an xy grid)
-- exact also in the overlaps, where the nearest face can be a hidden one.  For open
meshes the normal of the closest face decides (ties at shared edges/vertices broken by
the face whose normal is best aligned with ``p - q``).  Outside, the unsigned distance
to the triangle soup is a lower bound of the distance to the union of the pieces, so a
clearance test against it is conservative.
"""
from __future__ import annotations

from typing import Tuple

import numpy as np
from scipy.spatial import cKDTree


def sample_surface(vertices: np.ndarray, faces: np.ndarray, h: float
                   ) -> Tuple[np.ndarray, np.ndarray]:
    """Points covering every face with radius ``<= h`` (a barycentric grid per face,
    spaced at most ``h`` along the face's shortest edge and the next one).

    Returns ``(points [P, 3], face_index [P])``.
    """
    v0, v1, v2 = (vertices[faces[:, k]] for k in range(3))
    # rotate each face so that (a, b) is its shortest edge: the grid then follows the
    # two edges from a, and slivers (long capsule sides) get few points
    lens = np.stack([np.linalg.norm(v1 - v0, axis=1), np.linalg.norm(v2 - v1, axis=1),
                     np.linalg.norm(v0 - v2, axis=1)], 1)
    k = np.argmin(lens, 1)
    tri = np.stack([v0, v1, v2], 1)
    order = np.stack([k, (k + 1) % 3, (k + 2) % 3], 1)
    tri = np.take_along_axis(tri, order[:, :, None], 1)
    a, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    n1 = np.maximum(1, np.ceil(np.linalg.norm(e1, axis=1) / h)).astype(int)
    n2 = np.maximum(1, np.ceil(np.linalg.norm(e2, axis=1) / h)).astype(int)
    pts, fid = [], []
    # group faces by (n1, n2) so each group is one vectorised grid
    key = n1 * 100003 + n2
    for kv in np.unique(key):
        sel = np.nonzero(key == kv)[0]
        m1, m2 = int(n1[sel[0]]), int(n2[sel[0]])
        i, j = np.meshgrid(np.arange(m1 + 1), np.arange(m2 + 1), indexing="ij")
        s, t = (i / m1).ravel(), (j / m2).ravel()
        ok = s + t <= 1.0 + 1e-9
        s, t = s[ok], t[ok]
        p = a[sel, None] + s[None, :, None] * e1[sel, None] + t[None, :, None] * e2[sel, None]
        pts.append(p.reshape(-1, 3))
        fid.append(np.repeat(sel, len(s)))
    return np.concatenate(pts), np.concatenate(fid)


def closest_point_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray
                               ) -> np.ndarray:
    """Exact closest points (Ericson 2005, 5.1.5), all arrays ``[n, 3]``."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4

    def div(n, d):
        return n / np.where(np.abs(d) > 1e-300, d, 1.0)

    den = va + vb + vc
    v, w = div(vb, den), div(vc, den)
    q = a + ab * v[:, None] + ac * w[:, None]
    t = div(d4 - d3, (d4 - d3) + (d5 - d6))
    m = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
    q[m] = (b + (c - b) * t[:, None])[m]
    t = div(d2, d2 - d6)
    m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    q[m] = (a + ac * t[:, None])[m]
    m = (d6 >= 0) & (d5 <= d6)
    q[m] = c[m]
    t = div(d1, d1 - d3)
    m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    q[m] = (a + ab * t[:, None])[m]
    m = (d3 >= 0) & (d4 <= d3)
    q[m] = b[m]
    m = (d1 <= 0) & (d2 <= 0)
    q[m] = a[m]
    return q


class BodyDistance:
    """Signed distance from points to a body triangle mesh (positive outside)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, h: float = 0.01,
                 samples: Tuple[np.ndarray, np.ndarray] = None) -> None:
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)
        self.h = float(h)
        pts, fid = samples if samples is not None else sample_surface(self.vertices,
                                                                      self.faces, self.h)
        self.samples, self.sample_face = pts, fid
        self.tree = cKDTree(pts)
        a, b, c = (self.vertices[self.faces[:, k]] for k in range(3))
        n = np.cross(b - a, c - a)
        self.face_normals = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        e = np.sort(np.concatenate([self.faces[:, [0, 1]], self.faces[:, [1, 2]],
                                    self.faces[:, [2, 0]]]), axis=1)
        _, cnt = np.unique(e, axis=0, return_counts=True)
        #: closed (every edge in exactly two faces): inside/outside from winding numbers,
        #: exact also where closed pieces overlap (capsule bodies)
        self.closed = bool((cnt == 2).all())
        self._exposed_state = None
        if self.closed:
            self._build_ray_grid()

    # -- inside test: winding number along a vertical ray -----------------------------
    def _build_ray_grid(self, cell: float = 0.01) -> None:
        tri = self.vertices[self.faces]
        lo = tri[:, :, :2].min(1)
        hi = tri[:, :, :2].max(1)
        self._cell = cell
        self._origin = lo.min(0) - cell
        i0 = np.floor((lo - self._origin) / cell).astype(np.int64)
        i1 = np.floor((hi - self._origin) / cell).astype(np.int64)
        self._ny = int(i1[:, 1].max()) + 2
        cells, faces = [], []
        span = i1 - i0 + 1
        for sx in np.unique(span[:, 0]):
            for sy in np.unique(span[span[:, 0] == sx, 1]):
                sel = np.nonzero((span[:, 0] == sx) & (span[:, 1] == sy))[0]
                gx, gy = np.meshgrid(np.arange(sx), np.arange(sy), indexing="ij")
                cx = i0[sel, 0][:, None] + gx.ravel()[None]
                cy = i0[sel, 1][:, None] + gy.ravel()[None]
                cells.append((cx * self._ny + cy).ravel())
                faces.append(np.repeat(sel, sx * sy))
        cells, faces = np.concatenate(cells), np.concatenate(faces)
        order = np.argsort(cells, kind="stable")
        self._grid_cells, self._grid_faces = cells[order], faces[order]

    def inside(self, points: np.ndarray) -> np.ndarray:
        """True where the winding number of the (closed) body around the point is
        non-zero, i.e. inside at least one closed piece."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        # a tiny fixed offset keeps rays off edges and vertices of grid-aligned meshes
        q = p[:, :2] + np.array([1.234567e-9, 2.345678e-9])
        c = np.floor((q - self._origin) / self._cell).astype(np.int64)
        key = c[:, 0] * self._ny + c[:, 1]
        lo = np.searchsorted(self._grid_cells, key, side="left")
        hi = np.searchsorted(self._grid_cells, key, side="right")
        cnt = hi - lo
        pi = np.repeat(np.arange(len(p)), cnt)
        if len(pi) == 0:
            return np.zeros(len(p), bool)
        start = np.repeat(lo - np.concatenate([[0], np.cumsum(cnt)[:-1]]), cnt)
        fi = self._grid_faces[start + np.arange(len(pi))]
        tri = self.vertices[self.faces[fi]]
        a, b, cc = tri[:, 0], tri[:, 1], tri[:, 2]
        x, y = q[pi, 0], q[pi, 1]

        def edge(u, v):
            return (v[:, 0] - u[:, 0]) * (y - u[:, 1]) - (v[:, 1] - u[:, 1]) * (x - u[:, 0])

        w0, w1, w2 = edge(b, cc), edge(cc, a), edge(a, b)
        area = w0 + w1 + w2
        hit = ((w0 > 0) & (w1 > 0) & (w2 > 0)) | ((w0 < 0) & (w1 < 0) & (w2 < 0))
        safe = np.where(area != 0, area, 1.0)
        z = (w0 * a[:, 2] + w1 * b[:, 2] + w2 * cc[:, 2]) / safe
        hit &= z > p[pi, 2]
        sign = np.sign(self.face_normals[fi, 2])
        wind = np.zeros(len(p))
        np.add.at(wind, pi[hit], sign[hit])
        return np.abs(wind) > 0.5

    def query(self, points: np.ndarray, max_distance: float = np.inf
              ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Signed distance, closest point and outward direction for every point.

        Points certified farther than ``max_distance`` (and outside) get
        ``distance = lower bound`` (``>= max_distance``), ``closest = nan`` and
        ``direction = nan``; pass ``max_distance=inf`` for exact values everywhere.

        Returns:
            ``(distance [n], closest [n, 3], direction [n, 3])``; ``direction`` is the
            unit vector to move along to leave the body (``(p - q)/|p - q|`` outside,
            ``(q - p)/|q - p|`` inside, the face normal on the surface).
        """
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        n = len(p)
        d_s, s_i = self.tree.query(p)
        dist = d_s - self.h
        closest = np.full((n, 3), np.nan)
        direction = np.full((n, 3), np.nan)
        # certified far from the surface -- but a point deep inside is far too: inside
        # points always get the exact test
        if self.closed:
            outer = ~self.inside(p)
        else:  # open mesh: trust the nearest sample's face normal
            outer = np.einsum("ij,ij->i", p - self.samples[s_i],
                              self.face_normals[self.sample_face[s_i]]) > 0
        near = np.nonzero((d_s - self.h <= max_distance) | ~outer)[0]
        if len(near) == 0:
            return dist, closest, direction
        lists = self.tree.query_ball_point(p[near], d_s[near] + self.h)
        # candidate (point, face) pairs
        pi, fi = [], []
        for k, lst in enumerate(lists):
            f = np.unique(self.sample_face[lst])
            pi.append(np.full(len(f), near[k]))
            fi.append(f)
        pi, fi = np.concatenate(pi), np.concatenate(fi)
        tri = self.faces[fi]
        q = closest_point_on_triangles(p[pi], self.vertices[tri[:, 0]], self.vertices[tri[:, 1]],
                                       self.vertices[tri[:, 2]])
        diff = p[pi] - q
        dd = np.linalg.norm(diff, axis=1)
        cos = np.einsum("ij,ij->i", diff, self.face_normals[fi]) / np.maximum(dd, 1e-300)
        # best pair per point: smallest distance, ties broken by the largest |cos|
        key = np.round(dd, 10) - 1e-12 * np.abs(cos)
        order = np.lexsort((key, pi))
        first = np.ones(len(order), bool)
        first[1:] = pi[order][1:] != pi[order][:-1]
        best = order[first]
        who = pi[best]
        if self.closed:
            sign = np.where(outer[who], 1.0, -1.0)
        else:
            sign = np.where(cos[best] < 0, -1.0, 1.0)
        dist[who] = sign * dd[best]
        closest[who] = q[best]
        out = diff[best] / np.maximum(dd[best], 1e-300)[:, None] * sign[:, None]
        on = dd[best] < 1e-9
        out[on] = self.face_normals[fi[best]][on]
        direction[who] = out
        return dist, closest, direction

    def _exposure(self, ids: np.ndarray) -> np.ndarray:
        """Whether samples ``ids`` lie on the visible surface (not buried inside another
        closed piece); computed on demand and cached."""
        if self._exposed_state is None:
            self._exposed_state = np.full(len(self.samples), -1, dtype=np.int8)
        st = self._exposed_state
        todo = ids[st[ids] < 0]
        if len(todo):
            probe = self.samples[todo] + 1e-4 * self.face_normals[self.sample_face[todo]]
            st[todo] = ~self.inside(probe)
        return st[ids] == 1

    def _closest_exposed(self, p: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Exact closest point on the faces carrying visible samples, and its face: where a
        point inside the body leaves it."""
        q_out = np.zeros_like(p)
        f_out = np.zeros(len(p), dtype=np.int64)
        todo = np.arange(len(p))
        r = 0.05
        while len(todo):
            lists = self.tree.query_ball_point(p[todo], r)
            allid = np.unique(np.concatenate([np.asarray(l, dtype=np.int64) for l in lists]))
            vis = np.zeros(len(self.samples), bool)
            vis[allid[self._exposure(allid)]] = True
            pi, fi, again = [], [], []
            for k, lst in enumerate(lists):
                lst = np.asarray(lst, dtype=np.int64)
                lst = lst[vis[lst]]
                if len(lst) == 0:
                    again.append(todo[k])
                    continue
                dd = np.linalg.norm(self.samples[lst] - p[todo[k]], axis=1)
                keep = lst[dd <= dd.min() + 2 * self.h]  # their faces hold the closest point
                f = np.unique(self.sample_face[keep])
                pi.append(np.full(len(f), todo[k]))
                fi.append(f)
            if pi:
                pi, fi = np.concatenate(pi), np.concatenate(fi)
                tri = self.faces[fi]
                q = closest_point_on_triangles(p[pi], self.vertices[tri[:, 0]],
                                               self.vertices[tri[:, 1]], self.vertices[tri[:, 2]])
                dd = np.linalg.norm(p[pi] - q, axis=1)
                order = np.lexsort((dd, pi))
                first = np.ones(len(order), bool)
                first[1:] = pi[order][1:] != pi[order][:-1]
                best = order[first]
                q_out[pi[best]] = q[best]
                f_out[pi[best]] = fi[best]
            todo = np.asarray(again, dtype=np.int64)
            r *= 2
            if r > 10.0:
                break
        return q_out, f_out

    def push_out(self, points: np.ndarray, margin: float, iterations: int = 8,
                 extra: float = 1e-3) -> Tuple[np.ndarray, int]:
        """Move points closer than ``margin`` (or inside) to ``margin + extra`` from the
        body along their outward direction, repeating (a push may land near another body
        part).  Returns ``(points, number of points moved)``."""
        p = np.array(points, dtype=np.float64)
        moved = np.zeros(len(p), bool)
        for _ in range(iterations):
            d, q, nrm = self.query(p, max_distance=margin)
            bad = np.nonzero(d < margin)[0]
            if len(bad) == 0:
                break
            target = q[bad] + nrm[bad] * (margin + extra)
            if self.closed:
                # inside: the closest surface may be buried in another piece; leave
                # through the closest point of the visible surface instead
                ins = np.nonzero(d[bad] < 0)[0]
                if len(ins):
                    qe, fe = self._closest_exposed(p[bad[ins]])
                    target[ins] = qe + self.face_normals[fe] * (margin + extra)
            p[bad] = target
            moved[bad] = True
        return p, int(moved.sum())
