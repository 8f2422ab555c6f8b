"""The attention steps of :mod:`garmentgnn.nn.functional` against plain gathers and
scatters, the tensor cache the layers and models share, and the layer files' shape
(each layer's equation in its own ``forward``/``message``)."""
from __future__ import annotations

import gc
import inspect

import pytest
import torch
from conftest import random_graph
from torch_geometric.utils import scatter, softmax

from garmentgnn.nn import LAYERS, GraphTransformerConv, SATConv, TensorCache
from garmentgnn.nn._base import AttentionConv
from garmentgnn.nn._graph import prepare_graph
from garmentgnn.nn._sparse import Pattern
from garmentgnn.nn.functional import (attention_route, attention_spmm, csr_kernels, edge_dot,
                                      edge_rows_spmm, edge_softmax, segment_softmax)

N, H, C, D = 9, 3, 5, 4


def graph_and_features(sort: bool):
    ei = random_graph(N, 30, seed=7, sort=sort)
    g = torch.Generator().manual_seed(8)
    q, k, v = (torch.randn(N, H, C, generator=g, dtype=torch.float64) for _ in range(3))
    y = torch.randn(ei.size(1), D, generator=g, dtype=torch.float64)
    x = torch.zeros(N, 1, dtype=torch.float64)
    return prepare_graph(x, ei, None, None, require_edge_attr=False, validate=True), q, k, v, y


@pytest.mark.parametrize("sort", [True, False])
@pytest.mark.parametrize("kernels", [True, False])
def test_attention_steps_match_gathers_and_scatters(sort, kernels):
    """Oracle: per-edge gathers, PyG's ``softmax`` and ``scatter`` sums in the caller's
    edge order, written out here without the module's code."""
    g, q, k, v, y = graph_and_features(sort)
    src, dst = g.edge_index
    want_s = (q[dst] * k[src]).sum(-1)  # [E, H]
    want_a = softmax(want_s, dst, num_nodes=N)
    want_out = scatter(want_a.unsqueeze(-1) * v[src], dst, 0, dim_size=N, reduce="sum")
    want_rows = scatter(want_a.unsqueeze(-1) * y[:, None, :], dst, 0, dim_size=N, reduce="sum")
    with csr_kernels(kernels):
        r = attention_route(g, H, q)
    assert r.fused == kernels
    s = edge_dot(q, k, g, r)
    alpha = edge_softmax(s, r)
    torch.testing.assert_close(r.edges_out(s), want_s)
    torch.testing.assert_close(r.edges_out(alpha), want_a)
    torch.testing.assert_close(r.edges_in(want_a), alpha)
    if kernels:
        torch.testing.assert_close(attention_spmm(alpha, v, g, r), want_out)
        torch.testing.assert_close(edge_rows_spmm(alpha, y, g, r), want_rows)
    else:
        with pytest.raises(ValueError, match="`r`"):
            attention_spmm(alpha, v, g, r)
        with pytest.raises(ValueError, match="`r`"):
            edge_rows_spmm(alpha, y, g, r)


