"""The call contract every layer shares, and the machinery of the attention layers."""
from __future__ import annotations

import math
import typing
from typing import NamedTuple, Optional, Sequence, Tuple, Union, overload

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.nn.parameter import UninitializedParameter
from torch_geometric import is_compiling
from torch_geometric.nn.conv import MessagePassing
from torch_geometric.nn.dense.linear import Linear
from torch_geometric.nn.inits import reset
from torch_geometric.typing import Adj, OptTensor

from garmentgnn.nn._graph import (CSRPlan, Graph, PairTensor, check_inputs, check_outputs,
                                  edge_softmax, prepare_graph)
from garmentgnn.nn._sparse import (CSR_DTYPES, Pattern, head_pattern, incidence_pattern,
                                   kernels_enabled, sddmm, spmm)

_HOOKS = ("_propagate_forward_pre_hooks", "_propagate_forward_hooks",
          "_message_forward_pre_hooks", "_message_forward_hooks",
          "_aggregate_forward_pre_hooks", "_aggregate_forward_hooks",
          "_message_and_aggregate_forward_pre_hooks", "_message_and_aggregate_forward_hooks")


class LayerContract(MessagePassing):
    """The call contract of every :mod:`garmentgnn.nn` layer, as PyG's convs have it.

    ``layer(x, edge_index, edge_attr=None)`` returns the node output tensor.
    ``return_attention_weights`` (any bool, as in PyG) adds
    ``(edge_index, alpha)``; ``return_edge_attr=True`` adds the output edge
    features (the layer's new ones, or ``edge_attr`` as given for layers that
    do not update edges).  With both: ``(x_out, edge_attr_out, (edge_index, alpha))``.

    Subclasses set ``edge_dim``, ``validate``, ``check_finite`` and
    ``requires_edge_attr`` and implement :meth:`compute`.
    """

    edge_dim: Optional[int]
    validate: bool
    check_finite: bool
    requires_edge_attr: bool = False
    updates_edges: bool = False

    def compute(self, x: Union[Tensor, PairTensor],
                g: Graph) -> Tuple[Tensor, Optional[Tensor], Tuple[Tensor, Tensor]]:
        """``(x_out, edge_attr_out or None, (edge_index, alpha [E, H]))``, per-edge
        tensors in the caller's edge order."""
        raise NotImplementedError

    @overload
    def forward(self, x: Union[Tensor, PairTensor], edge_index: Adj,
                edge_attr: OptTensor = None, return_attention_weights: None = None,
                return_edge_attr: typing.Literal[False] = False) -> Tensor:
        pass

    @overload
    def forward(  # noqa: F811
            self, x: Union[Tensor, PairTensor], edge_index: Adj, edge_attr: OptTensor = None,
            return_attention_weights: bool = None,
            return_edge_attr: typing.Literal[False] = False) -> Tuple[Tensor, Tuple[Tensor, Tensor]]:
        pass

    @overload
    def forward(  # noqa: F811
            self, x: Union[Tensor, PairTensor], edge_index: Adj, edge_attr: OptTensor = None,
            return_attention_weights: None = None,
            return_edge_attr: typing.Literal[True] = True) -> Tuple[Tensor, OptTensor]:
        pass

    @overload
    def forward(  # noqa: F811
            self, x: Union[Tensor, PairTensor], edge_index: Adj, edge_attr: OptTensor = None,
            return_attention_weights: bool = None, return_edge_attr: typing.Literal[True] = True,
    ) -> Tuple[Tensor, OptTensor, Tuple[Tensor, Tensor]]:
        pass

    def forward(  # noqa: F811
        self,
        x: Union[Tensor, PairTensor],
        edge_index: Adj,
        edge_attr: OptTensor = None,
        return_attention_weights: Optional[bool] = None,
        return_edge_attr: bool = False,
    ) -> Union[Tensor, Tuple[Tensor, OptTensor], Tuple[Tensor, Tuple[Tensor, Tensor]],
               Tuple[Tensor, OptTensor, Tuple[Tensor, Tensor]]]:
        """Run the layer.

        Args:
            x: node features ``[N, F_in]``, or ``(x_src, x_dst)`` for a bipartite graph.
            edge_index: ``[2, E]`` (source, target) indices in any order, an
                :class:`~torch_geometric.EdgeIndex`, or a sparse ``adj_t``.
            edge_attr: ``[E, edge_dim]`` edge features in ``edge_index`` order.
            return_attention_weights: if set to a bool (either value, as in
                PyG), also return ``(edge_index, alpha)`` with ``alpha [E, H]``
                in ``edge_index`` order.
            return_edge_attr: also return the output edge features.

        Returns:
            ``x_out``; ``(x_out, edge_attr_out)`` with ``return_edge_attr``;
            ``(x_out, (edge_index, alpha))`` with ``return_attention_weights``;
            ``(x_out, edge_attr_out, (edge_index, alpha))`` with both.
        """
        if not is_compiling():
            check_inputs(self, x, edge_index, edge_attr)
        g = prepare_graph(x, edge_index, edge_attr, self.edge_dim,
                          require_edge_attr=self.requires_edge_attr, validate=self.validate)
        out, e_out, attention = self.compute(x, g)
        if self.check_finite and not is_compiling():
            xs = (("x", x),) if isinstance(x, Tensor) else (("x", x[0]), ("x", x[1]))
            check_outputs(type(self).__name__, (out, e_out), xs + (("edge_attr", g.edge_attr),))
        if e_out is None:  # the caller's edge features as given (or a hybrid adj_t's values)
            e_out = edge_attr if edge_attr is not None else g.edge_attr
        if isinstance(return_attention_weights, bool):
            if return_edge_attr:
                return out, e_out, attention
            return out, attention
        if return_edge_attr:
            return out, e_out
        return out


