"""Baseline attention layers checked against independent oracles.

* GraphTransformerConv / EdgeTransformerConv / StructureAwareTransformerConv:
  explicit per-target-node python loops built from the layer's own weights
  (separate q/k/v matmuls, ``torch.softmax`` over each node's incoming edges).
* GraphTransformerConv vs PyG's ``TransformerConv`` with copied weights.
* GATBaselineConv vs a standalone ``GATv2Conv`` loaded with the same state.
"""
from __future__ import annotations

import math

import pytest
import torch
from torch_geometric.nn.conv import GATv2Conv, TransformerConv

from garmentgnn.nn import (
    LAYERS,
    EdgeTransformerConv,
    GATBaselineConv,
    GraphTransformerConv,
    StructureAwareTransformerConv,
    make_layer,
)

ATOL = 1e-5


# --------------------------------------------------------------------------- graphs
def random_graph(num_src: int, num_dst: int, num_edges: int, sorted_by_dst: bool,
                 seed: int = 0) -> torch.Tensor:
    """Random [2, E] edges (duplicates allowed); target ``num_dst - 1`` gets no edge."""
    gen = torch.Generator().manual_seed(seed)
    src = torch.randint(0, num_src, (num_edges,), generator=gen)
    dst = torch.randint(0, num_dst - 1, (num_edges,), generator=gen)  # last dst isolated
    ei = torch.stack([src, dst])
    if sorted_by_dst:
        ei = ei[:, torch.argsort(dst, stable=True)]
        assert bool((ei[1, 1:] >= ei[1, :-1]).all())
    else:
        assert not bool((ei[1, 1:] >= ei[1, :-1]).all())
    return ei


def lin(layer_lin, t: torch.Tensor) -> torch.Tensor:
    """Apply a Linear through its raw parameters (no fused path)."""
    out = t @ layer_lin.weight.t()
    return out if layer_lin.bias is None else out + layer_lin.bias


def heads_out(agg: torch.Tensor, concat: bool) -> torch.Tensor:
    return agg.reshape(agg.size(0), -1) if concat else agg.mean(1)


def skip(layer, x_dst: torch.Tensor) -> torch.Tensor:
    return x_dst if layer.lin_skip is None else lin(layer.lin_skip, x_dst)


def loop_attention(q, k, v, ei, num_dst, edge_scores=None):
    """Per-target loop: alpha = softmax over incoming edges, agg = sum alpha v.

    ``q`` [N_dst, H, C], ``k``/``v`` [N_src, H, C]; ``edge_scores(e, i, j)``
    optionally replaces the plain scaled dot product for edge ``e = (j -> i)``.
    """
    H, C = q.shape[1:]
    agg = torch.zeros(num_dst, H, C)
    alpha = torch.zeros(ei.size(1), H)
    for i in range(num_dst):
        edges = (ei[1] == i).nonzero().flatten().tolist()
        if not edges:
            continue
        scores = []
        for e in edges:
            j = int(ei[0, e])
            scores.append(edge_scores(e, i, j) if edge_scores is not None
                          else (q[i] * k[j]).sum(-1) / math.sqrt(C))
        a = torch.softmax(torch.stack(scores), dim=0)  # [m, H]
        for n, e in enumerate(edges):
            alpha[e] = a[n]
            agg[i] += a[n].unsqueeze(-1) * v[int(ei[0, e])]
    return agg, alpha


# Widths: (in_channels, out_channels, heads, concat); equal and unequal in/out widths.
WIDTHS = [
    (8, 4, 2, True),    # 8 == 2 * 4: identity skip
    (5, 4, 2, True),    # lin_skip
    (4, 4, 3, False),   # mean of heads, identity skip
    (5, 3, 2, False),   # mean of heads, lin_skip
]


# --------------------------------------------------------------------------- GT
def reference_gt(layer: GraphTransformerConv, x_src, x_dst, ei):
    H, C = layer.heads, layer.out_channels
    q = lin(layer.lin_query, x_dst).view(-1, H, C)
    k = lin(layer.lin_key, x_src).view(-1, H, C)
    v = lin(layer.lin_value, x_src).view(-1, H, C)
    agg, alpha = loop_attention(q, k, v, ei, x_dst.size(0))
    out = lin(layer.lin_out, heads_out(agg, layer.concat)) + skip(layer, x_dst)
    return out, alpha


