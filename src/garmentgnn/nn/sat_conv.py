"""Structure-augmented transformer convolution (GarTrans, Eqs. 5-6)."""
from __future__ import annotations

from typing import Optional, Tuple, Union

import torch
import torch.nn.functional as F
from torch import Tensor
from torch_geometric.nn.dense.linear import Linear
from torch_geometric.typing import Adj, OptTensor, PairTensor

from garmentgnn.nn._base import AttentionConv, LayerOutput
from garmentgnn.nn._graph import Graph, check_edge_out_channels, check_layer_args
from garmentgnn.nn.functional import (Route, attention_spmm, edge_dot, edge_rows_spmm,
                                      edge_softmax, random_edge_mask)


class SATConv(AttentionConv):
    r"""The structure-augmented transformer (SAT) layer of GarTrans
    (Li et al., *GarTrans*, Eqs. (5)-(6)).

    For every edge :math:`j \to i` and head :math:`h` with :math:`C` channels:

    .. math::
        \mathbf{q}_i = \mathbf{W}_q \mathbf{x}_i,\quad
        \mathbf{k}_j = \mathbf{W}_k \mathbf{x}_j,\quad
        \mathbf{v}_j = \mathbf{W}_v \mathbf{x}_j,\quad
        p_{ij} = \mathbf{W}_p \mathbf{e}_{ij},\quad
        \mathbf{q}^e_{ij} = \mathbf{W}_{q'} \mathbf{e}_{ij}

    .. math::
        h_{ij} = \frac{\mathbf{q}_i^\top \mathbf{k}_j}{\sqrt{C}}\,
        \sigma(p_{ij}), \qquad
        \alpha_{ij} = \operatorname{softmax}_{j \in \mathcal{N}(i)} h_{ij}

    .. math::
        \mathbf{x}'_i = \mathbf{W}_o\,\big\Vert_h
        \sum_{j \in \mathcal{N}(i)} \alpha_{ij}
        (\mathbf{v}_j + \mathbf{q}^e_{ij}) + \mathrm{skip}(\mathbf{x}_i),
        \qquad
        \mathbf{e}'_{ij} = \mathbf{W}_e\,\mathbf{h}_{ij} + \mathrm{skip}(\mathbf{e}_{ij})

    where :math:`\Vert_h` concatenates the heads (or averages them when
    ``concat=False``), :math:`\mathbf{h}_{ij} \in \mathbb{R}^H` stacks the
    per-head scores, and each skip is the identity when the widths match and
    a linear map otherwise (the paper's "additional linear transformation on
    the residual connection").  The activation (the paper uses ELU) is left
    to the caller.

    Implementation: the value term uses linearity,
    :math:`\sum_j \alpha_{ij}\mathbf{W}_{q'}\mathbf{e}_{ij} =
    \mathbf{W}_{q'} \sum_j \alpha_{ij}\mathbf{e}_{ij}`, so on the fused
    route the per-head edge values are never materialised per edge; only the
    narrow edge features are aggregated (sparse SpMM over an incidence
    pattern), and the scores are a sparse SDDMM over all heads.  Edges in any
    order get this route: the layer sorts them once per graph (cached).  When
    something observes the messages (an explainer's edge mask, a message
    hook), under ``torch.compile`` and in half precision outside autocast
    (under autocast the kernels run in float32) the layer runs
    :meth:`propagate` with the full messages
    :math:`\alpha_{ij}(\mathbf{v}_j + \mathbf{q}^e_{ij})` instead; both
    routes compute the same numbers.

    Not to be confused with the *Structure-Aware Transformer* (also "SAT")
    of Chen et al. (2022): that one is
    :class:`~garmentgnn.nn.StructureAwareTransformerConv`.

    Args:
        in_channels (int or tuple): input width, or ``(src, dst)`` widths for
            bipartite graphs; ``-1`` infers it from the first call.
        out_channels (int): channels per head, :math:`C`.
        heads (int): number of heads :math:`H`.
        concat (bool): concatenate heads (output ``H * C``) or average them
            (output ``C``).
        edge_dim (int): input edge feature width (required, keyword).
        edge_out_channels (int, optional): width of the returned edge
            features; defaults to ``edge_dim`` (identity edge skip).
        dropout (float): dropout on the attention coefficients (training).
        attn_mask_p (float): probability of adding :math:`-\infty` to a score
            during training (the paper's random attention masking).  One
            incoming edge per node and head is always kept, so no NaN appears
            even at ``attn_mask_p=1``.
        bias (bool): learn additive biases.
        validate (bool): kept for PyG-style signatures: the index range is
            checked once per graph either way (the sparse kernels need it).
        check_finite (bool): raise ``ValueError`` when the output holds
            NaN/inf, naming the bad input or the overflow (one host sync per
            call; skipped under ``torch.compile``).

    Shapes:
        - **input:** ``x`` :math:`(|V|, F_{in})` or a pair,
          ``edge_index`` :math:`(2, |E|)` or sparse ``adj_t``,
          ``edge_attr`` :math:`(|E|, D)`
        - **output:** :math:`(|V|, H C)` (or :math:`(|V|, C)`); see
          :class:`~garmentgnn.nn._base.LayerContract` for
          ``return_edge_attr`` (edge features :math:`(|E|, D')`) and
          ``return_attention_weights`` (:math:`(|E|, H)`).
    """

    #: the name :func:`~garmentgnn.nn.make_layer` and the recipes know it by
    layer_name = "sat"

    requires_edge_attr = True
    updates_edges = True
    edge_output_modules = ("lin_edge_out", "lin_edge_skip")

    def __init__(
        self,
        in_channels: Union[int, Tuple[int, int]],
        out_channels: int,
        heads: int = 1,
        concat: bool = True,
        *,
        edge_dim: Optional[int] = None,
        edge_out_channels: Optional[int] = None,
        dropout: float = 0.0,
        attn_mask_p: float = 0.0,
        bias: bool = True,
        validate: bool = True,
        check_finite: bool = True,
        **kwargs,
    ) -> None:
        super().__init__(**kwargs)
        in_src, in_dst = check_layer_args(in_channels, out_channels, heads, edge_dim, dropout,
                                          edge_dim_required=True)
        assert edge_dim is not None
        if not (isinstance(attn_mask_p, (int, float)) and 0.0 <= attn_mask_p <= 1.0):
            raise ValueError(f"`attn_mask_p` must lie in [0, 1], got {attn_mask_p!r}")
        check_edge_out_channels(edge_out_channels)

        self.in_channels = in_channels
        self.out_channels = out_channels
        self.edge_dim = edge_dim
        self.heads = heads
        self.concat = concat
        self.edge_out_channels = edge_out_channels or edge_dim
        self.dropout = dropout
        self.attn_mask_p = attn_mask_p
        self.validate = validate
        self.check_finite = check_finite

        H, C = heads, out_channels
        out_width = H * C if concat else C
        self.lin_query = Linear(in_dst, H * C, bias=bias)
        self.lin_key = Linear(in_src, H * C, bias=bias)
        self.lin_value = Linear(in_src, H * C, bias=bias)
        self.lin_edge_gate = Linear(edge_dim, H, bias=bias)  # W_p: one gate per head
        self.lin_edge_value = Linear(edge_dim, H * C, bias=bias)  # W_q'
        self.lin_out = Linear(out_width, out_width, bias=bias)  # W_o
        self.lin_edge_out = Linear(H, self.edge_out_channels, bias=bias)  # W_e
        self.lin_skip = self.skip_layer(in_dst, out_width, bias)
        self.lin_edge_skip = (None if edge_dim == self.edge_out_channels
                              else Linear(edge_dim, self.edge_out_channels, bias=bias))
        self.reset_parameters()

    def forward(
        self,
        x: Union[Tensor, PairTensor],
        edge_index: Adj,
        edge_attr: OptTensor = None,
        return_attention_weights: Optional[bool] = None,
        return_edge_attr: bool = False,
    ) -> LayerOutput:
        """Run the layer; arguments and return values as in
        :class:`~garmentgnn.nn._base.LayerContract`."""
        g = self.prepare(x, edge_index, edge_attr)  # checks; edges sorted once per graph
        e = g.edge_attr
        assert e is not None
        H, C = self.heads, self.out_channels
        # Eqs. (3)-(4): q_i = W_q x_i + b_q,  k_j = W_k x_j + b_k,  v_j = W_v x_j + b_v
        # (one matmul; q_i comes scaled by 1/sqrt(d_a))
        q, k, v, x_dst = self.project_qkv(x)
        r = self.route(g, q, e)  # sparse kernels, or propagate() with message()

        # Eq. (5): p_ij = W_p e_ij + b_p  (one gate per head)
        p = self.lin_edge_gate(e)
        # Eq. (5): h_ij = q_i^T k_j / sqrt(d_a) * sigmoid(p_ij)
        h = edge_dot(q, k, g, r) * r.edges_in(torch.sigmoid(p))
        # random attention masking while training: -inf on a few scores (§3.3)
        logits = random_edge_mask(h, self.attn_mask_p, r) \
            if self.training and self.attn_mask_p > 0 else h
        # Eq. (5): alpha_ij = exp(h_ij) / sum_{u in N(i)} exp(h_iu)
        alpha = edge_softmax(logits, r)
        alpha_drop = F.dropout(alpha, p=self.dropout, training=self.training)

        # Eq. (6): x_hat_i = sum_{j in N(i)} alpha_ij (v_j + q_ij)
        #          with Eq. (5)'s q_ij = W_q' e_ij + b_q'
        if r.fused:
            x_hat = self.aggregate_fused(alpha_drop, v, e, g, r)
        else:
            qe = self.lin_edge_value(e).view(e.size(0), H, C)
            x_hat = self.propagate(g.edge_index, v=v, alpha=alpha_drop, qe=qe,
                                   size=(g.num_src, g.num_dst))
        # Eq. (6): x_i' = W_o x_hat_i + skip(x_i)
        out = self.merge_heads(x_hat, x_dst)
        # Eq. (6): e_ij' = W_e h_ij + skip(e_ij)  (the unmasked scores)
        e_out = self.update_edges(r.edges_out(h), e)
        return self.outputs(x, g, edge_attr, out, e_out, (g.edge_index, r.edges_out(alpha)),
                            return_attention_weights, return_edge_attr)

    def message(self, v_j: Tensor, alpha: Tensor, qe: Tensor) -> Tensor:  # type: ignore[override]
        # Eq. (6), one edge: alpha_ij (v_j + q_ij)
        return (v_j + qe) * alpha.unsqueeze(-1)

    def aggregate_fused(self, alpha: Tensor, v: Tensor, e: Tensor, g: Graph,
                        r: Route) -> Tensor:
        """Eq. (6)'s sum on the sparse kernels, ``[N_dst, H, C]``, by linearity of ``W_q'``::

            sum_j alpha_ij (v_j + W_q' e_ij + b_q')
                = sum_j alpha_ij v_j + [W_q' | b_q'] sum_j alpha_ij [e_ij | 1]

        so only the narrow ``[E, D+1]`` edge rows are summed, never ``[E, H, C]``
        values; the ones column gives the attention mass that the bias needs (exact
        also when dropout makes the weights not sum to 1)."""
        H, C, D = self.heads, self.out_channels, self.edge_dim
        out = attention_spmm(alpha, v, g, r)  # sum_j alpha_ij v_j: [N, H, C]
        b_q = self.lin_edge_value.bias
        rows = e if b_q is None else F.pad(e, (0, 1), value=1.0)
        agg_e = edge_rows_spmm(alpha, rows, g, r)  # sum_j alpha_ij [e_ij | 1]: [N, H, D(+1)]
        w = self.lin_edge_value.weight.view(H, C, D)
        if b_q is not None:
            w = torch.cat([w, b_q.view(H, C, 1)], 2)
        # all heads in one matmul against the block-diagonal [H(D+1), HC] map, added
        # into the node-major sums: [N, H(D+1)] @ blockdiag(W_q'^h^T | b_q'^h)
        N = out.size(0)
        return torch.addmm(out.view(N, H * C), agg_e.reshape(N, -1),
                           torch.block_diag(*w.transpose(1, 2))).view(N, H, C)

    def update_edges(self, h: Tensor, e: Tensor) -> Tensor:
        """``W_e h_ij + skip(e_ij)`` for scores ``h [E, H]`` in the caller's order."""
        if self.lin_edge_skip is None:  # one pass over the [E, D] output: e + [h | 1] [W_e | b]^T
            w_e, b_e = self.lin_edge_out.weight, self.lin_edge_out.bias
            if b_e is not None:
                h, w_e = F.pad(h, (0, 1), value=1.0), torch.cat([w_e, b_e.unsqueeze(1)], 1)
            return torch.addmm(e, h, w_e.t())
        return self.lin_edge_out(h) + self.lin_edge_skip(e)

    def __repr__(self) -> str:
        return (f"{self.__class__.__name__}({self.in_channels}, {self.out_channels}, "
                f"heads={self.heads}, edge_dim={self.edge_dim}, "
                f"edge_out_channels={self.edge_out_channels}, concat={self.concat})")
