"""Structure-aware transformer convolution (Chen, O'Bray & Borgwardt, ICML 2022)."""
from __future__ import annotations

from typing import Optional, Tuple, Union

import torch.nn.functional as F
from torch import Tensor, nn
from torch_geometric.nn.conv import GINConv, GINEConv
from torch_geometric.nn.dense.linear import Linear
from torch_geometric.typing import Adj, OptTensor, PairTensor

from garmentgnn.nn._base import AttentionConv
from garmentgnn.nn._graph import check_layer_args, edge_softmax, prepare_graph


class StructureAwareTransformerConv(AttentionConv):
    r"""The structure-aware transformer (SAT) attention of Chen, O'Bray &
    Borgwardt, *Structure-Aware Transformer for Graph Representation
    Learning*, ICML 2022 (GarTrans reference [59]), with the k-subtree
    structure extractor and attention restricted to the graph neighbourhood.

    A :math:`k`-layer GIN (GINE when ``edge_dim`` is given) computes a
    structure-aware embedding :math:`\varphi(\mathbf{x}, G)_i` of the
    :math:`k`-hop subtree rooted at every node; queries and keys come from
    it, values from the raw features.  For every edge :math:`j \to i` and
    head :math:`h` with :math:`C` channels:

    .. math::
        \varphi = \mathrm{GIN}_k \circ \mathrm{ReLU} \circ \cdots \circ
        \mathrm{ReLU} \circ \mathrm{GIN}_1(\mathbf{x}, \mathbf{e}),\quad
        \mathbf{q}_i = \mathbf{W}_q \varphi_i,\quad
        \mathbf{k}_j = \mathbf{W}_k \varphi_j,\quad
        \mathbf{v}_j = \mathbf{W}_v \mathbf{x}_j

    .. math::
        \alpha_{ij} = \operatorname{softmax}_{j \in \mathcal{N}(i)}
        \frac{\mathbf{q}_i^\top \mathbf{k}_j}{\sqrt{C}},\qquad
        \mathbf{x}'_i = \mathbf{W}_o\,\big\Vert_h
        \sum_{j \in \mathcal{N}(i)} \alpha_{ij} \mathbf{v}_j
        + \mathrm{skip}(\mathbf{x}_i)

    where each :math:`\mathrm{GIN}_l` is
    :math:`\mathrm{MLP}_l\big((1+\epsilon_l)\mathbf{h}_i + \sum_{j}
    \mathrm{ReLU}(\mathbf{h}_j + \mathbf{W}_l \mathbf{e}_{ij})\big)`
    (PyG :class:`~torch_geometric.nn.conv.GINEConv`; the edge term is
    dropped for :class:`~torch_geometric.nn.conv.GINConv`) with a 2-layer
    MLP of width ``in_channels``, :math:`\Vert_h` concatenates the heads (or
    averages them when ``concat=False``) and the skip is the identity when
    the widths match and a linear map otherwise.  The global (all-pairs)
    variant of the paper is not implemented; edge features only enter the
    extractor and are returned unchanged.  The activation is left to the
    caller.

    Args:
        in_channels (int or tuple): input width; a ``(src, dst)`` pair must
            have equal entries since the extractor runs on one node set.
        out_channels (int): channels per head, :math:`C`.
        edge_dim (int, optional): edge feature width; selects GINE (edge
            features required) over GIN (edges ignored).
        heads (int): number of heads :math:`H`.
        concat (bool): concatenate heads (output ``H * C``) or average them
            (output ``C``).
        dropout (float): dropout on the attention coefficients (training).
        bias (bool): learn additive biases.
        validate (bool): check inputs (shapes, index range, NaN/inf) and raise
            ``ValueError``; costs O(N + E) per call.
        k_hops (int): number of GIN layers :math:`k` of the extractor.

    Shapes:
        - **input:** ``x`` :math:`(|V|, F_{in})`,
          ``edge_index`` :math:`(2, |E|)` or sparse ``adj_t``,
          ``edge_attr`` :math:`(|E|, D)` (when ``edge_dim`` is set)
        - **output:** ``(x_out, edge_attr)`` with ``x_out`` of shape
          :math:`(|V|, H C)` (or :math:`(|V|, C)`) and ``edge_attr`` the
          input object (the values of a hybrid sparse ``adj_t`` when
          ``edge_attr`` is ``None``); with ``return_attention_weights=True`` a third item
          ``(edge_index, alpha)`` with ``alpha`` :math:`(|E|, H)`.
    """

    def __init__(
        self,
        in_channels: Union[int, Tuple[int, int]],
        out_channels: int,
        edge_dim: Optional[int] = None,
        heads: int = 1,
        concat: bool = True,
        dropout: float = 0.0,
        bias: bool = True,
        validate: bool = True,
        k_hops: int = 2,
        **kwargs,
    ) -> None:
        super().__init__(**kwargs)
        in_src, in_dst = check_layer_args(in_channels, out_channels, heads, edge_dim, dropout,
                                          edge_dim_required=False)
        if not isinstance(k_hops, int) or k_hops <= 0:
            raise ValueError(f"`k_hops` must be a positive int, got {k_hops!r}")
        if in_src != in_dst:
            raise ValueError(f"`in_channels`: the structure extractor runs on a single node set; "
                             f"got different source/target widths {in_channels!r}")

        self.in_channels = in_channels
        self.out_channels = out_channels
        self.edge_dim = edge_dim
        self.heads = heads
        self.concat = concat
        self.dropout = dropout
        self.validate = validate
        self.k_hops = k_hops

        H, C = heads, out_channels
        out_width = H * C if concat else C
        hidden = in_dst
        self.extractor = nn.ModuleList()  # k-subtree GNN extractor (phi)
        for _ in range(k_hops):
            mlp = nn.Sequential(nn.Linear(hidden, hidden, bias=bias), nn.ReLU(),
                                nn.Linear(hidden, hidden, bias=bias))
            self.extractor.append(GINConv(mlp, train_eps=True) if edge_dim is None
                                  else GINEConv(mlp, train_eps=True, edge_dim=edge_dim))
        self.lin_query = Linear(hidden, H * C, bias=bias)
        self.lin_key = Linear(hidden, H * C, bias=bias)
        self.lin_value = Linear(in_src, H * C, bias=bias)
        self.lin_out = Linear(out_width, out_width, bias=bias)  # W_o
        self.lin_skip = None if in_dst == out_width else Linear(in_dst, out_width, bias=bias)
        self.reset_parameters()

    def extract(self, x: Tensor, edge_index: Adj, edge_attr: OptTensor = None) -> Tensor:
        """The k-subtree structure embedding :math:`\\varphi` ``[N, in_channels]``.

        Node ``i``'s row depends only on nodes (and edges) at most ``k_hops``
        incoming hops away.
        """
        h = x
        for layer, conv in enumerate(self.extractor):
            if layer > 0:
                h = h.relu()
            h = conv(h, edge_index) if self.edge_dim is None else conv(h, edge_index, edge_attr)
        return h

    def forward(
        self,
        x: Union[Tensor, PairTensor],
        edge_index: Adj,
        edge_attr: OptTensor = None,
        return_attention_weights: Optional[bool] = None,
    ):
        """Run the layer.

        Args:
            x: node features ``[N, F_in]`` (a bipartite pair is rejected).
            edge_index: ``[2, E]`` (source, target) indices or sparse ``adj_t``.
            edge_attr: ``[E, edge_dim]`` edge features (required iff ``edge_dim``
                is set); returned as is.
            return_attention_weights: also return ``(edge_index, alpha)``.

        Returns:
            ``(x_out, edge_attr)``, plus ``(edge_index, alpha)`` when asked.
        """
        g = prepare_graph(x, edge_index, edge_attr, self.edge_dim,
                          require_edge_attr=self.edge_dim is not None, validate=self.validate)
        if not isinstance(x, Tensor):
            raise ValueError("`x`: StructureAwareTransformerConv runs its structure extractor on "
                             "a single node set; pass one [N, F] tensor, not a bipartite pair")
        phi = self.extract(x, g.edge_index, g.edge_attr)
        # queries and keys see the k-hop structure (phi); values are the plain features
        q, k = self.project(phi, (self.lin_query, self.lin_key), True)
        (v,) = self.project(x, (self.lin_value,))
        score = self.edge_scores(q, k, g)  # [E, H]
        alpha = edge_softmax(score, g)
        alpha_used = F.dropout(alpha, p=self.dropout, training=self.training)
        out = self.merge_heads(self.aggregate_values(alpha_used, v, g), x)

        # the caller's edge features as given; those a hybrid sparse adj_t carries otherwise
        e_out = edge_attr if edge_attr is not None else g.edge_attr
        if return_attention_weights:
            return out, e_out, (g.edge_index, alpha)
        return out, e_out

    def __repr__(self) -> str:
        return (f"{self.__class__.__name__}({self.in_channels}, {self.out_channels}, "
                f"heads={self.heads}, edge_dim={self.edge_dim}, k_hops={self.k_hops}, "
                f"concat={self.concat})")
