"""The graph-attention steps the layers are written with, as PyG's convs use
:func:`torch_geometric.utils.softmax` and :func:`torch_geometric.utils.spmm`.

A layer turns its inputs into a :class:`Graph` with :func:`prepare_graph` (which also
builds, or finds in its cache, the graph's :class:`CSRPlan`: the edges sorted by target,
once per ``edge_index`` tensor; :func:`build_plan` builds one directly), picks a
:class:`Route` per call with :func:`attention_route`, then writes its equation with
these functions:

=========================  ==================================================  ===================
function                   computes, per edge ``j -> i`` and head             fused route kernel
=========================  ==================================================  ===================
:func:`edge_dot`           ``q_i . k_j``                                       SDDMM
:func:`edge_softmax`       ``softmax_{j in N(i)} s_ij``                        segment max + sums
:func:`random_edge_mask`   ``-inf`` on random scores, one kept per target      --
:func:`attention_spmm`     ``sum_j alpha_ij v_j`` (node rows ``v [N, H, C]``)  SpMM
:func:`edge_rows_spmm`     ``sum_j alpha_ij y_ij`` (edge rows ``y [E, D]``)    SpMM (incidence)
=========================  ==================================================  ===================

Two routes compute the same numbers:

* the **fused** route (``route.fused``; eager mode, float32/float64 or any dtype under
  autocast, nothing observing the messages) runs on the sparse CSR kernels of
  :mod:`garmentgnn.nn._sparse` (in float32 for half-precision operands), all
  heads in one node-major pattern (row ``i*H + h``), on the graph's cached
  :class:`CSRPlan` (edges sorted by target once per ``edge_index`` tensor, whatever the
  caller's order);
* the **message** route gathers per edge in the caller's order, and the layer sums
  with :meth:`~torch_geometric.nn.conv.MessagePassing.propagate` and its ``message``,
  so explainers' edge masks and message hooks see every message as in PyG's convs.
  It runs under ``torch.compile``, in half precision outside autocast, when messages
  are observed, and on graphs without edges.

Per-edge, per-head tensors come in the route's working layout: ``[E, H]`` in the
caller's edge order on the message route, a flat ``[E*H]`` vector in the kernels' order
on the fused route (target by target, then head, then the target's edges in CSR
order); :meth:`Route.edges_in` and :meth:`Route.edges_out` convert from and to
``[E, H]`` in the caller's order.  ``csr_kernels(False)`` forces the
message route (tests, benchmarks).
"""
from __future__ import annotations

from typing import NamedTuple, Optional

import torch
from torch import Tensor
from torch_geometric.utils import scatter, softmax

from garmentgnn.nn._graph import CSRPlan, Graph, build_plan, prepare_graph
from garmentgnn.nn._sparse import (CSR_DTYPES, Pattern, csr_kernels, head_pattern,
                                   incidence_pattern, kernels_enabled, sddmm, spmm)

__all__ = ["Graph", "CSRPlan", "prepare_graph", "build_plan", "Route", "attention_route",
           "edge_dot", "edge_softmax", "random_edge_mask", "attention_spmm", "edge_rows_spmm",
           "segment_softmax", "keep_one_mask", "csr_kernels", "sddmm", "spmm"]


class Route(NamedTuple):
    """How one call runs: on the CSR kernels (``plan`` set) or by message passing.

    ``index`` is the segment (target, or (target, head) row) of every working
    entry, ``ptr`` the CSR offsets of those segments when they are sorted,
    ``num_segments`` their number, ``pattern`` the kernels' node-major head
    pattern (fused route only).
    """

    plan: Optional[CSRPlan]
    heads: int
    index: Tensor
    ptr: Optional[Tensor]
    num_segments: int
    pattern: Optional[Pattern]

    @property
    def fused(self) -> bool:
        """True on the sparse-kernel route."""
        return self.plan is not None

    def edges_in(self, t: Tensor) -> Tensor:
        """``[E, H]`` in the caller's order -> working layout."""
        if self.pattern is None:
            return t
        t = t.reshape(-1)
        idx = self.pattern.from_caller
        return t if idx is None else t.index_select(0, idx)

    def edges_out(self, t: Tensor) -> Tensor:
        """Working layout -> ``[E, H]`` in the caller's order."""
        if self.pattern is None:
            return t
        idx = self.pattern.to_caller
        return (t if idx is None else t.index_select(0, idx)).view(-1, self.heads)


