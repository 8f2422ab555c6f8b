"""Mesh connectivity and a procedural sheet mesh."""
from __future__ import annotations

import operator
from typing import NamedTuple, Optional, Tuple

import torch
from torch import Tensor
from torch_geometric.utils import sort_edge_index, to_undirected

from ._validate import check_faces, check_points


def faces_to_edge_index(faces: Tensor, num_nodes: int) -> Tensor:
    """Directed graph of a triangle mesh: both directions of every unique edge.

    Args:
        faces: ``[F, 3]`` long tensor of vertex indices.
        num_nodes: number of mesh vertices.

    Returns:
        ``[2, E]`` edge index, coalesced and sorted by target (column 1), the
        CSR order that lets :mod:`garmentgnn.nn` layers use segment reductions.
    """
    if not isinstance(faces, Tensor):
        raise TypeError(f"`faces`: expected a torch.Tensor [F, 3], got {type(faces).__name__}")
    if faces.is_floating_point() or faces.is_complex() or faces.dtype == torch.bool:
        raise TypeError(f"`faces`: expected an integer tensor, got dtype {faces.dtype}; "
                        f"use faces.long()")
    try:
        n = None if isinstance(num_nodes, bool) else operator.index(num_nodes)
    except (TypeError, RuntimeError):
        n = None
    if n is None or n < 0:
        raise ValueError(f"`num_nodes`: expected the number of mesh vertices (an int >= 0), "
                         f"got {num_nodes!r}")
    num_nodes = n
    if faces.dim() != 2 or faces.size(1) != 3:
        raise ValueError(f"`faces`: expected shape [F, 3], got {tuple(faces.shape)}")
    if faces.numel() and (int(faces.min()) < 0 or int(faces.max()) >= num_nodes):
        raise ValueError(f"`faces`: indices must lie in [0, {num_nodes}), got "
                         f"[{int(faces.min())}, {int(faces.max())}]")
    f = faces.long()
    ei = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], 0).t()
    ei = to_undirected(ei, num_nodes=num_nodes)
    return sort_edge_index(ei, num_nodes=num_nodes, sort_by_row=False)


def grid_mesh(nx: int, ny: int, size: Tuple[float, float] = (1.0, 1.0),
              dtype: torch.dtype = torch.float32) -> Tuple[Tensor, Tensor]:
    """A flat ``nx`` x ``ny`` vertex sheet in the z=0 plane, two triangles per cell.

    Returns:
        ``(pos [nx*ny, 3], faces [2*(nx-1)*(ny-1), 3])``.
    """
    if nx < 2 or ny < 2:
        raise ValueError(f"`nx`, `ny`: need at least 2 vertices per side, got {nx}, {ny}")
    xs = torch.linspace(0.0, size[0], nx, dtype=dtype)
    ys = torch.linspace(0.0, size[1], ny, dtype=dtype)
    gx, gy = torch.meshgrid(xs, ys, indexing="ij")
    pos = torch.stack([gx, gy, torch.zeros_like(gx)], -1).reshape(-1, 3)
    idx = torch.arange(nx * ny).view(nx, ny)
    a, b = idx[:-1, :-1].reshape(-1), idx[1:, :-1].reshape(-1)
    c, d = idx[1:, 1:].reshape(-1), idx[:-1, 1:].reshape(-1)
    faces = torch.cat([torch.stack([a, b, c], 1), torch.stack([a, c, d], 1)], 0)
    return pos, faces


def edge_features(pos: Tensor, edge_index: Tensor) -> Tensor:
    """Per-edge ``[length, unit direction (3)]`` features, ``[E, 4]``.

    ``pos [V, 3]`` finite floats, ``edge_index [2, E]`` integer indices into it; a
    length that overflows the dtype (coordinates far beyond metres) raises."""
    pos = check_points(pos, "pos", allow_empty=True)
    if pos.dim() != 2:
        raise ValueError(f"`pos`: expected [V, 3], got {tuple(pos.shape)}")
    if not isinstance(edge_index, Tensor) or edge_index.dim() != 2 or edge_index.size(0) != 2 \
            or edge_index.is_floating_point() or edge_index.dtype == torch.bool:
        raise ValueError("`edge_index`: expected an integer tensor [2, E] (faces_to_edge_index)")
    if edge_index.numel() and (int(edge_index.min()) < 0
                               or int(edge_index.max()) >= pos.size(0)):
        raise ValueError(f"`edge_index`: indices must lie in [0, {pos.size(0)})")
    d = pos.index_select(0, edge_index[1]) - pos.index_select(0, edge_index[0])
    length = d.norm(dim=-1, keepdim=True)
    if not torch.isfinite(length).all():
        raise ValueError(f"`pos`: edge lengths overflow {pos.dtype}; coordinates are far "
                         f"beyond garment scale (metres expected), or use float64")
    return torch.cat([length, d / length.clamp_min(1e-12)], -1)


