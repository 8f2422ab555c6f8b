"""Graph transformer with edge features, no gating (Dwivedi & Bresson, 2020)."""
from __future__ import annotations

from typing import Optional, Tuple, Union

import torch.nn.functional as F
from torch import Tensor
from torch_geometric.nn.dense.linear import Linear
from torch_geometric.typing import Adj, OptTensor, PairTensor

from garmentgnn.nn._base import AttentionConv, LayerOutput
from garmentgnn.nn._graph import check_edge_out_channels, check_layer_args
from garmentgnn.nn.functional import attention_spmm, edge_softmax


class EdgeTransformerConv(AttentionConv):
    r"""The graph transformer layer with edge features of Dwivedi & Bresson,
    *A Generalization of Transformer Networks to Graphs*, AAAI-DLG 2021
    (arXiv:2012.09699), GarTrans reference [53]; the "w/o edge gating"
    ablation of GarTrans.

    Edge features modulate the scores channel by channel instead of gating
    them.  For every edge :math:`j \to i` and head :math:`h` with :math:`C`
    channels:

    .. math::
        \mathbf{q}_i = \mathbf{W}_q \mathbf{x}_i,\quad
        \mathbf{k}_j = \mathbf{W}_k \mathbf{x}_j,\quad
        \mathbf{v}_j = \mathbf{W}_v \mathbf{x}_j,\quad
        \hat{\mathbf{w}}_{ij} = \Big(\frac{\mathbf{q}_i \odot \mathbf{k}_j}
        {\sqrt{C}}\Big) \odot \mathbf{W}_E \mathbf{e}_{ij}
        \in \mathbb{R}^{C}

    .. math::
        \alpha_{ij} = \operatorname{softmax}_{j \in \mathcal{N}(i)}
        \sum_{c=1}^{C} \hat{w}_{ij,c}

    .. math::
        \mathbf{x}'_i = \mathbf{W}_o\,\big\Vert_h
        \sum_{j \in \mathcal{N}(i)} \alpha_{ij} \mathbf{v}_j
        + \mathrm{skip}(\mathbf{x}_i),
        \qquad
        \mathbf{e}'_{ij} = \mathbf{W}_{eo}\,\big\Vert_h \hat{\mathbf{w}}_{ij}
        + \mathrm{skip}(\mathbf{e}_{ij})

    where :math:`\Vert_h` concatenates the heads (or averages them when
    ``concat=False``, for nodes and edges alike) and each skip is the
    identity when the widths match and a linear map otherwise.  The
    original paper's residuals, normalisation and feed-forward blocks, and
    the activation, are left to the caller; the score is not clamped (the
    reference code clamps to :math:`[-5, 5]` before :math:`\exp`).

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
        bias (bool): learn additive biases.
        validate (bool): kept for PyG-style signatures: the index range is
            checked once per graph either way (the sparse kernels need it).
        check_finite (bool): raise ``ValueError`` when an output holds NaN/inf.

    Shapes:
        - **input:** ``x`` :math:`(|V|, F_{in})` or a pair,
          ``edge_index`` :math:`(2, |E|)` or sparse ``adj_t``,
          ``edge_attr`` :math:`(|E|, D)`
        - **output:** :math:`(|V|, H C)` (or :math:`(|V|, C)`); with
          ``return_edge_attr=True`` also the new edge features :math:`(|E|, D')`.
    """

    #: the name :func:`~garmentgnn.nn.make_layer` and the recipes know it by
    layer_name = "gt_edge"

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
        bias: bool = True,
        validate: bool = True,
        check_finite: bool = True,
        **kwargs,
    ) -> None:
        super().__init__(**kwargs)
        if edge_dim is None:
            raise ValueError("`edge_dim`: EdgeTransformerConv needs edge features; "
                             "pass their width (use GraphTransformerConv to ignore edges)")
        in_src, in_dst = check_layer_args(in_channels, out_channels, heads, edge_dim, dropout,
                                          edge_dim_required=True)
        check_edge_out_channels(edge_out_channels)

        self.in_channels = in_channels
        self.out_channels = out_channels
        self.edge_dim = edge_dim
        self.heads = heads
        self.concat = concat
        self.edge_out_channels = edge_out_channels or edge_dim
        self.dropout = dropout
        self.validate = validate
        self.check_finite = check_finite

        H, C = heads, out_channels
        out_width = H * C if concat else C
        self.lin_query = Linear(in_dst, H * C, bias=bias)
        self.lin_key = Linear(in_src, H * C, bias=bias)
        self.lin_value = Linear(in_src, H * C, bias=bias)
        self.lin_edge = Linear(edge_dim, H * C, bias=bias)  # W_E
        self.lin_out = Linear(out_width, out_width, bias=bias)  # W_o
        self.lin_edge_out = Linear(out_width, self.edge_out_channels, bias=bias)  # W_eo
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
        src, dst = g.edge_index[0], g.edge_index[1]
        e = g.edge_attr
        assert e is not None
        H, C, E = self.heads, self.out_channels, g.edge_index.size(1)
        # q_i = W_q x_i / sqrt(C),  k_j = W_k x_j,  v_j = W_v x_j  (one matmul)
        q, k, v, x_dst = self.project_qkv(x)
        r = self.route(g, q)  # sparse kernels, or propagate() with message()

        # w_hat_ij = (q_i * k_j / sqrt(C)) * W_E e_ij, per channel: [E, H, C] in the caller's
        # order (the per-channel edge product needs it; it is also the new edge state)
        q_i, k_j = q.contiguous().index_select(0, dst), k.contiguous().index_select(0, src)
        w_hat = q_i * k_j * self.lin_edge(e).view(E, H, C)
        # alpha_ij = softmax_{j in N(i)} sum_c w_hat_ij,c
        alpha = edge_softmax(r.edges_in(w_hat.sum(-1)), r)
        alpha_drop = F.dropout(alpha, p=self.dropout, training=self.training)
        # x_hat_i = sum_{j in N(i)} alpha_ij v_j
        if r.fused:
            x_hat = attention_spmm(alpha_drop, v, g, r)
        else:
            x_hat = self.propagate(g.edge_index, v=v, alpha=alpha_drop,
                                   size=(g.num_src, g.num_dst))
        # x_i' = W_o x_hat_i + skip(x_i)
        out = self.merge_heads(x_hat, x_dst)

        # e_ij' = W_eo heads(w_hat_ij) + skip(e_ij)
        w_hat = w_hat.reshape(E, H * C) if self.concat else w_hat.mean(1)
        e_out = self.lin_edge_out(w_hat)
        e_out = e_out + (e if self.lin_edge_skip is None else self.lin_edge_skip(e))
        return self.outputs(x, g, edge_attr, out, e_out, (g.edge_index, r.edges_out(alpha)),
                            return_attention_weights, return_edge_attr)

    def message(self, v_j: Tensor, alpha: Tensor) -> Tensor:  # type: ignore[override]
        # one edge: alpha_ij v_j
        return v_j * alpha.unsqueeze(-1)

    def __repr__(self) -> str:
        return (f"{self.__class__.__name__}({self.in_channels}, {self.out_channels}, "
                f"heads={self.heads}, edge_dim={self.edge_dim}, "
                f"edge_out_channels={self.edge_out_channels}, concat={self.concat})")
