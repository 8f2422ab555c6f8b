"""The call contract every layer shares, and the machinery of the attention layers."""
from __future__ import annotations

import math
from typing import Optional, Sequence, Tuple, Union

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.nn.parameter import UninitializedParameter
from torch_geometric import is_compiling
from torch_geometric.nn.conv import MessagePassing
from torch_geometric.nn.dense.linear import Linear
from torch_geometric.nn.inits import reset
from torch_geometric.typing import Adj, OptTensor, PairTensor

from garmentgnn.nn._graph import Graph, check_inputs, check_outputs, prepare_graph
from garmentgnn.nn.functional import Route, attention_route

_HOOKS = ("_propagate_forward_pre_hooks", "_propagate_forward_hooks",
          "_message_forward_pre_hooks", "_message_forward_hooks",
          "_aggregate_forward_pre_hooks", "_aggregate_forward_hooks",
          "_message_and_aggregate_forward_pre_hooks", "_message_and_aggregate_forward_hooks")


#: what a layer's ``forward`` returns (see :meth:`LayerContract.outputs`)
LayerOutput = Union[Tensor, Tuple[Tensor, OptTensor], Tuple[Tensor, Tuple[Tensor, Tensor]],
                    Tuple[Tensor, OptTensor, Tuple[Tensor, Tensor]]]


class LayerContract(MessagePassing):
    """The call contract of every :mod:`garmentgnn.nn` layer, as PyG's convs have it.

    ``layer(x, edge_index, edge_attr=None)`` returns the node output tensor.
    ``return_attention_weights`` (any bool, as in PyG) adds
    ``(edge_index, alpha)``; ``return_edge_attr=True`` adds the output edge
    features (the layer's new ones, or ``edge_attr`` as given for layers that
    do not update edges).  With both: ``(x_out, edge_attr_out, (edge_index, alpha))``.

    Every layer's ``forward(x, edge_index, edge_attr=None, return_attention_weights=None,
    return_edge_attr=False)`` takes:

    * ``x``: node features ``[N, F_in]``, or ``(x_src, x_dst)`` for a bipartite graph;
    * ``edge_index``: ``[2, E]`` (source, target) indices in any order, an
      :class:`~torch_geometric.EdgeIndex`, or a sparse ``adj_t``;
    * ``edge_attr``: ``[E, edge_dim]`` edge features in ``edge_index`` order;
    * ``return_attention_weights``: if set to a bool (either value, as in PyG), also
      return ``(edge_index, alpha)`` with ``alpha [E, H]`` in ``edge_index`` order;
    * ``return_edge_attr``: also return the output edge features.

    It begins with :meth:`prepare` (checks, the graph's cached CSR plan) and ends with
    :meth:`outputs` (the finite check and the return value).  Subclasses set
    ``edge_dim``, ``validate``, ``check_finite`` and ``requires_edge_attr``.
    """

    edge_dim: Optional[int]
    validate: bool
    check_finite: bool
    requires_edge_attr: bool = False
    updates_edges: bool = False
    #: submodules that only the output edge features read: a stack that never reads the
    #: last layer's edge output leaves their parameters without a gradient
    #: (:meth:`edge_output_parameters`)
    edge_output_modules: Tuple[str, ...] = ()

    def edge_output_parameters(self):
        """The parameters that only the output edge features read (the layer's
        ``edge_output_modules``); none for a layer that does not update edges."""
        for name in self.edge_output_modules:
            module = getattr(self, name, None)
            if module is not None:
                yield from module.parameters()

    def prepare(self, x: Union[Tensor, PairTensor], edge_index: Adj,
                edge_attr: OptTensor) -> Graph:
        """Check the inputs and normalise them to a :class:`~garmentgnn.nn._graph.Graph`
        (``edge_index`` in the caller's order, its cached CSR plan)."""
        if not is_compiling():
            check_inputs(self, x, edge_index, edge_attr)
        return prepare_graph(x, edge_index, edge_attr, self.edge_dim,
                             require_edge_attr=self.requires_edge_attr, validate=self.validate)

    def outputs(self, x: Union[Tensor, PairTensor], g: Graph, edge_attr: OptTensor,
                out: Tensor, e_out: OptTensor, attention: Tuple[Tensor, Tensor],
                return_attention_weights: Optional[bool],
                return_edge_attr: bool) -> LayerOutput:
        """The finite check (``check_finite``) and the return value of ``forward``.

        ``e_out`` is the layer's new edge features, or ``None`` for the caller's
        ``edge_attr`` as given (or a hybrid ``adj_t``'s values); ``attention`` is
        ``(edge_index, alpha [E, H])`` in the caller's edge order."""
        if self.check_finite and not is_compiling():
            xs = (("x", x),) if isinstance(x, Tensor) else (("x", x[0]), ("x", x[1]))
            check_outputs(type(self).__name__, (out, e_out), xs + (("edge_attr", g.edge_attr),))
        if e_out is None:
            e_out = edge_attr if edge_attr is not None else g.edge_attr
        if isinstance(return_attention_weights, bool):
            if return_edge_attr:
                return out, e_out, attention
            return out, attention
        if return_edge_attr:
            return out, e_out
        return out


class AttentionConv(LayerContract):
    """Base class of the dot-product attention layers: the fused ``q, k, v``
    projections (:meth:`project_qkv`), the choice of route (:meth:`route`) and the head
    merge with the skip (:meth:`merge_heads`).  The per-edge steps (scores, softmax,
    sums) are the functions of :mod:`garmentgnn.nn.functional`, which also explains the
    two routes (sparse kernels, or :meth:`propagate` with the layer's ``message``) that
    compute the same numbers.
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
        """Apply several linear maps to the same ``x``.

        Returns one contiguous ``[N, H, C]`` per map (the sparse kernels' node-major
        operands as they are: one matmul per map, not one stacked matmul whose
        outputs would be strided views); with ``scale_first`` the first (the queries)
        is scaled by ``1/sqrt(C)``, which folds the attention temperature into an
        N-sized tensor instead of an E-sized one.  Lazy maps (``in_channels=-1``) are
        initialised from ``x`` first.
        """
        H, C = self.heads, self.out_channels
        out = []
        for i, lin in enumerate(lins):
            if isinstance(lin.weight, UninitializedParameter):
                lin.initialize_parameters(lin, (x,))
            weight, bias = lin.weight, lin.bias
            if scale_first and i == 0:
                s = 1.0 / math.sqrt(C)
                weight, bias = weight * s, (bias * s if bias is not None else None)
            out.append(F.linear(x, weight, bias).view(x.size(0), H, C))
        return tuple(out)

    def project_qkv(self, x: Union[Tensor, PairTensor]) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
        """Queries (scaled by ``1/sqrt(C)``) from the targets, keys and values from the sources.

        Returns ``(q, k, v, x_dst)`` (:meth:`project`; ``q`` from ``x_dst``, ``k, v``
        from ``x_src`` for a bipartite pair ``(x_src, x_dst)``).
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
        """This call's route (:func:`~garmentgnn.nn.functional.attention_route`)."""
        return attention_route(g, self.heads, *operands, observed=self.observed())

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
