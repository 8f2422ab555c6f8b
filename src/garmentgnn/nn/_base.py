"""Shared machinery of the dot-product attention layers in :mod:`garmentgnn.nn`."""
from __future__ import annotations

import math
from typing import Optional, Sequence, Tuple, Union

import torch
import torch.nn.functional as F
from torch import Tensor
from torch_geometric.nn.conv import MessagePassing
from torch_geometric.nn.dense.linear import Linear
from torch_geometric.nn.inits import reset

from garmentgnn.nn._graph import Graph, PairTensor, segment_sum
from garmentgnn.nn._sparse import csr_edge_spmm, csr_sddmm, csr_spmm, use_csr_kernels


class AttentionConv(MessagePassing):
    """Base class: fused projections, edge scores, value aggregation, head merge.

    Subclasses set ``heads``, ``out_channels``, ``concat``, ``lin_out`` and
    ``lin_skip`` (plus ``lin_query``, ``lin_key``, ``lin_value`` to use
    :meth:`project_qkv`) and call the helpers from ``forward``.  Every child
    module is re-initialised by :meth:`reset_parameters`.  Scores and value
    sums use the CSR sparse kernels of :mod:`garmentgnn.nn._sparse` when the
    edges are in CSR order (eager mode), and gathers plus segment/scatter
    reductions otherwise; both compute the same numbers and gradients.
    """

    heads: int
    out_channels: int
    concat: bool
    lin_out: Linear
    lin_skip: Optional[Linear]
    lin_query: Linear
    lin_key: Linear
    lin_value: Linear

    def __init__(self, **kwargs) -> None:
        kwargs.setdefault("aggr", "add")
        super().__init__(node_dim=0, **kwargs)

    def reset_parameters(self) -> None:
        """Re-initialise every child module, in registration order (recursing into containers)."""
        super().reset_parameters()
        for child in self.children():
            reset(child)

    def project(self, x: Tensor, lins: Sequence[Linear], scale_first: bool = False) -> Tuple[Tensor, ...]:
        """Apply several linear maps to the same ``x`` in one matmul.

        Returns one ``[N, H, C]`` view per map (no copy: the sparse kernels
        re-lay them out head-major, the gather path reads them strided); with
        ``scale_first`` the first (the queries) is scaled by ``1/sqrt(C)``,
        which folds the attention temperature into an N-sized tensor instead
        of an E-sized one.
        """
        H, C = self.heads, self.out_channels
        weight = torch.cat([lin.weight for lin in lins], 0)
        bias = torch.cat([lin.bias for lin in lins], 0) if lins[0].bias is not None else None
        if scale_first:
            s = torch.ones(weight.size(0), 1, dtype=weight.dtype, device=weight.device)
            s[: H * C] = 1.0 / math.sqrt(C)
            weight = weight * s
            bias = bias * s.squeeze(1) if bias is not None else None
        out = F.linear(x, weight, bias).view(x.size(0), len(lins), H, C)
        return out.unbind(1)

    def project_qkv(self, x: Union[Tensor, PairTensor]) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
        """Queries (scaled by ``1/sqrt(C)``) from the targets, keys and values from the sources.

        Returns ``(q, k, v, x_dst)``: for a single tensor all three in one
        fused matmul, for a bipartite pair ``(x_src, x_dst)`` one for ``q`` and
        one for ``k, v``.
        """
        if isinstance(x, Tensor):
            q, k, v = self.project(x, (self.lin_query, self.lin_key, self.lin_value), True)
            return q, k, v, x
        (q,) = self.project(x[1], (self.lin_query,), True)
        k, v = self.project(x[0], (self.lin_key, self.lin_value))
        return q, k, v, x[1]

    @staticmethod
    def edge_scores(q: Tensor, k: Tensor, g: Graph) -> Tensor:
        """``q_i . k_j`` per edge ``j -> i`` and head, ``[E, H]``."""
        if use_csr_kernels(g, q, k):
            return csr_sddmm(q, k, g)
        # contiguous first: gathering rows of a strided [N, H, C] view is several times slower
        q_i = q.contiguous().index_select(0, g.edge_index[1])
        return (q_i * k.contiguous().index_select(0, g.edge_index[0])).sum(-1)

    def aggregate_values(self, alpha: Tensor, v: Tensor, g: Graph) -> Tensor:
        """``sum_j alpha_ij v_j`` per head, ``[N_dst, H, C]``."""
        if use_csr_kernels(g, alpha, v):
            return csr_spmm(alpha, v, g)
        return self.propagate(g.edge_index, v=v.contiguous(), alpha=alpha, ptr_=g.ptr,
                              size=(g.num_src, g.num_dst))

    @staticmethod
    def aggregate_edges(alpha: Tensor, e: Tensor, g: Graph) -> Tensor:
        """``sum_j alpha_ij e_ij`` per head for edge values ``[E, D]``: ``[N_dst, H, D]``."""
        if use_csr_kernels(g, alpha, e):
            return csr_edge_spmm(alpha, e, g)
        return segment_sum(alpha.unsqueeze(-1) * e.unsqueeze(1), g.edge_index[1], g.ptr, g.num_dst)

    def merge_heads(self, out: Tensor, x_dst: Tensor) -> Tensor:
        """``W_o heads(out) + skip(x_dst)``: concatenate or average the heads."""
        out = out.reshape(out.size(0), -1) if self.concat else out.mean(1)
        out = self.lin_out(out)
        return out + (x_dst if self.lin_skip is None else self.lin_skip(x_dst))

    def message(self, v_j: Tensor, alpha: Tensor) -> Tensor:
        return v_j * alpha.unsqueeze(-1)

    def aggregate(self, inputs: Tensor, index: Tensor, ptr_: Optional[Tensor] = None,
                  dim_size: Optional[int] = None) -> Tensor:
        return segment_sum(inputs, index, ptr_, int(dim_size))