# ---------------------------------------------------------------------------
# Connectivity (pure torch, no python loops over faces)
# ---------------------------------------------------------------------------
class EdgeTopology(NamedTuple):
    """Unique undirected edges of a triangle mesh.

    Attributes:
        edges: ``[E, 2]`` long, each row ``(i, j)`` with ``i < j``, rows sorted
            lexicographically.
        face_edges: ``[F, 3]`` long; column ``k`` is the index into ``edges`` of the
            face edge ``(f[k], f[(k+1) % 3])`` (the edge opposite ``f[(k+2) % 3]``).
        counts: ``[E]`` long, number of faces using each edge (1 = boundary edge,
            2 = interior manifold edge, >2 = non-manifold edge).
    """
    edges: Tensor
    face_edges: Tensor
    counts: Tensor


class FaceAdjacency(NamedTuple):
    """Pairs of faces sharing an edge.

    Attributes:
        faces: ``[A, 2]`` long, the two face indices ``(f1, f2)``.
        edges: ``[A, 2]`` long, the shared edge ``(a, b)`` oriented as face ``f1``
            traverses it (``f1`` contains the directed edge ``a -> b``).
        opposite: ``[A, 2]`` long, the vertex of ``f1`` and of ``f2`` that is not on
            the shared edge.
    """
    faces: Tensor
    edges: Tensor
    opposite: Tensor


def _half_edges(faces: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
    """Directed face edges ``[3F, 2]``, owning face ``[3F]`` and opposite vertex ``[3F]``.

    Half-edge ``k * F + f`` is the edge ``(faces[f, k], faces[f, (k+1) % 3])``.
    """
    f = faces.long()
    he = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], 0)
    owner = torch.arange(f.size(0), device=f.device).repeat(3)
    opp = torch.cat([f[:, 2], f[:, 0], f[:, 1]], 0)
    return he, owner, opp


def _check_topology(faces: Tensor, num_vertices: Optional[int]) -> Tuple[Tensor, int]:
    if not isinstance(faces, Tensor):
        raise TypeError(f"`faces`: expected a torch.Tensor of shape [F, 3], got "
                        f"{type(faces).__name__}")
    n = int(faces.max()) + 1 if (num_vertices is None and faces.numel()) else (num_vertices or 0)
    return check_faces(faces, n), n


def unique_edges(faces: Tensor, num_vertices: Optional[int] = None) -> EdgeTopology:
    """Unique undirected edges, the face-to-edge map and per-edge face counts.

    Computed with a sort + ``torch.unique`` over the integer keys ``min * V + max`` of
    the ``3F`` half-edges.

    Args:
        faces: ``[F, 3]`` integer tensor.
        num_vertices: vertex count ``V`` (defaults to ``faces.max() + 1``).
    """
    faces, n = _check_topology(faces, num_vertices)
    he, _, _ = _half_edges(faces)
    lo, hi = he.min(1).values, he.max(1).values
    key = lo * n + hi
    uniq, inverse, counts = torch.unique(key, sorted=True, return_inverse=True,
                                         return_counts=True)
    edges = torch.stack([uniq // n, uniq % n], 1)
    face_edges = inverse.view(3, -1).t().contiguous()
    return EdgeTopology(edges, face_edges, counts)


def face_adjacency(faces: Tensor, num_vertices: Optional[int] = None) -> FaceAdjacency:
    """Pairs of faces that share an edge (the hinges used by dihedral angles / bending).

    The ``3F`` half-edges are stably sorted by their undirected key; every two
    consecutive half-edges with the same key form one pair.  An interior manifold
    edge yields exactly one pair, a boundary edge none, and a non-manifold edge used
    by ``m > 2`` faces a chain of ``m - 1`` pairs.

    Args:
        faces: ``[F, 3]`` integer tensor.
        num_vertices: vertex count (defaults to ``faces.max() + 1``).
    """
    faces, n = _check_topology(faces, num_vertices)
    he, owner, opp = _half_edges(faces)
    key = he.min(1).values * n + he.max(1).values
    key_sorted, order = torch.sort(key, stable=True)
    same = key_sorted[1:] == key_sorted[:-1]
    i1, i2 = order[:-1][same], order[1:][same]
    return FaceAdjacency(torch.stack([owner[i1], owner[i2]], 1), he[i1],
                         torch.stack([opp[i1], opp[i2]], 1))


def boundary_vertex_mask(faces: Tensor, num_vertices: Optional[int] = None) -> Tensor:
    """``[V]`` bool, ``True`` for vertices on a boundary edge (an edge used by one face)."""
    topo = unique_edges(faces, num_vertices)
    n = int(num_vertices) if num_vertices is not None else int(faces.max()) + 1
    mask = torch.zeros(n, dtype=torch.bool, device=faces.device)
    b = topo.edges[topo.counts == 1].reshape(-1)
    mask[b] = True
    return mask
