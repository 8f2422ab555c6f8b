"""Mesh connectivity and a procedural sheet mesh."""
from __future__ import annotations

from typing import Tuple

import torch
from torch import Tensor
from torch_geometric.utils import sort_edge_index, to_undirected


def faces_to_edge_index(faces: Tensor, num_nodes: int) -> Tensor:
    """Directed graph of a triangle mesh: both directions of every unique edge.

    Args:
        faces: ``[F, 3]`` long tensor of vertex indices.
        num_nodes: number of mesh vertices.

    Returns:
        ``[2, E]`` edge index, coalesced and sorted by target (column 1), the
        CSR order that lets :mod:`garmentgnn.nn` layers use segment reductions.
    """
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
    """Per-edge ``[length, unit direction (3)]`` features, ``[E, 4]``."""
    d = pos.index_select(0, edge_index[1]) - pos.index_select(0, edge_index[0])
    length = d.norm(dim=-1, keepdim=True)
    return torch.cat([length, d / length.clamp_min(1e-12)], -1)
