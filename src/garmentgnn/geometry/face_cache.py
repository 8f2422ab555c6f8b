"""Exact nearest-body-face search from candidate faces cached per garment-body pair.

:class:`NearestFaceCache` keeps, for every query point (a garment vertex of one frame),
``k`` candidate body faces and a lower bound on the distance of every *other* face, both
taken at a reference configuration.  A later search evaluates only the candidates and
proves, per point, that the nearest face is among them (the bound below); the points
it cannot prove are searched again over all faces and their candidates refreshed.  The
result is the face of the exact brute force (:func:`~garmentgnn.geometry.signed_distance`
with ``candidates=None``), not an approximation.

The bound.  Let ``p_r`` and body ``X_r`` be the reference, and ``L`` a lower bound on
``dist(p_r, f(X_r))`` over every face ``f`` that is not a candidate.  Now the point is at
``p`` and the body at ``X``.  Distances are unchanged when point and body move by a
common translation ``t`` (per frame: the centre of the bounding box of the body
displacements ``X - X_r``); let ``delta = |p - t - p_r|`` and
``beta = max_j |X_j - t - X_r,j|``.  Two facts:

1. ``dist(q, T)`` to a triangle is 1-Lipschitz in ``q``;
2. moving each corner of a triangle by at most ``beta`` changes ``dist(q, T)`` by at most
   ``beta`` (the point with the same barycentric coordinates moves by at most ``beta``).

So every non-candidate face satisfies ``dist(p, f(X)) = dist(p - t, f(X - t)) >=
dist(p - t, f(X_r)) - beta >= dist(p_r, f(X_r)) - delta - beta >= L - delta - beta``.
If the nearest candidate, evaluated exactly now, has ``d1 < L - delta - beta``, no
other face can be nearer: the candidates' argmin is the global one.  (Since
``d1 <= d1_r + delta + beta``, with ``d1_r`` the nearest distance at the reference, the
simpler ``2 (delta + beta) < L - d1_r`` is sufficient; the test uses the exact ``d1``,
which is tighter.)  A tolerance ``1024 eps (1 + max|X|)`` is taken off ``L`` for
rounding, so that the argmin is the brute force's computed one; candidates are kept
sorted by face index, so ties go to the lowest index as in the brute force.

Building the candidates (the first call, and every refreshed point): every face has
two cheap lower bounds on its distance, its bounding sphere, ``|p - c_f| - r_f``
(``c_f`` the centroid, ``r_f`` its largest corner distance), and its supporting plane,
``|n_f . (p - a_f)|``.  The ``search`` faces with the smallest bound (the larger of the
two) get exact distances; where the nearest of them is not below every other face's
bound the point is searched again with 4x as many faces (at last all of them, the
brute force).  The ``k`` nearest examined faces become the candidates and
``L = min(smallest bound of the faces not examined, (k+1)-th exact distance)``.  A point
refreshed while its frame's body is ``beta`` from the frame's reference stores
``L - beta`` (and ``p - t`` as its reference: the same argument backwards), so one body
reference per frame serves all points; a frame with more than ``rebuild_fraction`` of
its points to refresh is rebuilt whole at the current body (its ``beta`` back to 0).

Host synchronisation: evaluating the candidates and the bound needs none; one remains
per call, reading the ``[B, V]`` mask of unproven points to the host to select them;
a call that searches points has one more per 4x widening (whether any point needs it).
On CPU there is no device to wait for.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Dict, Optional, Tuple

import torch
from torch import Tensor

from ._compile import compiled_or_eager
from .triangle import closest_point_on_triangle

__all__ = ["NearestFaceCache", "FaceCacheStats"]

#: tolerance for rounding, in units of the dtype's eps times (1 + largest |coordinate|)
_TOL = 1024


@dataclass
class FaceCacheStats:
    """Counts of a :class:`NearestFaceCache` since it was made (or :meth:`reset`).

    Attributes:
        calls: searches made.
        points: point-frames queried (``B * V`` per call).
        refreshed: point-frames that failed the bound and were searched again alone.
        rebuilt: point-frames searched in a build of a whole frame (the first call, a
            change of shape or faces, or a frame with more than ``rebuild_fraction`` of
            its points failing).
        fallback: point-frames (among the searched ones) whose nearest face the lower
            bounds could not prove among the first ``search`` faces (searched wider).
    """
    calls: int = 0
    points: int = 0
    refreshed: int = 0
    rebuilt: int = 0
    fallback: int = 0

    @property
    def searched(self) -> int:
        """Point-frames searched over all faces (refreshed or rebuilt)."""
        return self.refreshed + self.rebuilt

    @property
    def refresh_rate(self) -> float:
        """``searched / points``: the share of point-frames not served by the cache."""
        return self.searched / self.points if self.points else 0.0


def _pair_d2(p: Tensor, a: Tensor, b: Tensor, c: Tensor) -> Tensor:
    """Squared point-triangle distances, the brute force's arithmetic."""
    q, _, _ = closest_point_on_triangle(p, a, b, c)
    return ((p - q) ** 2).sum(-1)


