"""SATConv against a loop-based reference of the paper's Eqs. (5)-(6)."""
import math

import pytest
import torch
from conftest import random_graph

from garmentgnn.nn import SATConv
from garmentgnn.nn._sparse import csr_kernels


def reference_sat(conv: SATConv, x, edge_index, e, drop=None):
    """Eqs. (5)-(6) written edge by edge and node by node, in float64.  Edge ``drop``
    (an index) keeps its attention weight but contributes no message, which is what an
    explainer's edge mask of 0 means (as for PyG's convs)."""
    H, C = conv.heads, conv.out_channels
    x, e = x.double(), e.double()

    def lin(m, t):
        return t @ m.weight.double().t() + (m.bias.double() if m.bias is not None else 0.0)

    q = lin(conv.lin_query, x).view(-1, H, C)
    k = lin(conv.lin_key, x).view(-1, H, C)
    v = lin(conv.lin_value, x).view(-1, H, C)
    N, E = x.size(0), edge_index.size(1)
    h = torch.zeros(E, H, dtype=torch.float64)
    for n in range(E):
        j, i = int(edge_index[0, n]), int(edge_index[1, n])
        p = lin(conv.lin_edge_gate, e[n])  # one gate per head
        for hd in range(H):
            h[n, hd] = (q[i, hd] @ k[j, hd]) / math.sqrt(C) * torch.sigmoid(p[hd])
    agg = torch.zeros(N, H, C, dtype=torch.float64)
    for i in range(N):
        inc = (edge_index[1] == i).nonzero().flatten()
        if inc.numel() == 0:
            continue
        for hd in range(H):
            a = torch.softmax(h[inc, hd], 0)
            for w, n in zip(a, inc):
                if drop is not None and int(n) == drop:
                    continue
                qe = lin(conv.lin_edge_value, e[n]).view(H, C)[hd]
                agg[i, hd] += w * (v[int(edge_index[0, n]), hd] + qe)
    heads = agg.reshape(N, H * C) if conv.concat else agg.mean(1)
    out = lin(conv.lin_out, heads) + (x if conv.lin_skip is None else lin(conv.lin_skip, x))
    e_out = lin(conv.lin_edge_out, h) + (e if conv.lin_edge_skip is None
                                         else lin(conv.lin_edge_skip, e))
    return out, e_out, h


@pytest.mark.parametrize("concat", [True, False])
@pytest.mark.parametrize("in_ch,edge_out", [(8, None), (5, 6)])
@pytest.mark.parametrize("sort,grad,kernels", [(False, True, True), (True, True, True),
                                               (True, False, True), (False, True, False)])