@pytest.mark.parametrize("sorted_by_dst", [False, True])
@pytest.mark.parametrize("in_ch,out_ch,heads,concat", WIDTHS)
def test_gt_matches_loop_reference(in_ch, out_ch, heads, concat, sorted_by_dst):
    torch.manual_seed(0)
    layer = GraphTransformerConv(in_ch, out_ch, heads=heads, concat=concat).eval()
    x = torch.randn(7, in_ch)
    ei = random_graph(7, 7, 20, sorted_by_dst)
    out, e_out, (ei_ret, alpha) = layer(x, ei, return_attention_weights=True,
                                        return_edge_attr=True)
    ref, ref_alpha = reference_gt(layer, x, x, ei)
    assert out.shape == (7, heads * out_ch if concat else out_ch)
    assert e_out is None
    assert torch.equal(ei_ret, ei)
    torch.testing.assert_close(alpha, ref_alpha, atol=ATOL, rtol=0)
    torch.testing.assert_close(out, ref, atol=ATOL, rtol=0)


@pytest.mark.parametrize("sorted_by_dst", [False, True])
def test_gt_bipartite_matches_loop_reference(sorted_by_dst):
    torch.manual_seed(1)
    layer = GraphTransformerConv((5, 3), 4, heads=2).eval()
    x_src, x_dst = torch.randn(6, 5), torch.randn(4, 3)
    ei = random_graph(6, 4, 12, sorted_by_dst)
    out = layer((x_src, x_dst), ei)
    ref, _ = reference_gt(layer, x_src, x_dst, ei)
    torch.testing.assert_close(out, ref, atol=ATOL, rtol=0)


def test_gt_ignores_and_returns_edge_attr():
    torch.manual_seed(2)
    layer = GraphTransformerConv(6, 3, edge_dim=2, heads=2).eval()
    x, ei = torch.randn(5, 6), random_graph(5, 5, 10, False)
    ea = torch.randn(10, 2)
    out_a, e_out = layer(x, ei, ea, return_edge_attr=True)
    out_b, none_out = layer(x, ei, return_edge_attr=True)
    assert e_out is ea and none_out is None
    torch.testing.assert_close(out_a, out_b, atol=0, rtol=0)
    with pytest.raises(ValueError, match="edge_attr"):
        layer(x, ei, torch.randn(10, 5))  # declared width is still checked


@pytest.mark.parametrize("sorted_by_dst", [False, True])
@pytest.mark.parametrize("in_ch,out_ch,heads,concat", WIDTHS)
def test_gt_equals_pyg_transformer_conv(in_ch, out_ch, heads, concat, sorted_by_dst):
    torch.manual_seed(3)
    ours = GraphTransformerConv(in_ch, out_ch, heads=heads, concat=concat).eval()
    pyg = TransformerConv(in_ch, out_ch, heads=heads, concat=concat, root_weight=True).eval()
    with torch.no_grad():
        for name in ("lin_query", "lin_key", "lin_value"):
            getattr(ours, name).load_state_dict(getattr(pyg, name).state_dict())
        ours.lin_out.weight.copy_(torch.eye(ours.lin_out.weight.size(0)))
        ours.lin_out.bias.zero_()
        if ours.lin_skip is None:  # identity skip: make PyG's lin_skip the identity
            pyg.lin_skip.weight.copy_(torch.eye(in_ch))
            pyg.lin_skip.bias.zero_()
        else:
            ours.lin_skip.load_state_dict(pyg.lin_skip.state_dict())
    x = torch.randn(8, in_ch)
    ei = random_graph(8, 8, 24, sorted_by_dst, seed=3)
    out, (_, alpha) = ours(x, ei, return_attention_weights=True)
    ref, (_, ref_alpha) = pyg(x, ei, return_attention_weights=True)
    torch.testing.assert_close(out, ref, atol=ATOL, rtol=0)
    torch.testing.assert_close(alpha, ref_alpha, atol=ATOL, rtol=0)