def attention_route(g: Graph, heads: int, *operands: Tensor, observed: bool = False) -> Route:
    """The route of one call on ``g`` with ``heads`` heads: fused unless the kernels are
    off, the graph has no plan (``torch.compile``) or no edges, ``observed`` (an
    explainer or hook needs the messages), or an operand's dtype has no CSR kernel
    outside autocast.  Under autocast, half-precision operands run on the kernels in
    float32 (:func:`~garmentgnn.nn._sparse.spmm`): the ops that follow pick their own
    dtypes, where a model cast to half precision would meet float32 results."""
    plan = g.plan
    # more edges than (source, target) pairs: multi-edges that torch's sparse CSR
    # sampling cannot hold (it needs nnz <= rows * cols); the message route can
    if (plan is None or not kernels_enabled() or plan.num_edges == 0 or observed
            or plan.num_edges > plan.num_src * plan.num_dst
            or any(t.dtype not in CSR_DTYPES and not torch.is_autocast_enabled(t.device.type)
                   for t in operands)):
        return Route(None, heads, g.edge_index[1], None, g.num_dst, None)
    pat = head_pattern(plan, heads)
    assert pat.rows is not None
    return Route(plan, heads, pat.rows, pat.ptr, heads * g.num_dst, pat)


def edge_dot(q: Tensor, k: Tensor, g: Graph, r: Route) -> Tensor:
    """``q_i . k_j`` per edge ``j -> i`` and head (``q [N_dst, H, C]``, ``k [N_src, H, C]``),
    in the working layout: one SDDMM over all heads on the fused route."""
    if r.pattern is not None:
        C = q.size(2)
        return sddmm(q.reshape(-1, C), k.reshape(-1, C), r.pattern)
    # contiguous first: gathering rows of a strided [N, H, C] view is several times slower
    q_i = q.contiguous().index_select(0, g.edge_index[1])
    return (q_i * k.contiguous().index_select(0, g.edge_index[0])).sum(-1)


def segment_softmax(src: Tensor, index: Tensor, num_segments: int,
                    ptr: Optional[Tensor] = None) -> Tensor:
    """Softmax of ``src`` over the entries of each segment (``index``: segment of each row).

    With a CSR pointer (entries sorted by segment) the maximum runs on
    :func:`torch.segment_reduce` (several times faster on CPU than a scatter); the
    sums use ``index_add``, which, unlike ``segment_reduce``, can be differentiated
    twice.  Without one it is PyG's :func:`~torch_geometric.utils.softmax`.  Entries of
    ``-inf`` get weight 0 as long as their segment holds a finite one.
    """
    if ptr is None:
        return softmax(src, index, None, num_segments)
    peak = torch.segment_reduce(src.detach(), "max", offsets=ptr, axis=0, unsafe=True)
    out = (src - peak.index_select(0, index)).exp()
    total = out.new_zeros((num_segments,) + tuple(out.shape[1:])).index_add_(0, index, out)
    return out / (total.index_select(0, index) + 1e-16)


def edge_softmax(scores: Tensor, r: Route) -> Tensor:
    """``softmax_{j in N(i)} s_ij``: over each target's incoming edges, per head
    (working layout in and out)."""
    return segment_softmax(scores, r.index, r.num_segments, r.ptr)


def keep_one_mask(mask: Tensor, index: Tensor, num_segments: int) -> Tensor:
    """``mask`` (boolean, entries to drop) with one entry per segment, drawn uniformly
    at random, always kept, so a softmax over the masked scores never sees only
    ``-inf``."""
    u = torch.rand(mask.shape, device=mask.device)
    u_max = scatter(u, index, dim=0, dim_size=num_segments, reduce="max")
    keep = u == u_max.index_select(0, index)
    return mask & ~keep


def random_edge_mask(scores: Tensor, p: float, r: Route) -> Tensor:
    """Random attention masking: each score becomes ``-inf`` with probability ``p``,
    except one incoming edge per (target, head), drawn uniformly, which is always kept."""
    drop = torch.rand_like(scores) < p
    return scores.masked_fill(keep_one_mask(drop, r.index, r.num_segments), float("-inf"))


def attention_spmm(alpha: Tensor, v: Tensor, g: Graph, r: Route) -> Tensor:
    """``sum_j alpha_ij v_j`` per head, ``[N_dst, H, C]`` from ``v [N_src, H, C]``: one
    SpMM over all heads (fused route only; the message route calls ``propagate``)."""
    if r.pattern is None:
        raise ValueError("`r`: attention_spmm runs on the fused route; on the message "
                         "route sum the messages with propagate()")
    out = spmm(alpha, v.reshape(-1, v.size(2)), r.pattern)
    return out.view(g.num_dst, v.size(1), -1)


def edge_rows_spmm(alpha: Tensor, y: Tensor, g: Graph, r: Route) -> Tensor:
    """``sum_j alpha_ij y_ij`` per head for edge rows ``y [E, D]`` in the caller's order:
    ``[N_dst, H, D]``, without permuting ``y`` (fused route only)."""
    if r.plan is None:
        raise ValueError("`r`: edge_rows_spmm runs on the fused route only")
    out = spmm(alpha, y, incidence_pattern(r.plan, r.heads))
    return out.view(g.num_dst, r.heads, -1)