def test_matches_dense_reference(concat, in_ch, edge_out, sort, grad, kernels):
    """Both edge orders on the fused route (sparse SDDMM/SpMM kernels; unsorted edges are
    sorted internally), with and without autograd, and the message route (kernels off:
    propagate), all match the reference."""
    torch.manual_seed(0)
    N, H, C, D = 9, 2, 4, 3
    if concat is False and in_ch == 8:
        in_ch = C  # equal widths for the mean-of-heads case
    ei = random_graph(N, 25, seed=3, sort=sort)
    x, e = torch.randn(N, in_ch), torch.randn(ei.size(1), D)
    conv = SATConv(in_ch, C, edge_dim=D, heads=H, concat=concat, edge_out_channels=edge_out).eval()
    width = H * C if concat else C
    assert (conv.lin_skip is None) == (in_ch == width)
    assert (conv.lin_edge_skip is None) == (edge_out in (None, D))
    with torch.set_grad_enabled(grad), csr_kernels(kernels):
        out, e_out, (ei_ret, alpha) = conv(x, ei, e, return_attention_weights=True,
                                           return_edge_attr=True)
    ref_out, ref_e, ref_h = reference_sat(conv, x, ei, e)
    torch.testing.assert_close(out.double(), ref_out, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(e_out.double(), ref_e, atol=1e-5, rtol=1e-5)
    assert torch.equal(ei_ret, ei)
    # attention weights: a distribution over incoming edges of every node
    sums = torch.zeros(N, H).index_add_(0, ei[1], alpha)
    torch.testing.assert_close(sums, torch.ones(N, H))


def test_isolated_node_gets_only_skip():
    torch.manual_seed(0)
    conv = SATConv(4, 4, edge_dim=2, heads=1).eval()
    x = torch.randn(3, 4)
    ei = torch.tensor([[0], [1]])  # node 2 has no incoming edge
    out = conv(x, ei, torch.randn(1, 2))
    torch.testing.assert_close(out[2], conv.lin_out.bias + x[2])


@pytest.mark.parametrize("sort", [False, True])
def test_attention_mask_never_nan_and_keeps_one_edge(sort):
    torch.manual_seed(0)
    N = 12
    ei = random_graph(N, 60, seed=1, sort=sort)
    x, e = torch.randn(N, 8), torch.randn(ei.size(1), 3)
    conv = SATConv(8, 4, edge_dim=3, heads=2, attn_mask_p=1.0).train()
    out, e_out, (_, alpha) = conv(x, ei, e, return_attention_weights=True,
                                  return_edge_attr=True)
    assert torch.isfinite(out).all() and torch.isfinite(e_out).all()
    # with p = 1 exactly one incoming edge per node and head survives, with weight 1
    nonzero = torch.zeros(N, 2).index_add_(0, ei[1], (alpha > 0).float())
    assert torch.equal(nonzero, torch.ones(N, 2))
    out.sum().backward()
    assert all(torch.isfinite(p.grad).all() for p in conv.parameters() if p.grad is not None)
    # in eval mode the mask is off
    conv.eval()
    _, (_, alpha) = conv(x, ei, e, return_attention_weights=True)
    assert (alpha > 0).all()


def test_attention_mask_drops_a_fraction():
    torch.manual_seed(0)
    N = 200
    ei = random_graph(N, 4000, seed=2)
    conv = SATConv(4, 4, edge_dim=1, attn_mask_p=0.3).train()
    _, (_, alpha) = conv(torch.randn(N, 4), ei, torch.randn(ei.size(1), 1),
                            return_attention_weights=True)
    frac = (alpha == 0).float().mean().item()
    assert 0.2 < frac < 0.3  # 0.3 minus the one kept edge per node


@pytest.mark.parametrize("sort", [False, True])
def test_gradcheck_float64(sort):
    """Finite differences check both the autograd (gather) path and the hand-written
    backward of the CSR kernels."""
    torch.manual_seed(0)
    N = 5
    ei = random_graph(N, 8, seed=4, sort=sort)
    conv = SATConv(3, 2, edge_dim=2, heads=2, edge_out_channels=3).double().eval()
    x = torch.randn(N, 3, dtype=torch.float64, requires_grad=True)
    e = torch.randn(ei.size(1), 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: conv(a, ei, b, return_edge_attr=True), (x, e))


def test_repr_and_reset():
    conv = SATConv(16, 8, edge_dim=4, heads=4)
    assert repr(conv) == ("SATConv(16, 8, heads=4, edge_dim=4, edge_out_channels=4, "
                          "concat=True)")
    w = conv.lin_query.weight.detach().clone()
    conv.reset_parameters()
    assert not torch.equal(w, conv.lin_query.weight)


def test_bipartite_matches_shared_input():
    torch.manual_seed(0)
    N = 7
    ei = random_graph(N, 20, seed=5)
    x, e = torch.randn(N, 6), torch.randn(ei.size(1), 2)
    conv = SATConv(6, 3, edge_dim=2, heads=2).eval()
    a, ea = conv(x, ei, e, return_edge_attr=True)
    b, eb = conv((x, x), ei, e, return_edge_attr=True)
    torch.testing.assert_close(a, b)
    torch.testing.assert_close(ea, eb)


@pytest.mark.parametrize("kwargs", [dict(attn_mask_p=1.5), dict(dropout=1.0), dict(heads=0)])
def test_constructor_rejects_bad_arguments(kwargs):
    args = dict(in_channels=4, out_channels=4, edge_dim=2)
    args.update(kwargs)
    name = next(iter(kwargs))
    with pytest.raises(ValueError, match=name):
        SATConv(**args)