# --------------------------------------------------------------------------- edge transformer
def reference_edge(layer: EdgeTransformerConv, x, ei, ea):
    H, C = layer.heads, layer.out_channels
    q = lin(layer.lin_query, x).view(-1, H, C)
    k = lin(layer.lin_key, x).view(-1, H, C)
    v = lin(layer.lin_value, x).view(-1, H, C)
    we = lin(layer.lin_edge, ea).view(-1, H, C)
    w_hat = torch.zeros(ei.size(1), H, C)

    def edge_scores(e, i, j):
        w_hat[e] = q[i] * k[j] / math.sqrt(C) * we[e]
        return w_hat[e].sum(-1)

    agg, alpha = loop_attention(q, k, v, ei, x.size(0), edge_scores)
    out = lin(layer.lin_out, heads_out(agg, layer.concat)) + skip(layer, x)
    e_skip = ea if layer.lin_edge_skip is None else lin(layer.lin_edge_skip, ea)
    e_out = lin(layer.lin_edge_out, heads_out(w_hat, layer.concat)) + e_skip
    return out, e_out, alpha


@pytest.mark.parametrize("sorted_by_dst", [False, True])
@pytest.mark.parametrize("edge_out", [None, 5])
@pytest.mark.parametrize("in_ch,out_ch,heads,concat", WIDTHS)
def test_edge_transformer_matches_loop_reference(in_ch, out_ch, heads, concat, edge_out,
                                                 sorted_by_dst):
    torch.manual_seed(4)
    layer = EdgeTransformerConv(in_ch, out_ch, edge_dim=3, heads=heads, concat=concat,
                                edge_out_channels=edge_out).eval()
    assert (layer.lin_edge_skip is None) == (edge_out is None)
    x = torch.randn(7, in_ch)
    ei = random_graph(7, 7, 20, sorted_by_dst, seed=4)
    ea = torch.randn(20, 3)
    out, e_out, (_, alpha) = layer(x, ei, ea, return_attention_weights=True,
                                   return_edge_attr=True)
    ref, ref_e, ref_alpha = reference_edge(layer, x, ei, ea)
    assert e_out.shape == (20, edge_out or 3)
    torch.testing.assert_close(alpha, ref_alpha, atol=ATOL, rtol=0)
    torch.testing.assert_close(out, ref, atol=ATOL, rtol=0)
    torch.testing.assert_close(e_out, ref_e, atol=ATOL, rtol=0)


def test_edge_transformer_needs_edges():
    with pytest.raises(ValueError, match="edge_dim"):
        EdgeTransformerConv(4, 4)
    layer = EdgeTransformerConv(4, 2, edge_dim=3, heads=2)
    with pytest.raises(ValueError, match="edge_attr"):
        layer(torch.randn(3, 4), torch.tensor([[0, 1], [1, 2]]))


def test_edge_transformer_sparse_adjacency_matches_edge_index():
    torch.manual_seed(5)
    layer = EdgeTransformerConv(6, 3, edge_dim=2, heads=2).eval()
    x = torch.randn(6, 6)
    ei = torch.tensor([[1, 2, 0, 3, 5, 4, 0, 2], [0, 0, 1, 2, 2, 3, 4, 5]])  # sorted, no dups
    ea = torch.randn(8, 2)
    adj_t = torch.sparse_coo_tensor(ei.flip(0), ea, (6, 6, 2)).coalesce()  # hybrid [N, N, D]
    out_a, e_a = layer(x, ei, ea, return_edge_attr=True)
    out_b, e_b = layer(x, adj_t, return_edge_attr=True)
    torch.testing.assert_close(out_a, out_b, atol=ATOL, rtol=0)
    torch.testing.assert_close(e_a, e_b, atol=ATOL, rtol=0)


