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
``d_s + h`` of ``p`` (its nearest sample is within ``h`` of the closest point), and the
exact point-triangle test of :func:`garmentgnn.geometry.closest_point_on_triangle`
(Ericson) on those candidates gives the distance.

The sign: when every edge of the body mesh has exactly two faces (closed pieces, possibly
overlapping like the capsule body's), a point is inside when the winding number of the
mesh around it is non-zero (:class:`garmentgnn.geometry.WindingNumber`, counted along a
vertical ray) -- exact also in the overlaps, where the nearest face can be a hidden one.
For open meshes the normal of the closest face decides (ties at shared edges/vertices
broken by the face whose normal is best aligned with ``p - q``).  Outside, the unsigned
distance to the triangle soup is a lower bound of the distance to the union of the
pieces, so a clearance test against it is conservative.
"""
from __future__ import annotations

from typing import Tuple

import numpy as np
import torch
from scipy.spatial import cKDTree

from garmentgnn.geometry import (WindingNumber, closest_point_on_triangle, face_normals,
                                 unique_edges)


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


def _closest_points(p: np.ndarray, vertices: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Exact closest points ``[n, 3]`` of points ``p [n, 3]`` on triangles ``tri [n, 3]``
    (vertex indices), float64 numpy in and out."""
    t = torch.from_numpy
    q, _, _ = closest_point_on_triangle(t(p), *(t(vertices[tri[:, k]]) for k in range(3)))
    return q.numpy()


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
        V, F = torch.from_numpy(self.vertices), torch.from_numpy(self.faces)
        self.face_normals = face_normals(V, F).numpy()
        #: closed (every edge in exactly two faces): inside/outside from winding numbers,
        #: exact also where closed pieces overlap (capsule bodies)
        self.closed = bool((unique_edges(F, len(V)).counts == 2).all())
        self._exposed_state = None
        self._winding = WindingNumber(V, F, cell=0.01) if self.closed else None

    def inside(self, points: np.ndarray) -> np.ndarray:
        """True where the winding number of the (closed) body around the point is
        non-zero, i.e. inside at least one closed piece."""
        return self._winding.inside(np.asarray(points, dtype=np.float64).reshape(-1, 3))

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
        q = _closest_points(p[pi], self.vertices, self.faces[fi])
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
            allid = np.unique(np.concatenate([np.asarray(ids, dtype=np.int64) for ids in lists]))
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
                q = _closest_points(p[pi], self.vertices, self.faces[fi])
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
        part).  Returns ``(points, number of points moved)``.

        Not :func:`garmentgnn.geometry.push_outside` (the one-step, differentiable
        projection of learned models' outputs): the move per iteration is the same,
        ``q + (margin + extra) n``, but bodies here are unions of overlapping closed
        pieces (capsules), where the pseudo-normal sign of
        :func:`~garmentgnn.geometry.signed_distance` is relative to the piece holding the
        closest point and its closest face can be buried inside another piece.  So this
        one signs by winding number, leaves through the closest visible surface, repeats
        until every point clears the margin, and skips certified-far points with the
        sample KD-tree; the templates' stored geometry depends on these choices."""
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