def _candidate_d2(P: Tensor, X: Tensor, faces: Tensor, cand: Tensor) -> Tensor:
    """``[B, V, K]`` squared distances from ``P [B, V, 3]`` to faces ``cand [B, V, K]`` of
    ``X [B, Vb, 3]``."""
    B = cand.shape[0]
    vid = faces[cand]  # [B, V, K, 3]
    i = torch.arange(B, device=P.device).view(B, 1, 1)
    return _pair_d2(P.unsqueeze(2), X[i, vid[..., 0]], X[i, vid[..., 1]], X[i, vid[..., 2]])


def _tolerance(X: Tensor) -> Tensor:
    """``[B]`` rounding allowance of frames ``X [B, Vb, 3]``."""
    return _TOL * torch.finfo(X.dtype).eps * (1 + X.abs().amax((1, 2)))


def _certify(P: Tensor, X: Tensor, ref_p: Tensor, ref_x: Tensor, cand: Tensor, bound: Tensor,
             faces: Tensor) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """The nearest candidate ``[B, V]`` and the bound's slack ``[B, V]`` (proven where
    ``> 0``), with the frames' translation ``t [B, 3]`` and ``beta [B]``."""
    D = X - ref_x
    t = (D.amax(1) + D.amin(1)) * 0.5
    beta = ((D - t.unsqueeze(1)) ** 2).sum(-1).amax(1).sqrt()
    delta = ((P - t.unsqueeze(1) - ref_p) ** 2).sum(-1).sqrt()
    d2 = _candidate_d2(P, X, faces, cand)
    j = d2.argmin(-1, keepdim=True)
    d1 = d2.gather(-1, j).squeeze(-1).sqrt()
    slack = bound - delta - (beta + _tolerance(X)).unsqueeze(1) - d1
    return cand.gather(-1, j).squeeze(-1), slack, t, beta


_COMPILED: Dict[str, Any] = {}


def _certify_fn(compiled: bool) -> Callable[..., Tuple[Tensor, Tensor, Tensor, Tensor]]:
    """:func:`_certify`, or with ``compiled`` its ``torch.compile``
    (:func:`~garmentgnn.geometry._compile.compiled_or_eager`: dynamic shapes, built once
    per process, eager under a dispatch mode; where compiling fails it warns once and
    stays eager)."""
    if not compiled:
        return _certify
    return compiled_or_eager(_certify, _COMPILED, "face-cache search", stacklevel=4)


def _examine(p: Tensor, lb: Tensor, tri: Tensor, k: int, m: int, tol: float
             ) -> Tuple[Tensor, Tensor, Tensor, int]:
    """Exact distances from ``p [n, 3]`` to the ``m`` triangles of ``tri [F, 3, 3]`` with
    the smallest lower bounds ``lb [n, F]``: nearest face ``[n]``, the ``k`` nearest
    ``[n, k]`` (by index) and a lower bound ``[n]`` on every other face's distance.
    Points whose nearest examined face is not provably below every unexamined face's
    bound are examined again with ``4 m`` faces (finally all): also returned, their
    count."""
    F = lb.size(1)
    m = min(m, F)
    sel = lb.topk(m, largest=False).indices.sort(-1).values  # by index: brute-force ties
    t = tri[sel]  # [n, m, 3, 3]
    d = _pair_d2(p.unsqueeze(1), t[..., 0, :], t[..., 1, :], t[..., 2, :]).sqrt()  # [n, m]
    j = d.argmin(-1, keepdim=True)
    fid = sel.gather(-1, j).squeeze(-1)
    rest = lb.scatter(1, sel, float("inf")).amin(1) - tol  # the faces not examined
    top = d.topk(min(k + 1, m), largest=False)
    keep = sel.gather(-1, top.indices[:, :k]).sort(-1).values
    low = torch.minimum(rest, top.values[:, k] - tol) if k < m else rest
    if m == F:
        return fid, keep, low, 0
    again = torch.nonzero(~(d.gather(-1, j).squeeze(-1) < rest)).squeeze(1)  # a host sync
    if again.numel():
        f2, c2, l2, _ = _examine(p[again], lb[again], tri, k, 4 * m, tol)
        fid[again], keep[again], low[again] = f2, c2, l2
    return fid, keep, low, int(again.numel())


