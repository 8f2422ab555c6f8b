"""The common layer contract, checked for every layer the registry finds (each class with
a ``layer_name`` in a ``garmentgnn/nn/*_conv.py`` file: a new layer file is checked
without editing this test)."""
import pytest
import torch
from conftest import random_graph
from torch_geometric import EdgeIndex
from torch_geometric.data import Batch, Data

from garmentgnn.nn import LAYERS, make_layer
from garmentgnn.nn._linear import NarrowLinear

NAMES = sorted(LAYERS)
EDGE_DIM = 4


def build(name, in_ch=6, out_ch=4, heads=2, concat=True, **kw):
    torch.manual_seed(0)
    return make_layer(name, in_ch, out_ch, edge_dim=EDGE_DIM, heads=heads, concat=concat, **kw)


def run(layer, x, ei, e):
    out, e_out = layer(x, ei, e, return_edge_attr=True)
    return out, e_out


def uses_edges(name):
    """Whether layer ``name``, built with ``edge_dim``, reads edge features."""
    return bool(build(name).requires_edge_attr)


def test_registry_finds_every_layer_file():
    """Each ``*_conv.py`` module of the package holds one named layer, and the registry
    has them all (the paper's SAT layer and its four baselines among them); a class path
    names a layer outside the package; anything else is refused naming both forms."""
    import pkgutil  # noqa: PLC0415
    from pathlib import Path  # noqa: PLC0415

    import garmentgnn.nn as gnn  # noqa: PLC0415
    files = {i.name for i in pkgutil.iter_modules([str(Path(gnn.__file__).parent)])
             if i.name.endswith("_conv")}
    assert {LAYERS[n].__module__.rsplit(".", 1)[-1] for n in NAMES} == files
    assert {"sat", "gt", "gt_edge", "structure_aware", "gat"} <= set(NAMES)
    assert all(LAYERS[n].layer_name == n for n in NAMES)
    assert {n: uses_edges(n) for n in ("sat", "gt", "gt_edge", "structure_aware", "gat")} \
        == {"sat": True, "gt": False, "gt_edge": True, "structure_aware": True, "gat": True}
    by_path = make_layer("garmentgnn.nn.sat_conv.SATConv", 4, 4, edge_dim=EDGE_DIM)
    assert type(by_path) is LAYERS["sat"]
    for bad in ("nope", "garmentgnn.nn.no_such.Conv", "torch.tensor"):
        with pytest.raises(ValueError, match="`name`: unknown layer .*class path"):
            make_layer(bad, 4, 4)