def test_segment_softmax_with_pointer_equals_pyg_softmax():
    """The segment-max route (sorted segments with a CSR pointer) against PyG's
    ``softmax``, with ``-inf`` entries (weight 0) and an empty segment."""
    index = torch.tensor([0, 0, 0, 2, 2, 3])
    ptr = torch.tensor([0, 3, 3, 5, 6])
    src = torch.randn(6, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    src[1, 0] = float("-inf")
    out = segment_softmax(src, index, 4, ptr)
    torch.testing.assert_close(out, softmax(src, index, num_nodes=4))
    assert out[1, 0] == 0


def test_tensor_cache_follows_identity_version_and_lifetime():
    cache = TensorCache(maxsize=2)
    a, b = torch.arange(4), torch.arange(3)
    cache.store(a, "a3", 3)
    cache.store(a, "a5", 5)
    assert cache.lookup(a, 3) == "a3" and cache.lookup(a, 5) == "a5"
    assert cache.lookup(a) is None and cache.lookup(b, 3) is None
    cache.store(b, "b")  # over maxsize: the oldest entry goes
    assert cache.lookup(a, 3) is None and cache.lookup(a, 5) == "a5"
    b.add_(1)  # an in-place edit bumps the version: a miss
    assert cache.lookup(b) is None
    key = id(b)
    del b  # freed with its tensor
    assert key not in cache
    with torch.inference_mode():  # no version counter: never stored
        c = torch.arange(2)
        cache.store(c, "c")
        assert cache.lookup(c) is None


@pytest.mark.parametrize("name", sorted(LAYERS))
def test_each_layer_writes_its_own_forward_and_message(name):
    """A reader finds the layer's computation where PyG's convs have it: ``forward`` in
    the layer's own class and, for the attention layers, which sum with ``propagate``,
    their own ``message``."""
    cls = LAYERS[name]
    assert "forward" in vars(cls)
    assert not hasattr(cls, "compute")
    if issubclass(cls, AttentionConv):
        assert "message" in vars(cls)
    assert list(inspect.signature(cls.forward).parameters) == [
        "self", "x", "edge_index", "edge_attr", "return_attention_weights", "return_edge_attr"]


@pytest.mark.parametrize("cls, numbers", [(SATConv, ("(5)", "(6)")),
                                          (GraphTransformerConv, ("(3)", "(4)"))])
def test_paper_equations_are_numbered_in_forward(cls, numbers):
    source = inspect.getsource(cls.forward)
    for number in numbers:
        assert f"Eq. {number}" in source


@pytest.mark.parametrize("layer", [SATConv, GraphTransformerConv])
def test_a_training_step_leaves_no_tensor_in_a_reference_cycle(layer):
    """Forward and backward build the graph's sparse patterns and their transposes; once
    the step's objects are gone nothing of it may wait for the cyclic garbage collector
    (Python's ``gc`` with ``DEBUG_SAVEALL`` is the oracle): a pattern and its transpose
    referring to each other kept every step's index tensors alive until a full
    collection, and a long fit's memory grew by tens of MB a step."""
    ei = random_graph(60, 400, seed=3)
    conv = layer(8, 4, heads=2, edge_dim=3)
    gc.collect()
    gc.disable()
    try:
        for seed in range(3):  # a new graph (a new plan and patterns) every step
            g = torch.Generator().manual_seed(seed)
            x = torch.randn(60, 8, generator=g, requires_grad=True)
            e = torch.randn(ei.size(1), 3, generator=g)
            out = conv(x, ei.clone(), e)
            out = out[0] if isinstance(out, tuple) else out
            out.square().sum().backward()
        del x, e, out
        gc.set_debug(gc.DEBUG_SAVEALL)
        gc.collect()
        left = [type(o).__name__ for o in gc.garbage
                if isinstance(o, torch.Tensor) or type(o).__module__.startswith("garmentgnn")]
    finally:
        gc.set_debug(0)
        gc.garbage.clear()
        gc.enable()
    assert left == []


def test_pattern_transpose_against_dense_and_without_its_parent():
    """``Pattern.T`` and ``to_t`` against the dense transpose (the oracle); ``T.T`` is
    the pattern itself while it lives, and a transpose that outlives it builds it again."""
    g = torch.Generator().manual_seed(0)
    dense = (torch.rand(5, 7, generator=g) < 0.4).float()
    dense[0, 0] = 1.0
    csr = dense.to_sparse_csr()
    pat = Pattern(csr.crow_indices(), csr.col_indices(), (5, 7))
    values = torch.randn(int(dense.sum()), generator=g)
    m = pat.matrix(values).to_dense()
    t = pat.T
    t_values = values[pat.to_t]
    assert torch.equal(t.matrix(t_values).to_dense(), m.t())
    assert t.T is pat
    assert torch.equal(t_values[t.to_t], values)  # the transpose's map leads back
    ptr, col = pat.ptr, pat.col
    del pat
    gc.collect()
    again = t.T  # the parent is gone: built from the transpose
    assert torch.equal(again.ptr, ptr) and torch.equal(again.col, col)
    assert torch.equal(again.matrix(t_values[t.to_t]).to_dense(), m)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_pattern_product_ignores_what_its_output_held(dtype):
    """``Pattern.mm`` (``addmm`` with ``beta=0`` into an uninitialised output, int32
    indices) equals the dense product, also written into a NaN-filled output, with an
    empty row and a row holding every column."""
    g = torch.Generator().manual_seed(1)
    dense = (torch.rand(6, 9, generator=g) < 0.4).to(dtype)
    dense[2] = 0.0
    dense[4] = 1.0
    csr = dense.to_sparse_csr()
    pat = Pattern(csr.crow_indices(), csr.col_indices(), (6, 9))
    values = torch.randn(int(dense.sum()), generator=g, dtype=dtype)
    m = torch.zeros(6, 9, dtype=dtype)
    m[dense.bool()] = values  # row-major order = CSR order
    b = torch.randn(9, 5, generator=g, dtype=dtype)
    torch.testing.assert_close(pat.mm(values, b), m @ b)
    out = torch.full((6, 5), float("nan"), dtype=dtype)
    got = pat.mm(values, b, out=out)
    assert got.data_ptr() == out.data_ptr()
    torch.testing.assert_close(got, m @ b)
    assert all(i.dtype == torch.int32 for i in pat.kernel_indices())


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_half_precision_runs_on_the_kernels_in_float32_under_autocast(dtype):
    """Under autocast, half-precision operands take the fused route and the kernels run
    them in float32; outside it they take the message route (a model cast to half
    precision would meet float32 results).  Oracle: gathers, PyG's ``softmax`` and
    ``scatter`` sums in float64 of the same rounded values, and their gradients."""
    g, q, k, v, y = graph_and_features(False)
    half = [t.to(dtype).requires_grad_() for t in (q, k, v, y)]
    assert not attention_route(g, H, half[0]).fused
    with torch.autocast("cpu", dtype=dtype):
        r = attention_route(g, H, half[0])
        assert r.fused
        alpha = edge_softmax(edge_dot(half[0], half[1], g, r), r)
        got = [attention_spmm(alpha, half[2], g, r), edge_rows_spmm(alpha, half[3], g, r)]
    assert all(t.dtype == torch.float32 for t in got)
    src, dst = g.edge_index
    exact = [t.detach().double().requires_grad_() for t in half]
    a = softmax((exact[0][dst] * exact[1][src]).sum(-1), dst, num_nodes=N)
    want = [scatter(a.unsqueeze(-1) * exact[2][src], dst, 0, dim_size=N, reduce="sum"),
            scatter(a.unsqueeze(-1) * exact[3][:, None, :], dst, 0, dim_size=N, reduce="sum")]
    for o, w in zip(got, want):
        torch.testing.assert_close(o.double(), w, rtol=1e-5, atol=1e-5)
    w = torch.randn(N, H, C + D, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    grads = torch.autograd.grad((torch.cat(got, -1) * w).sum(), half)
    want_g = torch.autograd.grad((torch.cat(want, -1) * w).sum(), exact)
    for gh, gw in zip(grads, want_g):  # each rounded once to the operand's dtype
        assert gh.dtype == dtype
        torch.testing.assert_close(gh.double(), gw, rtol=1e-2, atol=1e-2 * gw.abs().max())
