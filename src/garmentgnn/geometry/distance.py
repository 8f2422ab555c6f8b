"""Distances from garment vertices to a body: signed distance to a triangle mesh and
vertex-to-joint distances.

The signed distance ``s(p)`` is the one of GarTrans Eq. 10 (collision loss
``k_c sum_i |min(s(p_i) - eps, 0)|``): positive outside the body, negative inside.
"""
from __future__ import annotations

from typing import Any, Callable, Dict, List, NamedTuple, Optional, Sequence, Tuple

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from ._compile import compiled_or_eager
from ._index import gather_rows, scatter_rows
from ._validate import check_faces, check_points, safe_norm
from .mesh import EdgeTopology, unique_edges
from .normals import face_angles_unchecked, face_cross, scatter_faces_to_vertices
from .triangle import (REGION_EDGE, REGION_FACE, REGION_VERTEX, closest_point_on_triangle,
                       squared_distances_per_coordinate)
from .winding import WindingNumber

__all__ = ["closest_point_on_triangle", "SignedDistance", "signed_distance", "push_outside",
           "vertex_joint_distances", "WindingNumber", "REGION_FACE", "REGION_VERTEX",
           "REGION_EDGE"]

class SignedDistance(NamedTuple):
    """Result of :func:`signed_distance`.

    Attributes:
        distance: ``[..., V]`` signed distance (positive outside, negative inside).
        closest: ``[..., V, 3]`` closest point on the body surface.
        normal: ``[..., V, 3]`` unit (pseudo-)normal of the body at the closest point
            (face normal inside a face, edge / vertex pseudo-normal on edges / corners).
        face: ``[..., V]`` long, index of the body face holding the closest point.
    """
    distance: Tensor
    closest: Tensor
    normal: Tensor
    face: Tensor


def _tri_gather(body: Tensor, faces: Tensor, face_idx: Tensor) -> Tensor:
    """Triangles ``[B, P, 3, 3]`` for face indices ``[B, P]`` of a body ``[B, Vb, 3]``."""
    B, P = face_idx.shape
    vid = faces[face_idx.reshape(-1)].view(B, P * 3)
    tri = torch.gather(body, 1, vid.unsqueeze(-1).expand(B, P * 3, 3))
    return tri.view(B, P, 3, 3)


def _vertex_face_table(faces: Tensor, num_vertices: int) -> Tensor:
    """``[Vb, max_degree]`` incident faces per vertex, padded with ``-1`` (sort-based)."""
    v = faces.reshape(-1)
    fid = torch.arange(faces.size(0), device=faces.device).repeat_interleave(3)
    order = torch.argsort(v, stable=True)
    v, fid = v[order], fid[order]
    deg = torch.bincount(v, minlength=num_vertices)
    start = torch.cumsum(deg, 0) - deg
    slot = torch.arange(v.numel(), device=v.device) - start[v]
    table = torch.full((num_vertices, max(int(deg.max()), 1)), -1, dtype=torch.long,
                       device=faces.device)
    table[v, slot] = fid
    return table


#: body topologies (unique edges, vertex-face table) by faces content, newest last
_TOPOLOGY: List[Tuple[Tensor, int, EdgeTopology, Tensor]] = []


@torch.inference_mode(False)  # a topology built in inference mode serves autograd later
def body_topology(faces: Tensor, num_vertices: int) -> Tuple[EdgeTopology, Tensor]:
    """``(unique_edges(faces), vertex-face table)`` of a body mesh, kept for the last few
    meshes by content (a body's faces arrive as a fresh tensor with every batch, with the
    same values): one comparison of the faces instead of a sort and ``unique`` per call."""
    for i, (f, n, topo, table) in enumerate(_TOPOLOGY):
        if n == num_vertices and f.shape == faces.shape and f.device == faces.device \
                and torch.equal(f, faces):
            if i != len(_TOPOLOGY) - 1:
                _TOPOLOGY.append(_TOPOLOGY.pop(i))
            return topo, table
    f = faces.clone()
    topo = unique_edges(f, num_vertices)
    table = _vertex_face_table(f, num_vertices)
    _TOPOLOGY.append((f, num_vertices, topo, table))
    del _TOPOLOGY[:-4]
    return topo, table


