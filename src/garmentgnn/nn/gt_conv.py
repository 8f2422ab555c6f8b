"""Plain graph transformer convolution (GarTrans, Eqs. 3-4; "w/o edge processing")."""
from __future__ import annotations

from typing import Optional, Tuple, Union

import torch.nn.functional as F
from torch import Tensor
from torch_geometric.nn.dense.linear import Linear
from torch_geometric.typing import Adj, OptTensor, PairTensor

from garmentgnn.nn._base import AttentionConv, LayerOutput
from garmentgnn.nn._graph import check_layer_args
from garmentgnn.nn.functional import attention_spmm, edge_dot, edge_softmax


class GraphTransformerConv(AttentionConv):
    r"""The plain graph transformer layer of GarTrans, Eqs. (3)-(4)
    (Dwivedi & Bresson, 2020, without edge features), used as the
    "w/o edge processing" ablation.

    For every edge :math:`j \to i` and head :math:`h` with :math:`C` channels:

    .. math::
        \mathbf{q}_i = \mathbf{W}_q \mathbf{x}_i,\quad
        \mathbf{k}_j = \mathbf{W}_k \mathbf{x}_j,\quad
        \mathbf{v}_j = \mathbf{W}_v \mathbf{x}_j,\quad
        h_{ij} = \frac{\mathbf{q}_i^\top \mathbf{k}_j}{\sqrt{C}},\quad
        \alpha_{ij} = \operatorname{softmax}_{j \in \mathcal{N}(i)} h_{ij}

    .. math::
        \mathbf{x}'_i = \mathbf{W}_o\,\big\Vert_h
        \sum_{j \in \mathcal{N}(i)} \alpha_{ij} \mathbf{v}_j
        + \mathrm{skip}(\mathbf{x}_i)

    where :math:`\Vert_h` concatenates the heads (or averages them when
    ``concat=False``) and the skip is the identity when the widths match and
    a linear map (``lin_skip``) otherwise.  Edge features take no part:
    ``edge_dim`` is accepted (so the layer is a drop-in replacement in a
    registry) and only used to check the shape of ``edge_attr``, which
    ``return_edge_attr=True`` hands back unchanged.  The activation is left to the caller.

    With ``lin_out`` set to the identity this is PyG's
    :class:`~torch_geometric.nn.conv.TransformerConv` with
    ``root_weight=True`` and no ``edge_dim``.

    Args:
        in_channels (int or tuple): input width, or ``(src, dst)`` widths for
            bipartite graphs; ``-1`` infers it from the first call.
        out_channels (int): channels per head, :math:`C`.
        heads (int): number of heads :math:`H`.
        concat (bool): concatenate heads (output ``H * C``) or average them
            (output ``C``).
        edge_dim (int, optional): declared edge feature width; ignored apart
            from the shape check of ``edge_attr``.
        dropout (float): dropout on the attention coefficients (training).
        bias (bool): learn additive biases.
        validate (bool): kept for PyG-style signatures: the index range is
            checked once per graph either way (the sparse kernels need it).
        check_finite (bool): raise ``ValueError`` when the output holds NaN/inf.

    Shapes:
        - **input:** ``x`` :math:`(|V|, F_{in})` or a pair,
          ``edge_index`` :math:`(2, |E|)` or sparse ``adj_t``,
          ``edge_attr`` :math:`(|E|, D)` or ``None``
        - **output:** :math:`(|V|, H C)` (or :math:`(|V|, C)`); with
          ``return_edge_attr=True`` also ``edge_attr`` as given.
    """

    #: the name :func:`~garmentgnn.nn.make_layer` and the recipes know it by
    layer_name = "gt"

    def __init__(
        self,
        in_channels: Union[int, Tuple[int, int]],
        out_channels: int,
        heads: int = 1,
        concat: bool = True,
        *,
        edge_dim: Optional[int] = None,
        dropout: float = 0.0,
        bias: bool = True,
        validate: bool = True,
        check_finite: bool = True,
        **kwargs,
    ) -> None:
        super().__init__(**kwargs)
        in_src, in_dst = check_layer_args(in_channels, out_channels, heads, edge_dim, dropout,
                                          edge_dim_required=False)

        self.in_channels = in_channels
        self.out_channels = out_channels
        self.edge_dim = edge_dim
        self.heads = heads
        self.concat = concat
        self.dropout = dropout
        self.validate = validate
        self.check_finite = check_finite

        H, C = heads, out_channels
        out_width = H * C if concat else C
        self.lin_query = Linear(in_dst, H * C, bias=bias)
        self.lin_key = Linear(in_src, H * C, bias=bias)
        self.lin_value = Linear(in_src, H * C, bias=bias)
        self.lin_out = Linear(out_width, out_width, bias=bias)  # W_o
        self.lin_skip = self.skip_layer(in_dst, out_width, bias)
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
        # Eqs. (3)-(4): q_i = W_q x_i + b_q,  k_j = W_k x_j + b_k,  v_j = W_v x_j + b_v
        # (one matmul; q_i comes scaled by 1/sqrt(d_a))
        q, k, v, x_dst = self.project_qkv(x)
        r = self.route(g, q)  # sparse kernels, or propagate() with message()

        # Eq. (3): h_ij = q_i^T k_j / sqrt(d_a)
        h = edge_dot(q, k, g, r)
        # Eq. (3): alpha_ij = softmax_{j in N(i)} h_ij
        alpha = edge_softmax(h, r)
        alpha_drop = F.dropout(alpha, p=self.dropout, training=self.training)
        # Eq. (4): x_hat_i = sum_{j in N(i)} alpha_ij v_j
        if r.fused:
            x_hat = attention_spmm(alpha_drop, v, g, r)
        else:
            x_hat = self.propagate(g.edge_index, v=v, alpha=alpha_drop,
                                   size=(g.num_src, g.num_dst))
        # Eq. (4): x_i' = W_o x_hat_i + skip(x_i)
        out = self.merge_heads(x_hat, x_dst)
        return self.outputs(x, g, edge_attr, out, None, (g.edge_index, r.edges_out(alpha)),
                            return_attention_weights, return_edge_attr)

    def message(self, v_j: Tensor, alpha: Tensor) -> Tensor:  # type: ignore[override]
        # Eq. (4), one edge: alpha_ij v_j
        return v_j * alpha.unsqueeze(-1)

    def __repr__(self) -> str:
        return (f"{self.__class__.__name__}({self.in_channels}, {self.out_channels}, "
                f"heads={self.heads}, edge_dim={self.edge_dim}, concat={self.concat})")
