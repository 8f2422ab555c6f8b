"""GATv2 baseline behind the common layer contract."""
from __future__ import annotations

from typing import Optional, Tuple, Union

import torch
from torch import Tensor
from torch_geometric.nn.conv import GATv2Conv
from torch_geometric.nn.dense.linear import Linear
from torch_geometric.typing import Adj, OptTensor, PairTensor

from garmentgnn.nn._base import LayerContract, LayerOutput
from garmentgnn.nn._graph import check_layer_args
from garmentgnn.nn._linear import NarrowLinear


class GATBaselineConv(LayerContract):
    r"""A graph attention baseline: PyG's
    :class:`~torch_geometric.nn.conv.GATv2Conv` (Brody, Alon & Yahav, *How
    Attentive are Graph Attention Networks?*, ICLR 2022) plus a residual
    skip, behind the same contract as the transformer layers.

    For every edge :math:`j \to i` and head :math:`h`:

    .. math::
        \alpha_{ij} = \operatorname{softmax}_{j \in \mathcal{N}(i)}
        \mathbf{a}^\top \mathrm{LeakyReLU}\big(\mathbf{W}_s \mathbf{x}_i
        + \mathbf{W}_t \mathbf{x}_j + \mathbf{W}_e \mathbf{e}_{ij}\big),\qquad
        \mathbf{x}'_i = \big\Vert_h \sum_{j \in \mathcal{N}(i)}
        \alpha_{ij} \mathbf{W}_t \mathbf{x}_j + \mathbf{b}
        + \mathrm{skip}(\mathbf{x}_i)

    where :math:`\Vert_h` concatenates the heads (or averages them when
    ``concat=False``), the edge term appears only when ``edge_dim`` is set,
    and the skip is the identity when the widths match and a linear map
    (``lin_skip``) otherwise, so stacks stay residual like the other layers.
    Edge features only enter the scores and are returned unchanged.  The
    activation is left to the caller.

    Self-loops are **not** added by default (``add_self_loops=False``, unlike
    PyG's default): mesh vertices always have neighbours, the skip already
    carries :math:`\mathbf{x}_i`, and the contract returns attention weights
    aligned with the *input* edges.  With ``add_self_loops=True`` the
    returned ``(edge_index, alpha)`` covers the augmented edge set built by
    ``GATv2Conv``.

    Its message passing (and so explainers' edge masks, message hooks and
    attention collection) happens in the child ``gat``: register message
    hooks there.

    Args:
        in_channels (int or tuple): input width, or ``(src, dst)`` widths for
            bipartite graphs; ``-1`` infers it from the first call.
        out_channels (int): channels per head.
        heads (int): number of heads :math:`H`.
        concat (bool): concatenate heads (output ``H * C``) or average them
            (output ``C``).
        edge_dim (int, optional): edge feature width; when set, edge features
            are required and enter the attention scores.
        dropout (float): dropout on the attention coefficients (training).
        bias (bool): learn additive biases.
        validate (bool): kept for PyG-style signatures: the index range is
            checked once per graph either way (the sparse kernels need it).
        check_finite (bool): raise ``ValueError`` when the output holds NaN/inf.
        add_self_loops (bool): let ``GATv2Conv`` add self-loops.
        **kwargs: passed to ``GATv2Conv`` (e.g. ``negative_slope``,
            ``share_weights``); ``residual`` is rejected since the layer has
            its own skip.

    Shapes:
        - **input:** ``x`` :math:`(|V|, F_{in})` or a pair,
          ``edge_index`` :math:`(2, |E|)` or sparse ``adj_t``,
          ``edge_attr`` :math:`(|E|, D)` or ``None``
        - **output:** :math:`(|V|, H C)` (or :math:`(|V|, C)`); with
          ``return_edge_attr=True`` also ``edge_attr`` as given.
    """

    #: the name :func:`~garmentgnn.nn.make_layer` and the recipes know it by
    layer_name = "gat"

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
        add_self_loops: bool = False,
        **kwargs,
    ) -> None:
        super().__init__(node_dim=0)
        _, in_dst = check_layer_args(in_channels, out_channels, heads, edge_dim, dropout,
                                     edge_dim_required=False)
        if kwargs.get("residual"):
            raise ValueError("`residual`: GATBaselineConv adds its own skip (lin_skip); "
                             "do not ask GATv2Conv for another one")
        kwargs.pop("residual", None)

        self.in_channels = in_channels
        self.out_channels = out_channels
        self.edge_dim = edge_dim
        self.requires_edge_attr = edge_dim is not None
        self.heads = heads
        self.concat = concat
        self.dropout = dropout
        self.validate = validate
        self.check_finite = check_finite
        self.add_self_loops = add_self_loops

        out_width = heads * out_channels if concat else out_channels
        self.gat = GATv2Conv(in_channels, out_channels, heads=heads, concat=concat,
                             dropout=dropout, edge_dim=edge_dim, bias=bias,
                             add_self_loops=add_self_loops, **kwargs)
        if edge_dim is not None:  # W_e e_ij fused into the scores under torch.compile
            with torch.random.fork_rng(devices=[]):  # reset_parameters below draws it
                self.gat.lin_edge = NarrowLinear(edge_dim, heads * out_channels, bias=False,
                                                 weight_initializer="glorot")
        self.lin_skip = None if in_dst == out_width else Linear(in_dst, out_width, bias=bias)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        super().reset_parameters()
        self.gat.reset_parameters()
        if self.lin_skip is not None:
            self.lin_skip.reset_parameters()

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
        x_dst = x if isinstance(x, Tensor) else x[1]
        e = g.edge_attr if self.edge_dim is not None else None
        # alpha_ij = softmax_{j in N(i)} a^T LeakyReLU(W_s x_i + W_t x_j + W_e e_ij),
        # x_hat_i = ||_h sum_{j in N(i)} alpha_ij W_t x_j + b: GATv2Conv's forward and message
        x_hat, (ei, alpha) = self.gat(x, g.edge_index, e, return_attention_weights=True)
        # x_i' = x_hat_i + skip(x_i)
        out = x_hat + (x_dst if self.lin_skip is None else self.lin_skip(x_dst))
        return self.outputs(x, g, edge_attr, out, None, (ei, alpha),
                            return_attention_weights, return_edge_attr)

    def __repr__(self) -> str:
        return (f"{self.__class__.__name__}({self.in_channels}, {self.out_channels}, "
                f"heads={self.heads}, edge_dim={self.edge_dim}, concat={self.concat})")