# --------------------------------------------------------------------------- structure-aware
@pytest.mark.parametrize("sorted_by_dst", [False, True])
@pytest.mark.parametrize("edge_dim", [None, 3])
@pytest.mark.parametrize("in_ch,out_ch,heads,concat", WIDTHS)
def test_structure_aware_matches_loop_reference(in_ch, out_ch, heads, concat, edge_dim,
                                                sorted_by_dst):
    torch.manual_seed(6)
    layer = StructureAwareTransformerConv(in_ch, out_ch, edge_dim=edge_dim, heads=heads,
                                          concat=concat).eval()
    x = torch.randn(7, in_ch)
    ei = random_graph(7, 7, 20, sorted_by_dst, seed=6)
    ea = torch.randn(20, 3) if edge_dim else None
    out, e_out, (_, alpha) = layer(x, ei, ea, return_attention_weights=True,
                                   return_edge_attr=True)
    assert e_out is ea

    H, C = heads, out_ch
    phi = layer.extract(x, ei, ea)
    assert phi.shape == (7, in_ch)
    q = lin(layer.lin_query, phi).view(-1, H, C)
    k = lin(layer.lin_key, phi).view(-1, H, C)
    v = lin(layer.lin_value, x).view(-1, H, C)
    agg, ref_alpha = loop_attention(q, k, v, ei, 7)
    ref = lin(layer.lin_out, heads_out(agg, concat)) + skip(layer, x)
    torch.testing.assert_close(alpha, ref_alpha, atol=ATOL, rtol=0)
    torch.testing.assert_close(out, ref, atol=ATOL, rtol=0)


def _path_graph(n: int) -> torch.Tensor:
    a = torch.arange(n - 1)
    return torch.cat([torch.stack([a, a + 1]), torch.stack([a + 1, a])], 1)


@pytest.mark.parametrize("edge_dim", [None, 2])
def test_structure_extractor_sees_exactly_k_hops(edge_dim):
    torch.manual_seed(7)
    layer = StructureAwareTransformerConv(4, 2, edge_dim=edge_dim, heads=2, k_hops=2).eval()
    ei = _path_graph(6)  # 0 - 1 - 2 - 3 - 4 - 5
    ea = torch.randn(ei.size(1), 2) if edge_dim else None
    x = torch.randn(6, 4)
    base = layer.extract(x, ei, ea)[0]

    def changed(x2=x, ei2=ei, ea2=ea) -> bool:
        return not torch.allclose(layer.extract(x2, ei2, ea2)[0], base, atol=1e-6, rtol=0)

    x_hop2, x_hop3 = x.clone(), x.clone()
    x_hop2[2] += 1.0
    x_hop3[3] += 1.0
    assert changed(x2=x_hop2)        # node 2 is two hops from node 0
    assert not changed(x2=x_hop3)    # node 3 is three hops away
    # removing the edge 2 -> 1 (the graph two hops from node 0) changes phi_0 ...
    keep = ~((ei[0] == 2) & (ei[1] == 1))
    assert changed(ei2=ei[:, keep], ea2=None if ea is None else ea[keep])
    # ... removing 3 -> 2 does not
    keep = ~((ei[0] == 3) & (ei[1] == 2))
    assert not changed(ei2=ei[:, keep], ea2=None if ea is None else ea[keep])
    if edge_dim:
        ea2 = ea.clone()
        ea2[((ei[0] == 2) & (ei[1] == 1)).nonzero().item()] += 1.0
        assert changed(ea2=ea2)
        ea3 = ea.clone()
        ea3[((ei[0] == 3) & (ei[1] == 2)).nonzero().item()] += 1.0
        assert not changed(ea2=ea3)


