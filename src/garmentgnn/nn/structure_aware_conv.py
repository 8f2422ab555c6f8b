"""Structure-aware transformer convolution (Chen, O'Bray & Borgwardt, ICML 2022)."""
from __future__ import annotations

from typing import Optional, Tuple, Union

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch_geometric.nn.conv import GINConv, GINEConv
from torch_geometric.nn.dense.linear import Linear
from torch_geometric.typing import Adj, OptTensor, PairTensor

from garmentgnn.nn._base import AttentionConv, LayerOutput
from garmentgnn.nn._graph import check_layer_args
from garmentgnn.nn.functional import attention_spmm, edge_dot, edge_softmax


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
    MLP of width ``hidden_channels``, :math:`\Vert_h` concatenates the heads
    (or averages them when ``concat=False``) and the skip is the identity
    when the widths match and a linear map otherwise.  The global
    (all-pairs) variant of the paper is not implemented; edge features only
    enter the extractor.  The activation is left to the caller.

    **Bipartite graphs** (``x = (x_src, x_dst)``, e.g. inside
    :func:`~torch_geometric.nn.to_hetero`): the extractor runs on the graph
    whose nodes are both sets and whose edges are the given ``src -> dst``
    edges, so a target's :math:`\varphi` sees its sources' features and a
    source's :math:`\varphi` (which has no incoming edge there) its own; this
    is the same k-subtree extractor, applied to that graph.  A pair is always
    read as two node sets, so ``conv((x, x), ...)`` differs from
    ``conv(x, ...)``.

    Not to be confused with :class:`~garmentgnn.nn.SATConv`, the
    structure-*augmented* transformer of GarTrans, also abbreviated "SAT".

    Args:
        in_channels (int or tuple): input width, or ``(src, dst)`` widths;
            ``-1`` infers it from the first call.
        out_channels (int): channels per head, :math:`C`.
        heads (int): number of heads :math:`H`.
        concat (bool): concatenate heads (output ``H * C``) or average them
            (output ``C``).
        edge_dim (int, optional): edge feature width; selects GINE (edge
            features required) over GIN (edges ignored).
        dropout (float): dropout on the attention coefficients (training).
        bias (bool): learn additive biases.
        validate (bool): kept for PyG-style signatures: the index range is
            checked once per graph either way (the sparse kernels need it).
        check_finite (bool): raise ``ValueError`` when the output holds NaN/inf.
        k_hops (int): number of GIN layers :math:`k` of the extractor.
        hidden_channels (int, optional): width of the extractor; defaults to
            the input width when that is known and the same for sources and
            targets, else to the output width.  When it differs from an input
            width, a linear map (``lin_extract`` or ``lin_extract_src`` /
            ``lin_extract_dst``) brings that input to it first.

    Shapes:
        - **input:** ``x`` :math:`(|V|, F_{in})` or a pair,
          ``edge_index`` :math:`(2, |E|)` or sparse ``adj_t``,
          ``edge_attr`` :math:`(|E|, D)` (when ``edge_dim`` is set)
        - **output:** :math:`(|V|, H C)` (or :math:`(|V|, C)`); with
          ``return_edge_attr=True`` also ``edge_attr`` as given.
    """

    #: the name :func:`~garmentgnn.nn.make_layer` and the recipes know it by
    layer_name = "structure_aware"

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
        k_hops: int = 2,
        hidden_channels: Optional[int] = None,
        **kwargs,
    ) -> None:
        super().__init__(**kwargs)
        in_src, in_dst = check_layer_args(in_channels, out_channels, heads, edge_dim, dropout,
                                          edge_dim_required=False)
        if not isinstance(k_hops, int) or isinstance(k_hops, bool) or k_hops <= 0:
            raise ValueError(f"`k_hops` must be a positive int, got {k_hops!r}")

        self.in_channels = in_channels
        self.out_channels = out_channels
        self.edge_dim = edge_dim
        self.requires_edge_attr = edge_dim is not None
        self.heads = heads
        self.concat = concat
        self.dropout = dropout
        self.validate = validate
        self.check_finite = check_finite
        self.k_hops = k_hops

        H, C = heads, out_channels
        out_width = H * C if concat else C
        known = in_src == in_dst and in_src > 0
        hidden = hidden_channels or (in_src if known else out_width)
        check_layer_args(hidden, 1, 1, None, 0.0, edge_dim_required=False)
        self.hidden_channels = hidden
        # inputs narrower or wider than the extractor get a linear map to it first
        self.lin_extract = self.lin_extract_src = self.lin_extract_dst = None
        if isinstance(in_channels, int):
            if in_channels != hidden:
                self.lin_extract = Linear(in_channels, hidden, bias=bias)
        elif not (in_src == in_dst == hidden):
            self.lin_extract_src = Linear(in_src, hidden, bias=bias)
            self.lin_extract_dst = Linear(in_dst, hidden, bias=bias)
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
        self.lin_skip = self.skip_layer(in_dst, out_width, bias)
        self.reset_parameters()

    def _extract_input(self, x: Tensor, side: str) -> Tensor:
        lin = self.lin_extract if self.lin_extract is not None else (
            self.lin_extract_src if side == "src" else self.lin_extract_dst)
        return x if lin is None else lin(x)

    def extract(self, x: Union[Tensor, PairTensor], edge_index: Tensor,
                edge_attr: OptTensor = None) -> Union[Tensor, PairTensor]:
        """The k-subtree structure embedding :math:`\\varphi`, ``[N, hidden_channels]``
        (a ``(phi_src, phi_dst)`` pair for a bipartite ``x``).

        Node ``i``'s row depends only on nodes (and edges) at most ``k_hops``
        incoming hops away.  ``edge_index`` is a ``[2, E]`` tensor.
        """
        if isinstance(x, Tensor):
            h, ei, n_src = self._extract_input(x, "src"), edge_index, None
        else:  # the graph on both node sets: targets are numbered after the sources
            n_src = x[0].size(0)
            h = torch.cat([self._extract_input(x[0], "src"), self._extract_input(x[1], "dst")])
            ei = torch.stack([edge_index[0], edge_index[1] + n_src])
        for layer, conv in enumerate(self.extractor):
            if layer > 0:
                h = h.relu()
            h = conv(h, ei) if self.edge_dim is None else conv(h, ei, edge_attr)
        return h if n_src is None else (h[:n_src], h[n_src:])

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
        # phi = GIN_k(... ReLU(GIN_1(x, e))): the k-subtree structure embedding
        phi = self.extract(x, g.edge_index, g.edge_attr)
        # q_i = W_q phi_i / sqrt(C),  k_j = W_k phi_j,  v_j = W_v x_j
        if isinstance(x, Tensor):
            q, k = self.project(phi, (self.lin_query, self.lin_key), True)
            (v,) = self.project(x, (self.lin_value,))
            x_dst = x
        else:
            (q,) = self.project(phi[1], (self.lin_query,), True)
            (k,) = self.project(phi[0], (self.lin_key,))
            (v,) = self.project(x[0], (self.lin_value,))
            x_dst = x[1]
        r = self.route(g, q)  # sparse kernels, or propagate() with message()

        # alpha_ij = softmax_{j in N(i)} q_i^T k_j / sqrt(C)
        alpha = edge_softmax(edge_dot(q, k, g, r), r)
        alpha_drop = F.dropout(alpha, p=self.dropout, training=self.training)
        # x_hat_i = sum_{j in N(i)} alpha_ij v_j
        if r.fused:
            x_hat = attention_spmm(alpha_drop, v, g, r)
        else:
            x_hat = self.propagate(g.edge_index, v=v, alpha=alpha_drop,
                                   size=(g.num_src, g.num_dst))
        # x_i' = W_o x_hat_i + skip(x_i)
        out = self.merge_heads(x_hat, x_dst)
        return self.outputs(x, g, edge_attr, out, None, (g.edge_index, r.edges_out(alpha)),
                            return_attention_weights, return_edge_attr)

    def message(self, v_j: Tensor, alpha: Tensor) -> Tensor:  # type: ignore[override]
        # one edge: alpha_ij v_j
        return v_j * alpha.unsqueeze(-1)

    def __repr__(self) -> str:
        return (f"{self.__class__.__name__}({self.in_channels}, {self.out_channels}, "
                f"heads={self.heads}, edge_dim={self.edge_dim}, k_hops={self.k_hops}, "
                f"concat={self.concat})")