@pytest.mark.parametrize("name", NAMES)
def test_batched_mesh_graph_equals_separate_graphs(name, mesh_graph):
    pos, _, ei, e = mesh_graph
    layer = build(name).eval()
    graphs = []
    for s in range(3):
        gen = torch.Generator().manual_seed(s)
        x = torch.cat([pos, torch.randn(pos.size(0), 3, generator=gen)], -1)
        graphs.append(Data(x=x, edge_index=ei, edge_attr=e + 0.1 * s))
    batch = Batch.from_data_list(graphs)
    out, e_out = run(layer, batch.x, batch.edge_index, batch.edge_attr)
    assert out.shape == (batch.num_nodes, 8)
    assert torch.isfinite(out).all()
    for s, g in enumerate(graphs):
        o, eo = run(layer, g.x, g.edge_index, g.edge_attr)
        torch.testing.assert_close(out[batch.ptr[s]:batch.ptr[s + 1]], o, atol=1e-5, rtol=1e-5)
        if eo is not None:
            m = batch.batch[batch.edge_index[0]] == s
            torch.testing.assert_close(e_out[m], eo, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("name", NAMES)
def test_permutation_equivariance(name):
    N = 10
    ei = random_graph(N, 30, seed=7)
    x, e = torch.randn(N, 6), torch.randn(ei.size(1), EDGE_DIM)
    layer = build(name).eval()
    out, e_out = run(layer, x, ei, e)
    perm, eperm = torch.randperm(N), torch.randperm(ei.size(1))
    inv = torch.empty_like(perm)
    inv[perm] = torch.arange(N)
    ei_p = inv[ei][:, eperm]  # node i becomes inv[i]; edges shuffled
    out_p, e_out_p = run(layer, x[perm], ei_p, e[eperm])
    torch.testing.assert_close(out_p, out[perm], atol=1e-5, rtol=1e-5)
    if e_out is not None:
        torch.testing.assert_close(e_out_p, e_out[eperm], atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("form", ["coo_hybrid", "csr", "edge_index_obj"])
@pytest.mark.parametrize("grad", [True, False])
def test_sparse_adjacency_matches_edge_index(name, form, grad):
    """Sparse adj_t (CSR order) equals unsorted edge_index; without autograd the CSR
    order also switches on the sparse-kernel path, which must agree too."""
    N = 9
    ei = random_graph(N, 25, seed=8)
    ei = torch.unique(ei, dim=1)  # sparse adjacency cannot hold duplicate edges
    x, e = torch.randn(N, 6), torch.randn(ei.size(1), EDGE_DIM)
    layer = build(name).eval()
    out, e_out = run(layer, x, ei, e)
    # row-major order of adj_t: sorted by (target, source)
    order = torch.argsort(ei[1] * N + ei[0])
    with torch.set_grad_enabled(grad):
        if form == "coo_hybrid":
            adj_t = torch.sparse_coo_tensor(ei.flip(0), e, (N, N, EDGE_DIM))
            out_s, e_out_s = layer(x, adj_t, return_edge_attr=True)
        elif form == "csr":
            adj_t = torch.sparse_coo_tensor(ei.flip(0), torch.ones(ei.size(1)),
                                            (N, N)).to_sparse_csr()
            out_s, e_out_s = layer(x, adj_t, e[order], return_edge_attr=True)
        else:
            eidx = EdgeIndex(ei[:, order], sparse_size=(N, N), sort_order="col")
            out_s, e_out_s = layer(x, eidx, e[order], return_edge_attr=True)
    torch.testing.assert_close(out_s, out, atol=1e-5, rtol=1e-5)
    if e_out is not None:
        torch.testing.assert_close(e_out_s, e_out[order], atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("name", NAMES)
def test_gradcheck(name):
    N = 5
    ei = random_graph(N, 8, seed=9)
    layer = build(name, in_ch=3, out_ch=2).double().eval()
    x = torch.randn(N, 3, dtype=torch.float64, requires_grad=True)
    e = torch.randn(ei.size(1), EDGE_DIM, dtype=torch.float64, requires_grad=uses_edges(name))

    def f(a, b):
        out, e_out = layer(a, ei, b, return_edge_attr=True)
        return out if e_out is None or not e_out.requires_grad else (out, e_out)

    assert torch.autograd.gradcheck(f, (x, e))


@pytest.mark.parametrize("name", NAMES)
def test_torch_compile_matches_eager(name, mesh_graph):
    pos, _, ei, e = mesh_graph
    x = torch.cat([pos, pos.flip(-1)], -1)
    layer = build(name).eval()
    ref, e_ref = run(layer, x, ei, e)
    compiled = torch.compile(layer, backend="aot_eager")
    out = compiled(x, ei, e)
    torch.testing.assert_close(out, ref, atol=1e-5, rtol=1e-5)


@pytest.mark.slow
def test_sat_inductor_compile(mesh_graph):
    pos, _, ei, e = mesh_graph
    x = torch.cat([pos, pos.flip(-1)], -1)
    layer = build("sat").eval()
    ref, e_ref = layer(x, ei, e, return_edge_attr=True)
    out, e_out = torch.compile(layer)(x, ei, e, return_edge_attr=True)
    torch.testing.assert_close(out, ref, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(e_out, e_ref, atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("name", NAMES)
def test_bad_input_raises_value_error_naming_argument(name):
    N = 6
    ei = random_graph(N, 10, seed=10)
    x, e = torch.randn(N, 6), torch.randn(ei.size(1), EDGE_DIM)
    layer = build(name)
    bad_x = x.clone()
    bad_x[2, 1] = float("nan")
    with pytest.raises(ValueError, match="`x`"):
        layer(bad_x, ei, e)
    with pytest.raises(ValueError, match="`edge_index`"):
        layer(x, torch.cat([ei, torch.tensor([[0], [N]])], 1),
              torch.randn(ei.size(1) + 1, EDGE_DIM))
    with pytest.raises(ValueError, match="`edge_index`"):
        layer(x, torch.cat([ei, torch.tensor([[-1], [0]])], 1),
              torch.randn(ei.size(1) + 1, EDGE_DIM))
    with pytest.raises(ValueError, match="`edge_index`"):
        layer(x, ei[0], e)
    if uses_edges(name):
        with pytest.raises(ValueError, match="`edge_attr`"):
            layer(x, ei, e[:-1])  # one row short
        with pytest.raises(ValueError, match="`edge_attr`"):
            layer(x, ei, torch.randn(ei.size(1), EDGE_DIM + 1))  # wrong edge_dim
        bad_e = e.clone()
        bad_e[0, 0] = float("inf")
        with pytest.raises(ValueError, match="`edge_attr`"):
            layer(x, ei, bad_e)
    with pytest.raises(TypeError, match="`edge_index`"):
        layer(x, ei.float(), e)


@pytest.mark.parametrize("name", NAMES)
def test_check_finite_false_skips_the_check(name):
    N = 6
    ei = random_graph(N, 10, seed=11)
    x, e = torch.randn(N, 6), torch.randn(ei.size(1), EDGE_DIM)
    x[0, 0] = float("nan")
    layer = build(name, check_finite=False).eval()
    out = layer(x, ei, e)  # no error: the caller opted out of the finite-value check
    assert out.shape[0] == N


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("concat", [True, False])
def test_widths_and_reset(name, concat):
    layer = build(name, in_ch=5, out_ch=3, heads=2, concat=concat)
    N = 6
    ei = random_graph(N, 12, seed=12)
    out = layer(torch.randn(N, 5), ei, torch.randn(ei.size(1), EDGE_DIM))
    assert out.shape == (N, 6 if concat else 3)
    before = [p.detach().clone() for p in layer.parameters()]
    layer.reset_parameters()
    after = list(layer.parameters())
    assert any(not torch.equal(a, b) for a, b in zip(before, after))
    assert type(layer).__name__ in repr(layer)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_cpu_autocast_low_precision(name, dtype, mesh_graph):
    """CPU autocast works (the CSR kernels have no CPU half kernels, so low-precision
    operands run on them in float32) and stays near float32."""
    pos, _, ei, e = mesh_graph
    x = torch.cat([pos, pos.flip(-1)], -1)
    layer = build(name).eval()
    ref, _ = run(layer, x, ei, e)
    with torch.no_grad(), torch.autocast("cpu", dtype=dtype):
        out, _ = run(layer, x, ei, e)
    assert torch.isfinite(out).all()
    tol = 0.05 if dtype == torch.bfloat16 else 0.01
    assert (out.float() - ref).abs().max() <= tol * (1 + ref.abs().max())


@pytest.mark.parametrize("bias", [False, True])
def test_narrow_linear_traced_equals_the_matmul(bias):
    """``NarrowLinear`` traced by ``torch.compile`` (sums of broadcast products) gives
    ``F.linear``'s values and gradients (input and weight); eager it is ``F.linear``."""
    torch.manual_seed(0)
    lin = NarrowLinear(4, 12, bias=bias).double()
    x = torch.randn(50, 4, dtype=torch.float64, requires_grad=True)

    def loss(f):
        out = f(x)
        return out, torch.autograd.grad((out * torch.arange(12.0).double()).sum(),
                                        [x] + list(lin.parameters()))
    ref, ref_g = loss(lambda v: torch.nn.functional.linear(v, lin.weight, lin.bias))
    got, got_g = loss(torch.compile(lin, backend="aot_eager"))
    torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-12)
    for g, r in zip(got_g, ref_g):
        torch.testing.assert_close(g, r, rtol=1e-12, atol=1e-12)
    assert torch.equal(lin(x), torch.nn.functional.linear(x, lin.weight, lin.bias))