@pytest.mark.parametrize("edge_dim", [None, 2])
def test_structure_aware_bipartite_is_the_graph_on_both_node_sets(edge_dim):
    """A bipartite call equals the same layer on the graph whose nodes are the sources
    followed by the targets (targets' rows of the output)."""
    torch.manual_seed(10)
    layer = StructureAwareTransformerConv((4, 4), 3, heads=2, edge_dim=edge_dim).eval()
    x_src, x_dst = torch.randn(6, 4), torch.randn(4, 4)
    ei = random_graph(6, 4, 12, False, seed=10)
    ea = torch.randn(12, 2) if edge_dim else None
    out = layer((x_src, x_dst), ei, ea)
    union = torch.stack([ei[0], ei[1] + 6])
    ref = layer(torch.cat([x_src, x_dst]), union, ea)[6:]
    torch.testing.assert_close(out, ref, atol=ATOL, rtol=0)
    # different widths: each side is mapped to the extractor's width first
    wide = StructureAwareTransformerConv((4, 5), 3, heads=2, edge_dim=edge_dim).eval()
    assert wide.lin_extract_src is not None and wide.lin_extract_dst is not None
    assert wide((x_src, torch.randn(4, 5)), ei, ea).shape == (4, 6)
    with pytest.raises(ValueError, match="k_hops"):
        StructureAwareTransformerConv(4, 2, k_hops=0)


# --------------------------------------------------------------------------- GAT
@pytest.mark.parametrize("sorted_by_dst", [False, True])
@pytest.mark.parametrize("edge_dim", [None, 3])
@pytest.mark.parametrize("in_ch,out_ch,heads,concat", WIDTHS)
def test_gat_matches_standalone_gatv2(in_ch, out_ch, heads, concat, edge_dim, sorted_by_dst):
    torch.manual_seed(8)
    layer = GATBaselineConv(in_ch, out_ch, edge_dim=edge_dim, heads=heads, concat=concat).eval()
    ref_gat = GATv2Conv(in_ch, out_ch, heads=heads, concat=concat, edge_dim=edge_dim,
                        add_self_loops=False).eval()
    ref_gat.load_state_dict(layer.gat.state_dict())
    x = torch.randn(7, in_ch)
    ei = random_graph(7, 7, 20, sorted_by_dst, seed=8)
    ea = torch.randn(20, 3) if edge_dim else None
    out, e_out, (ei_ret, alpha) = layer(x, ei, ea, return_attention_weights=True,
                                        return_edge_attr=True)
    ref, (_, ref_alpha) = ref_gat(x, ei, ea, return_attention_weights=True)
    ref = ref + skip(layer, x)
    assert e_out is ea
    assert torch.equal(ei_ret, ei) and alpha.shape == (20, heads)
    torch.testing.assert_close(out, ref, atol=ATOL, rtol=0)
    torch.testing.assert_close(alpha, ref_alpha, atol=ATOL, rtol=0)


def test_gat_rejects_double_residual():
    with pytest.raises(ValueError, match="residual"):
        GATBaselineConv(4, 4, residual=True)


# --------------------------------------------------------------------------- contract
@pytest.mark.parametrize("name", sorted(LAYERS))
def test_contract_shapes_grads_and_validation(name):
    torch.manual_seed(9)
    layer = make_layer(name, 5, 3, edge_dim=2, heads=2, dropout=0.1).train()
    x = torch.randn(6, 5, requires_grad=True)
    ei = random_graph(6, 6, 14, False, seed=9)
    ea = torch.randn(14, 2)
    out, e_out, (_, alpha) = layer(x, ei, ea, return_attention_weights=True,
                                   return_edge_attr=True)
    assert out.shape == (6, 6) and e_out.shape == (14, 2) and alpha.shape == (14, 2)
    (out.sum() + e_out.sum()).backward()
    assert torch.isfinite(x.grad).all()
    assert name in repr(layer) or type(layer).__name__ in repr(layer)

    bad_x = torch.randn(6, 5)
    bad_x[0, 0] = float("nan")
    with pytest.raises(ValueError, match="`x`"):
        layer(bad_x, ei, ea)
    with pytest.raises(ValueError, match="edge_index"):
        layer(torch.randn(6, 5), ei + 10, ea)
    for kwargs, arg in (({"heads": 0}, "heads"), ({"dropout": 1.0}, "dropout"),
                        ({"edge_dim": -1}, "edge_dim")):
        with pytest.raises(ValueError, match=arg):
            make_layer(name, 5, 3, **{"edge_dim": 2, **kwargs})
    with pytest.raises(ValueError, match="out_channels"):
        make_layer(name, 5, 0, edge_dim=2)

    layer.reset_parameters()  # must not fail