@torch.no_grad()
def _nearest_faces_bruteforce(points: Tensor, body: Tensor, faces: Tensor,
                              chunk_size: int) -> Tensor:
    """Exact argmin over all faces, ``[B, V]``, in chunks of garment vertices."""
    B, V, _ = points.shape
    a, b, c = (body[:, faces[:, k]].unsqueeze(1) for k in range(3))  # [B, 1, F, 3]
    out = torch.empty(B, V, dtype=torch.long, device=points.device)
    for s in range(0, V, chunk_size):
        p = points[:, s:s + chunk_size].unsqueeze(2)  # [B, c, 1, 3]
        q, _, _ = closest_point_on_triangle(p, a, b, c)
        out[:, s:s + chunk_size] = ((p - q) ** 2).sum(-1).argmin(-1)
    return out


def _nearest_faces_grouped(points: Tensor, body: Tensor, faces: Tensor,
                           chunk_size: Optional[int],
                           groups: Optional[List[Tuple[int, int, int, int]]]) -> Tensor:
    """:func:`_nearest_faces_bruteforce` over each group's own faces (``groups``:
    :func:`_check_groups`), ``[B, V]`` indices into ``faces``."""
    if groups is None:
        cs = chunk_size or max(1, (1 << 18) // max(faces.size(0), 1))
        return _nearest_faces_bruteforce(points, body, faces, cs)
    out = torch.empty(points.shape[:2], dtype=torch.long, device=points.device)
    for p0, p1, b0, b1 in groups:
        if p1 > p0:
            own = ((faces[:, 0] >= b0) & (faces[:, 0] < b1)).nonzero().squeeze(1)
            cs = chunk_size or max(1, (1 << 18) // max(own.numel(), 1))
            out[:, p0:p1] = own[_nearest_faces_bruteforce(points[:, p0:p1], body, faces[own],
                                                          cs)]
    return out


def _face_corners(body: Tensor, faces: Tensor) -> Tensor:
    """The corners of every face of ``body [B, Vb, 3]``, ``[9, B, F]``: rows ``a_x, a_y,
    a_z, b_x, ..., c_z`` (one row a coordinate, for :func:`_closest_candidate`)."""
    B, F = body.shape[0], faces.shape[0]
    return gather_rows(body, faces).permute(2, 3, 0, 1).reshape(9, B, F)  # [B, F, 3, 3]


def _closest_candidate(p: Tensor, corners: Tensor, nn: Tensor, table: Tensor) -> Tensor:
    """The face closest to each point of ``p [B, c, 3]`` among the faces around its
    nearest body vertices ``nn [B, c, k]`` (``table [Vb, D]``: the faces of each vertex,
    ``-1`` = none), on the frames' face corners ``corners [9, B, F]``
    (:func:`_face_corners`): ``[B, c]``.  A face found through several vertices is
    evaluated once for each; ties go to the first (the nearest vertex's)."""
    B, c, _ = nn.shape
    cand = table[nn].reshape(B, c, -1)  # [B, c, K]
    valid = cand >= 0
    cs = cand.clamp_min(0)
    i = torch.arange(B, device=p.device).view(B, 1, 1)
    t = [corners[j][i, cs] for j in range(9)]  # 9 x [B, c, K]
    d2 = squared_distances_per_coordinate([p[..., j].unsqueeze(-1) for j in range(3)],
                                          t[0:3], t[3:6], t[6:9])
    d2 = d2.masked_fill(~valid, float("inf"))
    return cs.gather(-1, d2.argmin(-1, keepdim=True)).squeeze(-1)


_COMPILED: Dict[str, Any] = {}


def _closest_candidate_fn(compiled: bool) -> Callable[[Tensor, Tensor, Tensor, Tensor], Tensor]:
    """:func:`_closest_candidate`, or with ``compiled`` its ``torch.compile``
    (:func:`~garmentgnn.geometry._compile.compiled_or_eager`: dynamic shapes, built once
    per process, eager under a dispatch mode or after a failed compile).  Inductor fuses
    the table lookup, the corners' gather and Ericson's element-wise cascade into one loop
    along the candidates, which the per-coordinate arithmetic
    (``triangle.squared_distances_per_coordinate``) lets it vectorise: 3.8x the compiled
    ``[..., 3]`` form it replaced, 16x eager (8 frames x 416 points x 80 candidates, one
    thread: 5.3, 20 and 85 ms).  The result is the same face up to ties in distance."""
    if not compiled:
        return _closest_candidate
    return compiled_or_eager(_closest_candidate, _COMPILED, "distance search", stacklevel=3)


@torch.no_grad()
def _nearest_vertices(points: Tensor, body: Tensor, k: int,
                      groups: Optional[List[Tuple[int, int, int, int]]] = None) -> Tensor:
    """Indices ``[B, V, k]`` of the ``k`` body vertices nearest to each point of
    ``points [B, V, 3]`` on ``body [B, Vb, 3]`` (the same frame), nearest first;
    ``groups`` (:func:`_check_groups`): point rows ``p0:p1`` search body vertices
    ``b0:b1`` only (``k`` at most the smallest such range).

    On the CPU: a k-d tree per frame (and group) (:class:`scipy.spatial.cKDTree`, built
    on the body and queried with every point), 2.7x faster than ``cdist`` + ``topk``
    over the whole body at 8 frames x 416 points x 1,229 body vertices (7 against 19
    ms, one thread).  Elsewhere: ``torch.cdist`` + ``torch.topk``.  The two can order
    two vertices at equal distance (to rounding) differently."""
    if groups is None:
        groups = [(0, points.shape[1], 0, body.shape[1])]
    if points.device.type != "cpu":
        out = torch.empty(points.shape[0], points.shape[1], k, dtype=torch.long,
                          device=points.device)
        for p0, p1, b0, b1 in groups:
            out[:, p0:p1] = b0 + torch.cdist(points[:, p0:p1], body[:, b0:b1]).topk(
                k, dim=-1, largest=False).indices
        return out
    wide = (torch.float32, torch.float64)
    pn = points.detach().to(points.dtype if points.dtype in wide else torch.float32).numpy()
    bn = body.detach().to(body.dtype if body.dtype in wide else torch.float32).numpy()
    out = np.empty((points.shape[0], points.shape[1], k), dtype=np.int64)
    for b in range(points.shape[0]):
        for p0, p1, b0, b1 in groups:
            if p1 > p0:
                out[b, p0:p1] = b0 + cKDTree(bn[b, b0:b1]).query(pn[b, p0:p1],
                                                                 k=k)[1].reshape(-1, k)
    return torch.from_numpy(out)


def _check_groups(point_ptr: Any, body_ptr: Any, num_points: int, num_body: int,
                  faces: Tensor) -> Optional[List[Tuple[int, int, int, int]]]:
    """``point_ptr`` / ``body_ptr`` (:func:`signed_distance`) as ``(p0, p1, b0, b1)`` per
    mesh, validated (``None``: one mesh for all points)."""
    if point_ptr is None and body_ptr is None:
        return None
    ptrs = []
    for name, ptr, end in (("point_ptr", point_ptr, num_points),
                           ("body_ptr", body_ptr, num_body)):
        if isinstance(ptr, Tensor):
            ptr = ptr.tolist() if ptr.dim() == 1 and not ptr.is_floating_point() else None
        ok = isinstance(ptr, (list, tuple)) and len(ptr) >= 2 and all(
            isinstance(i, int) and not isinstance(i, bool) for i in ptr)
        if not ok or ptr[0] != 0 or ptr[-1] != end or any(
                b < a for a, b in zip(ptr, ptr[1:])):
            raise ValueError(f"`{name}`: expected non-decreasing ints from 0 to {end} (the "
                             f"rows of each mesh, like PyG's `ptr`), got {ptr!r}")
        ptrs.append(list(ptr))
    pp, bp = ptrs
    if len(pp) != len(bp):
        raise ValueError(f"`point_ptr` and `body_ptr`: one range per mesh in both, got "
                         f"{len(pp) - 1} and {len(bp) - 1}")
    mesh = torch.bucketize(faces, torch.tensor(bp[1:], device=faces.device), right=True)
    if not bool((mesh == mesh[:, :1]).all()):
        raise ValueError("`body_faces`: a face joins vertices of two meshes of `body_ptr`; "
                         "each mesh's faces must index only its own vertex range")
    groups = [(pp[n], pp[n + 1], bp[n], bp[n + 1]) for n in range(len(pp) - 1)]
    has_faces = torch.bincount(mesh[:, 0], minlength=len(groups)).tolist()
    empty = [n for n, (p0, p1, _, _) in enumerate(groups) if p1 > p0 and not has_faces[n]]
    if empty:
        raise ValueError(f"`body_faces`: body mesh {empty[0]} of `body_ptr` has points but "
                         f"no faces")
    return groups


@torch.no_grad()
def _nearest_faces_candidates(points: Tensor, body: Tensor, faces: Tensor, k: int,
                              chunk_size: int, compiled: bool = False,
                              groups: Optional[List[Tuple[int, int, int, int]]] = None
                              ) -> Tensor:
    """Argmin over the faces incident to the ``k`` nearest body vertices (of the point's
    own mesh with ``groups``), ``[B, V]`` (``compiled``: see :func:`_closest_candidate_fn`)."""
    closest = _closest_candidate_fn(compiled)
    B, V, _ = points.shape
    table = body_topology(faces, body.size(1))[1]  # [Vb, D]
    # the smallest body among the meshes that have points (those have faces)
    smallest = min((b1 - b0 for p0, p1, b0, b1 in groups or () if p1 > p0),
                   default=body.size(1))
    nn = _nearest_vertices(points, body, min(k, smallest), groups)  # [B, V, k]
    corners = _face_corners(body, faces)
    out = torch.empty(B, V, dtype=torch.long, device=points.device)
    for s in range(0, V, chunk_size):  # contiguous slices: one compiled graph for all
        out[:, s:s + chunk_size] = closest(points[:, s:s + chunk_size].contiguous(), corners,
                                           nn[:, s:s + chunk_size].contiguous(), table)
    return out


def signed_distance(points: Tensor, body_pos: Tensor, body_faces: Tensor,
                    chunk_size: Optional[int] = None, candidates: Optional[int] = None,
                    body_edges: Optional[EdgeTopology] = None,
                    compiled: bool = False, cache: Optional[Any] = None,
                    point_ptr: Optional[Sequence[int]] = None,
                    body_ptr: Optional[Sequence[int]] = None) -> SignedDistance:
    """Signed distance from garment vertices to a body triangle mesh (the ``s(p)`` of Eq. 10).

    ``s(p) = sign((p - q) . n(q)) * |p - q|`` with ``q`` the exact closest point on
    the body surface (:func:`closest_point_on_triangle` on every face, Ericson's
    regions) and ``n(q)`` the **angle-weighted pseudo-normal** of Baerentzen & Aanaes
    (2005): the face normal if ``q`` is inside a face, the normalised sum of the two
    face normals if ``q`` is on an edge, the angle-weighted vertex normal if ``q`` is a
    corner.  For a closed, consistently outward-oriented (watertight) body this sign
    is exact, unlike the closest face's normal, which fails near convex edges and
    corners.  For a body made of several overlapping closed pieces (e.g. capsules)
    the sign is relative to the piece holding the closest point.

    Memory: the face search runs without autograd in chunks of ``chunk_size`` garment
    vertices (``chunk_size * F`` point-triangle pairs at a time; default chosen so a
    chunk has about 2**18 pairs per batch element); the differentiable pass then
    recomputes ``q`` only for the selected face of each vertex, so autograd stores
    ``O(V)`` values.  The distance is differentiable w.r.t. ``points`` (gradient
    ``n`` inside a face region, ``(p - q) / |p - q|`` in general) and ``body_pos``.

    ``candidates=k`` (optional, approximate) restricts the search to faces incident to
    the ``k`` nearest body vertices (a k-d tree per frame on the CPU).  This is exact when
    the closest face touches one of those vertices, which holds when body triangles
    are small compared with the garment-body gap; a point over the middle of a large
    triangle whose corners are all farther than ``k`` other vertices can get a
    slightly larger distance.  ``candidates=None`` (default) is the exact brute force.

    Args:
        points: ``[..., V, 3]`` garment positions.
        body_pos: ``[..., Vb, 3]`` body positions (batch dims broadcast with ``points``).
        body_faces: ``[Fb, 3]`` long, outward-oriented (counter-clockwise seen from
            outside).
        chunk_size: garment vertices per chunk of the face search.
        candidates: number of nearest body vertices for the approximate search.
        body_edges: ``unique_edges(body_faces)``, to skip recomputing it every call.
        compiled: run the candidate search (``candidates=k``) through ``torch.compile``
            (same faces up to ties; about 4x faster on CPU after a one-off compile of
            10-20 s per process; falls back to eager with a warning where compiling
            fails).
        cache: a :class:`~garmentgnn.geometry.NearestFaceCache` kept for this
            garment-body pair: the face search runs through it instead (exact, the faces
            of ``candidates=None``, from candidates cached by earlier calls and proven
            by a bound; ``candidates`` and ``chunk_size`` are then unused, ``compiled``
            compiles its candidate evaluation).  The differentiable part is the same.
        point_ptr, body_ptr: several garment-body pairs in one call (the layout of a
            PyG ``Batch``'s ``ptr``): points ``point_ptr[n]:point_ptr[n + 1]`` (along
            ``V``) are measured to body mesh ``n``, vertices ``body_ptr[n]:body_ptr[n +
            1]`` (along ``Vb``), whose faces index only that range; equal to one call per
            pair (the body-side work and the search run once for all; not with
            ``cache``, which serves one pair).
    """
    points = check_points(points, "points")
    body_pos = check_points(body_pos, "body_pos")
    body_faces = check_faces(body_faces, body_pos.size(-2), "body_faces")
    if points.dtype != body_pos.dtype:
        raise TypeError(f"`body_pos`: dtype {body_pos.dtype} differs from `points` dtype "
                        f"{points.dtype}; convert one of them")
    try:
        batch = torch.broadcast_shapes(points.shape[:-2], body_pos.shape[:-2])
    except RuntimeError:
        raise ValueError(f"`body_pos`: batch shape {tuple(body_pos.shape[:-2])} does not "
                         f"broadcast with `points` batch shape {tuple(points.shape[:-2])}"
                         ) from None
    if chunk_size is not None and (not isinstance(chunk_size, int) or chunk_size < 1):
        raise ValueError(f"`chunk_size`: expected a positive int, got {chunk_size!r}")
    if candidates is not None and (not isinstance(candidates, int) or candidates < 1):
        raise ValueError(f"`candidates`: expected a positive int or None, got {candidates!r}")
    V, Vb, F = points.size(-2), body_pos.size(-2), body_faces.size(0)
    groups = _check_groups(point_ptr, body_ptr, V, Vb, body_faces)
    if groups is not None and cache is not None:
        raise ValueError("`cache`: a NearestFaceCache serves one garment-body pair; pass "
                         "it without `point_ptr` / `body_ptr`")
    B = 1
    for s in batch:
        B *= s
    P = points.expand(*batch, V, 3).reshape(B, V, 3)
    X = body_pos.expand(*batch, Vb, 3).reshape(B, Vb, 3)
    f = body_faces

    if cache is not None:
        fid = cache.nearest(P, X, f, compiled=compiled or None)
    elif candidates is None:
        fid = _nearest_faces_grouped(P.detach(), X.detach(), f, chunk_size, groups)
    else:
        cs = chunk_size or max(1, (1 << 18) // max(candidates * 8, 1))
        fid = _nearest_faces_candidates(P.detach(), X.detach(), f, candidates, cs, compiled,
                                        groups)

    tri = _tri_gather(X, f, fid)  # [B, V, 3, 3], differentiable in X
    q, _, region = closest_point_on_triangle(P, tri[..., 0, :], tri[..., 1, :], tri[..., 2, :])

    # angle-weighted pseudo-normals of the body
    cf = face_cross(X, f)
    nf = cf / safe_norm(cf, keepdim=True)  # [B, F, 3]
    topo = body_topology(f, Vb)[0] if body_edges is None else body_edges
    if topo.face_edges.shape != f.shape:
        raise ValueError("`body_edges`: does not match `body_faces`; pass "
                         "unique_edges(body_faces)")
    ne = scatter_rows(nf.unsqueeze(-2).expand(B, F, 3, 3), topo.face_edges, topo.edges.size(0))
    ne = ne / safe_norm(ne, keepdim=True)
    nv = scatter_faces_to_vertices(nf.unsqueeze(-2) * face_angles_unchecked(X, f).unsqueeze(-1),
                                   f, Vb)
    nv = nv / safe_norm(nv, keepdim=True)

    def pick(table: Tensor, idx: Tensor) -> Tensor:  # table [B, N, 3], idx [B, V]
        return torch.gather(table, 1, idx.unsqueeze(-1).expand(B, V, 3))

    n_face = pick(nf, fid)
    k_vert = (region - 1).clamp(0, 2)
    n_vert = pick(nv, f[fid, k_vert])
    k_edge = (region - 4).clamp(0, 2)
    n_edge = pick(ne, topo.face_edges[fid, k_edge])
    r = region.unsqueeze(-1)
    normal = torch.where(r == 0, n_face, torch.where(r <= 3, n_vert, n_edge))

    diff = P - q
    dist = safe_norm(diff)
    sign = torch.where((diff * normal).sum(-1) < 0, -1.0, 1.0).to(dist.dtype)
    out = (sign * dist, q, normal, fid)
    return SignedDistance(*(t.reshape(*batch, *t.shape[1:]) for t in out))


def push_outside(points: Tensor, body_pos: Tensor, body_faces: Tensor, margin: float,
                 candidates: Optional[int] = 8, compiled: bool = False,
                 cache: Optional[Any] = None, point_ptr: Optional[Sequence[int]] = None,
                 body_ptr: Optional[Sequence[int]] = None) -> Tensor:
    """Move every point closer than ``margin`` to the body (or inside it) to distance
    ``margin`` outside: ``p' = p + max(margin - s(p), 0) grad s(p)`` with ``s`` of
    :func:`signed_distance` and ``grad s = sign (p - q) / |p - q|`` (``q`` the closest
    body point; the body's pseudo-normal where ``p`` lies on the surface).  Points
    already ``margin`` or farther outside are returned unchanged.

    This is the one-step collision projection used as post-processing by learned
    garment models (e.g. TailorNet); it lands exactly at ``margin`` when the
    closest point keeps its face, i.e. for depths below the body's local feature size.
    Differentiable in ``points`` and ``body_pos``.  ``candidates``, ``compiled``,
    ``cache``, ``point_ptr`` and ``body_ptr``: see :func:`signed_distance`
    (``candidates=None``: exact brute force; a ``cache`` makes the search exact as well,
    from cached candidates; the pointers: several garment-body pairs in one call).

    Garment fitting does not use it: ``garmentgnn.garments._distance.BodyDistance.push_out``
    solves a different problem (the same move ``q + margin n``, but repeated until no
    point is within the margin, signed by winding number so that it is right inside
    *overlapping* closed pieces such as the capsule body's, and leaving through the
    closest *visible* surface instead of a face buried in another piece); one step of
    this pseudo-normal projection can push such a point the wrong way.
    """
    if not margin >= 0:
        raise ValueError(f"`margin` must be >= 0 (metres), got {margin}")
    sd = signed_distance(points, body_pos, body_faces, candidates=candidates,
                         compiled=compiled, cache=cache, point_ptr=point_ptr,
                         body_ptr=body_ptr)
    diff = points - sd.closest
    dist = safe_norm(diff, keepdim=True)
    tiny = 1e3 * torch.finfo(dist.dtype).eps
    grad = torch.where(dist > tiny, torch.sign(sd.distance).unsqueeze(-1) * diff
                       / dist.clamp_min(tiny), sd.normal)
    depth = torch.relu(margin - sd.distance).unsqueeze(-1)
    return points + depth * grad


def vertex_joint_distances(pos: Tensor, joints: Tensor) -> Tensor:
    """Euclidean distances from every vertex to every joint, ``d_vs = |p_v - j_s|``.

    Args:
        pos: ``[..., V, 3]``.
        joints: ``[..., S, 3]`` (batch dims broadcast with ``pos``).

    Returns:
        ``[..., V, S]``; differentiable (finite gradient also at zero distance).
    """
    pos = check_points(pos, "pos")
    joints = check_points(joints, "joints")
    try:
        torch.broadcast_shapes(pos.shape[:-2], joints.shape[:-2])
    except RuntimeError:
        raise ValueError(f"`joints`: batch shape {tuple(joints.shape[:-2])} does not "
                         f"broadcast with `pos` batch shape {tuple(pos.shape[:-2])}") from None
    return safe_norm(pos.unsqueeze(-2) - joints.unsqueeze(-3))