class Route(NamedTuple):
    """How one call runs: on the CSR kernels (``plan`` set) or by message passing.

    Per-edge, per-head tensors come in the route's working layout: ``[E, H]``
    in the caller's edge order on the message route, a flat head-major
    ``[H*E]`` vector in CSR order on the fused route (the value layout of the
    kernels' block-diagonal pattern).  ``index`` is the segment (target, or
    (head, target) row) of every working entry, ``ptr`` the CSR offsets of
    those segments when they are sorted, ``num_segments`` their number.
    """

    plan: Optional[CSRPlan]
    heads: int
    index: Tensor
    ptr: Optional[Tensor]
    num_segments: int
    pattern: Optional[Pattern]

    def edges_in(self, t: Tensor) -> Tensor:
        """``[E, H]`` in the caller's order -> working layout."""
        if self.plan is None:
            return t
        t = t.t()
        return (t if self.plan.perm is None else t.index_select(1, self.plan.perm)).reshape(-1)

    def edges_out(self, t: Tensor) -> Tensor:
        """Working layout -> ``[E, H]`` in the caller's order."""
        if self.plan is None:
            return t
        t = t.view(self.heads, -1)
        return (t if self.plan.inv is None else t.index_select(1, self.plan.inv)).t()


class AttentionConv(LayerContract):
    """Base class: fused projections, edge scores, value aggregation, head merge.

    Every call takes one of two routes that compute the same numbers:

    * the **fused** route (eager mode, float32/float64, nothing observing the
      messages): scores as a sparse SDDMM and sums as SpMMs over all heads on
      the graph's CSR pattern (edges sorted internally, once per graph);
    * the **message** route: :meth:`propagate` with per-edge messages, in
      the caller's edge order.  It runs under ``torch.compile``, for
      bfloat16/float16, when an explainer masks edges (``explain``), when
      any message-passing hook is registered, and on graphs without edges,
      so masks and hooks see every message exactly as PyG's convs show them.
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

    def skip_layer(self, in_dst: int, out_width: int, bias: bool) -> Optional[Linear]:
        """Identity skip when the widths match, else a linear map (always one when
        ``in_dst`` is lazy (-1): the width is unknown until the first call)."""
        return None if in_dst == out_width else Linear(in_dst, out_width, bias=bias)

    # ------------------------------------------------------------------ projections
    def project(self, x: Tensor, lins: Sequence[Linear], scale_first: bool = False
                ) -> Tuple[Tensor, ...]:
        """Apply several linear maps to the same ``x`` in one matmul.

        Returns one ``[N, H, C]`` view per map; with ``scale_first`` the first
        (the queries) is scaled by ``1/sqrt(C)``, which folds the attention
        temperature into an N-sized tensor instead of an E-sized one.  Lazy
        maps (``in_channels=-1``) are initialised from ``x`` first.
        """
        H, C = self.heads, self.out_channels
        for lin in lins:
            if isinstance(lin.weight, UninitializedParameter):
                lin.initialize_parameters(lin, (x,))
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

    # ------------------------------------------------------------------ routing
    def observed(self) -> bool:
        """True when an explainer or a hook needs the per-edge messages."""
        return bool(self.explain) or any(len(getattr(self, h)) > 0 for h in _HOOKS)

    def route(self, g: Graph, *operands: Tensor) -> Route:
        plan, H = g.plan, self.heads
        # more edges than (source, target) pairs: multi-edges that torch's sparse CSR
        # sampling cannot hold (it needs nnz <= rows * cols); the message route can
        if (plan is None or not kernels_enabled() or plan.num_edges == 0 or self.observed()
                or plan.num_edges > plan.num_src * plan.num_dst
                or any(t.dtype not in CSR_DTYPES for t in operands)):
            return Route(None, H, g.edge_index[1], None, g.num_dst, None)
        pat = head_pattern(plan, H)
        return Route(plan, H, pat.rows, pat.ptr, H * g.num_dst, pat)

    # ------------------------------------------------------------------ attention steps
    @staticmethod
    def edge_scores(q: Tensor, k: Tensor, g: Graph, r: Route) -> Tensor:
        """``q_i . k_j`` per edge ``j -> i`` and head, in the working layout."""
        if r.pattern is not None:
            H, C = q.size(1), q.size(2)
            qs = q.transpose(0, 1).reshape(H * g.num_dst, C)
            ks = k.transpose(0, 1).reshape(H * g.num_src, C)
            return sddmm(qs, ks, r.pattern)
        # contiguous first: gathering rows of a strided [N, H, C] view is several times slower
        q_i = q.contiguous().index_select(0, g.edge_index[1])
        return (q_i * k.contiguous().index_select(0, g.edge_index[0])).sum(-1)

    @staticmethod
    def softmax(scores: Tensor, r: Route) -> Tensor:
        """Softmax over each target's incoming edges, per head (working layout)."""
        return edge_softmax(scores, r.index, r.num_segments, r.ptr)

    def aggregate_values(self, alpha: Tensor, v: Tensor, g: Graph, r: Route,
                         **messages: Tensor) -> Tensor:
        """``sum_j alpha_ij v_j`` per head, ``[N_dst, H, C]``; ``messages`` are the
        extra per-edge arguments of :meth:`message` (message route only)."""
        if r.pattern is not None:
            H, C = v.size(1), v.size(2)
            out = spmm(alpha, v.transpose(0, 1).reshape(H * g.num_src, C), r.pattern)
            return out.view(H, g.num_dst, C).transpose(0, 1)
        return self.propagate(g.edge_index, v=v, alpha=alpha, size=(g.num_src, g.num_dst),
                              **messages)

    @staticmethod
    def aggregate_edge_rows(alpha: Tensor, y: Tensor, g: Graph, r: Route) -> Tensor:
        """``sum_j alpha_ij y_ij`` per head for edge rows ``y [E, D]`` in the caller's
        order: ``[N_dst, H, D]`` (fused route only)."""
        assert r.plan is not None
        out = spmm(alpha, y, incidence_pattern(r.plan, r.heads))
        return out.view(r.heads, g.num_dst, -1).transpose(0, 1)

    def merge_heads(self, out: Tensor, x_dst: Tensor) -> Tensor:
        """``W_o heads(out) + skip(x_dst)``: concatenate or average the heads."""
        out = out.reshape(out.size(0), self.heads * self.out_channels) if self.concat \
            else out.mean(1)
        lin, skip = self.lin_out, self.lin_skip
        lazy = any(isinstance(p, UninitializedParameter)
                   for m in (lin, skip) if m is not None for p in m.parameters())
        if lazy or torch.is_autocast_enabled(out.device.type):  # autocast: per-op dtypes
            return lin(out) + (x_dst if skip is None else skip(x_dst))
        # residual (and both biases) first, then one matmul accumulating into it:
        # one pass over the output fewer than linear + add
        b = lin.bias
        if skip is None:
            base = x_dst + b if b is not None else x_dst.clone()
        else:
            sb = skip.bias
            base = F.linear(x_dst, skip.weight, sb if b is None else (b if sb is None else sb + b))
        return base.addmm_(out, lin.weight.t())

    def message(self, v_j: Tensor, alpha: Tensor) -> Tensor:
        return v_j * alpha.unsqueeze(-1)
