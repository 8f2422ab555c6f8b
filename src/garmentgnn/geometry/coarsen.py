"""Coarse levels of a mesh graph over the same vertices, as HOOD's hierarchical message
passing has them (Grigorev, Thomaszewski, Black & Hilliges, CVPR 2023: each level a subset
of the vertices below, with longer edges); the rule that picks them is this module's.

A level's vertices are a maximal independent set of the level below (no two of them
neighbours there, every other vertex next to one of them), and two of them are joined
when they lie within ``hops`` edges of each other in the level below.  With ``hops = 3``
a level keeps the connected components of the one below (every vertex of a path lies
next to a chosen one, and the chosen ones of two neighbours are at most three edges
apart), and an edge of level ``l`` spans up to ``3^l`` mesh edges, so a few message-
passing steps over the coarse levels carry information across a whole garment.

The independent set is Luby's, with fixed ranks instead of random draws: a vertex joins
when its rank is below every undecided neighbour's, which needs a few rounds of tensor
operations (no Python loop over vertices; CPU or GPU).  Each rank is a hash of the
vertex's index *within its own graph* (``batch``), so a batch of garments gets exactly
the levels each garment gets alone.
"""
from __future__ import annotations

from typing import List, Optional

import torch
from torch import Tensor

__all__ = ["coarse_levels", "independent_set"]

#: Knuth's multiplicative hash (odd, so a bijection modulo 2^31): the ranks
_HASH = 2654435761
_MOD = 2 ** 31


def _local_index(num_nodes: int, batch: Optional[Tensor], device) -> Tensor:
    """Each node's index within its graph (``batch``: the graph of each node, sorted)."""
    idx = torch.arange(num_nodes, device=device)
    if batch is None:
        return idx
    if batch.shape != (num_nodes,):
        raise ValueError(f"`batch`: expected [{num_nodes}] (the graph of each node), got "
                         f"{list(batch.shape)}")
    if num_nodes and bool((batch[1:] < batch[:-1]).any()):
        raise ValueError("`batch`: expected the graphs' nodes in order (sorted), as PyG's "
                         "Batch gives them")
    counts = torch.bincount(batch)
    first = torch.cumsum(counts, 0) - counts
    return idx - first[batch]


def independent_set(edge_index: Tensor, num_nodes: int, mask: Optional[Tensor] = None,
                    batch: Optional[Tensor] = None) -> Tensor:
    """A maximal independent set ``[num_nodes]`` bool of the graph ``edge_index [2, E]``
    (both directions) on the nodes ``mask`` (default all; edges leaving it are ignored):
    Luby's rounds with ranks hashed from each node's index within its graph ``batch``."""
    device = edge_index.device
    mask = torch.ones(num_nodes, dtype=torch.bool, device=device) if mask is None else mask
    rank = (_local_index(num_nodes, batch, device) * _HASH + 12345) % _MOD
    src, dst = edge_index
    inside = mask[src] & mask[dst] & (src != dst)
    src, dst = src[inside], dst[inside]
    chosen = torch.zeros(num_nodes, dtype=torch.bool, device=device)
    undecided = mask.clone()
    while bool(undecided.any()):
        live = undecided[src] & undecided[dst]
        lowest = torch.full((num_nodes,), _MOD, dtype=rank.dtype, device=device)
        lowest = lowest.scatter_reduce(0, dst[live], rank[src[live]], "amin")
        won = undecided & (rank < lowest)
        chosen |= won
        covered = torch.zeros_like(chosen)
        covered[dst[won[src]]] = True
        undecided &= ~(won | covered)
    return chosen


def _within(edge_index: Tensor, num_nodes: int, keep: Tensor, hops: int) -> Tensor:
    """The pairs ``[2, E']`` of distinct nodes in ``keep`` at most ``hops`` edges apart in
    ``edge_index`` (both directions), sorted: a breadth-first expansion of every kept
    node's pairs, one hop a round."""
    n = num_nodes
    src, dst = edge_index
    order = torch.argsort(src)
    dst = dst[order]
    deg = torch.bincount(src, minlength=n)
    first = torch.cumsum(deg, 0) - deg
    u = v = keep.nonzero().squeeze(1)
    for _ in range(hops):
        d = deg[v]
        at = torch.arange(int(d.sum()), device=v.device) - (torch.cumsum(d, 0) - d
                                                            ).repeat_interleave(d)
        w = dst[first[v].repeat_interleave(d) + at]
        key = torch.cat([u * n + v, u.repeat_interleave(d) * n + w]).unique()
        u, v = key // n, key % n
    take = keep[v] & (u != v)
    return torch.stack([u[take], v[take]])


def coarse_levels(edge_index: Tensor, num_nodes: int, levels: int, hops: int = 3,
                  batch: Optional[Tensor] = None) -> List[Tensor]:
    """The edges ``[2, E_l]`` of each of ``levels`` coarse levels above the graph
    ``edge_index [2, E]`` (both directions), over its own node indices (module doc):
    level ``l``'s nodes are a maximal independent set of level ``l - 1``'s
    (:func:`independent_set`), joined within ``hops`` edges of level ``l - 1``.
    ``batch``: the graph of each node (a batch of garments gets each garment's levels)."""
    for name, v, low in (("levels", levels, 0), ("hops", hops, 1), ("num_nodes", num_nodes, 0)):
        if not isinstance(v, int) or isinstance(v, bool) or v < low:
            raise ValueError(f"`{name}`: expected an int >= {low}, got {v!r}")
    if edge_index.dim() != 2 or edge_index.shape[0] != 2:
        raise ValueError(f"`edge_index`: expected [2, E], got {list(edge_index.shape)}")
    if edge_index.numel() and not (0 <= int(edge_index.min())
                                   and int(edge_index.max()) < num_nodes):
        raise ValueError(f"`edge_index`: node indices outside [0, {num_nodes})")
    out: List[Tensor] = []
    edges, nodes = edge_index, None
    for _ in range(levels):
        nodes = independent_set(edges, num_nodes, nodes, batch)
        edges = _within(edges, num_nodes, nodes, hops)
        out.append(edges)
    return out