def _search_frame(p: Tensor, x: Tensor, faces: Tensor, k: int, m: int
                  ) -> Tuple[Tensor, Tensor, Tensor, int]:
    """Nearest face ``[n]``, ``k`` candidates ``[n, k]`` (sorted by index) and the lower
    bound ``[n]`` on the distance of every other face, for points ``p [n, 3]`` on one body
    ``x [Vb, 3]``; and how many points needed more than ``m`` exact distances (see the
    module docstring; ``k <= m``)."""
    F = faces.size(0)
    tol = float(_tolerance(x.unsqueeze(0)))
    tri = x[faces]  # [F, 3, 3]
    centre = tri.mean(1)
    radius = ((tri - centre.unsqueeze(1)) ** 2).sum(-1).amax(1).sqrt()
    cross = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = cross.norm(dim=-1, keepdim=True)
    normal = torch.where(area2 > 0, cross / area2.clamp_min(torch.finfo(x.dtype).tiny), 0.0)
    offset = (normal * tri[:, 0]).sum(-1)
    rows = max(1, (1 << 20) // F)
    out = []
    for s in range(0, p.size(0), rows):
        pc = p[s:s + rows]
        # lower bounds of every face's distance: bounding sphere, supporting plane
        lb = torch.maximum(
            torch.cdist(pc, centre, compute_mode="donot_use_mm_for_euclid_dist") - radius,
            (pc @ normal.T - offset).abs())
        out.append(_examine(pc, lb, tri, k, m, tol))
    fid, cand, low = (torch.cat([o[i] for o in out]) for i in range(3))
    return fid, cand, low, sum(o[3] for o in out)


class NearestFaceCache:
    """Nearest body face of each query point, exact, from cached candidates.

    Keep one per garment-body pair (or per chunk of frames) and pass it as ``cache=`` to
    :func:`~garmentgnn.geometry.signed_distance` / :func:`~garmentgnn.geometry.push_outside`,
    or call :meth:`nearest`.  The first call searches every point (lower bounds of every
    face, then exact distances to the most promising ones) and stores, per point of
    every frame, ``k`` candidate faces with the bound that proves them; later calls with
    the same shapes evaluate only the candidates, and search again the points that
    moved too far (the module docstring has the bound and its proof).  The faces found
    are those of the brute force (``candidates=None``), ties to the lower face index.

    Args:
        k: candidate faces kept per point (evaluated on every call).
        search: faces whose exact distance a (re)search computes, chosen by their lower
            bounds (default ``2 k``: with ``search = k`` the bound is the next face's
            lower bound, much looser than its exact distance, and points refresh ~10x
            more often; a point whose nearest face is not proven among them is
            searched with 4x as many).
        rebuild_fraction: a frame with more than this share of its points failing the
            bound is rebuilt whole at its current body (its body reference renewed).
        compiled: run the per-call candidate evaluation and bound through
            ``torch.compile`` (warns and stays eager where compiling fails).

    State: per frame the reference body ``[B, Vb, 3]``; per point ``k`` candidates, its
    reference position and the bound.  A call whose batch size, vertex counts, dtype,
    device or faces differ rebuilds; one built on a single frame (``B = 1``) serves a
    batch of ``B`` frames from that frame (each frame then refreshed on its own).
    Results carry no gradient: the face choice is discrete (``signed_distance``
    differentiates the distance to the chosen face).  :attr:`stats` counts calls and
    refreshes.
    """

    def __init__(self, k: int = 32, search: Optional[int] = None,
                 rebuild_fraction: float = 0.25, compiled: bool = False) -> None:
        if not isinstance(k, int) or k < 1:
            raise ValueError(f"`k`: expected a positive int, got {k!r}")
        if search is not None and (not isinstance(search, int) or search < k):
            raise ValueError(f"`search`: expected an int >= k ({k}) or None, got {search!r}")
        if not 0 <= rebuild_fraction <= 1:
            raise ValueError(f"`rebuild_fraction`: expected a share in [0, 1], got "
                             f"{rebuild_fraction!r}")
        self.k = k
        self.search = 2 * k if search is None else search
        self.rebuild_fraction = rebuild_fraction
        self.compiled = compiled
        self.stats = FaceCacheStats()
        self.reset()

    def reset(self) -> None:
        """Forget the cached candidates (not the stats): the next call rebuilds."""
        self._faces: Optional[Tensor] = None
        self._cand = self._bound = self._ref_p = self._ref_x = None

    def _fits(self, P: Tensor, X: Tensor, faces: Tensor) -> bool:
        if self._faces is None:
            return False
        ref_p, ref_x = self._ref_p, self._ref_x
        if (ref_p.shape[1:] != P.shape[1:] or ref_x.shape[1:] != X.shape[1:]
                or ref_p.shape[0] not in (1, P.shape[0]) or ref_p.dtype != P.dtype
                or ref_p.device != P.device):
            return False
        # a different faces tensor is compared (a host sync on a device: pass the same one)
        return faces is self._faces or (faces.shape == self._faces.shape
                                         and bool(torch.equal(faces, self._faces)))

    @torch.no_grad()
    def nearest(self, points: Tensor, body: Tensor, faces: Tensor,
                compiled: Optional[bool] = None) -> Tensor:
        """Index of the nearest face of ``body`` for each point: ``points [B, V, 3]``
        (or ``[V, 3]``), ``body [B, Vb, 3]`` (or ``[Vb, 3]``, shared), ``faces [F, 3]``
        long; returns ``[B, V]`` (``[V]``) long.  ``compiled`` overrides the cache's."""
        single = points.dim() == 2
        P = (points.unsqueeze(0) if single else points).detach()
        X = body.detach()
        X = X.unsqueeze(0) if X.dim() == 2 else X
        X = X.expand(P.size(0), *X.shape[1:])
        B, V = P.shape[:2]
        k, m = min(self.k, faces.size(0)), self.search
        self.stats.calls += 1
        self.stats.points += B * V
        if not self._fits(P, X, faces):
            self._faces = faces
            self._cand = P.new_empty(B, V, k, dtype=torch.long)
            self._bound, self._ref_p, self._ref_x = P.new_empty(B, V), P.clone(), X.clone()
            fid = P.new_empty(B, V, dtype=torch.long)
            for b in range(B):
                fid[b] = self._rebuild(b, P[b], X[b], k, m)
            return fid[0] if single else fid
        if self._ref_p.shape[0] != B:  # built on one frame: each frame starts from it
            self._cand, self._bound, self._ref_p, self._ref_x = (
                t.expand(B, *t.shape[1:]).clone()
                for t in (self._cand, self._bound, self._ref_p, self._ref_x))
        certify = _certify_fn(self.compiled if compiled is None else compiled)
        fid, slack, t, beta = certify(P, X, self._ref_p, self._ref_x, self._cand,
                                      self._bound, faces)
        bad = (~(slack > 0)).cpu()  # the host sync: which points to search again
        for b, n in enumerate(bad.sum(1).tolist()):
            if n == 0:
                continue
            if n > self.rebuild_fraction * V:
                fid[b] = self._rebuild(b, P[b], X[b], k, m)
                continue
            idx = torch.nonzero(bad[b]).squeeze(1).to(P.device)
            f, c, low, nf = _search_frame(P[b, idx], X[b], faces, k, m)
            # in the frame's reference: p - t, and the bound less the body's residual beta
            fid[b, idx], self._cand[b, idx] = f, c
            self._bound[b, idx] = low - beta[b]
            self._ref_p[b, idx] = P[b, idx] - t[b]
            self.stats.refreshed += n
            self.stats.fallback += nf
        return fid[0] if single else fid

    def _rebuild(self, b: int, p: Tensor, x: Tensor, k: int, m: int) -> Tensor:
        """Search every point of frame ``b`` and make ``x`` its body reference."""
        fid, cand, low, nf = _search_frame(p, x, self._faces, k, m)
        self._cand[b], self._bound[b] = cand, low
        self._ref_p[b], self._ref_x[b] = p, x
        self.stats.rebuilt += p.size(0)
        self.stats.fallback += nf
        return fid
