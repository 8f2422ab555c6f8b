"""Edge cases of the layers' inputs: empty graphs, overflowing features, bad constructor
arguments, the per-graph CSR plan, and no import-time side effects."""
from __future__ import annotations

import subprocess
import sys
import types
import warnings
from pathlib import Path

import pytest
import torch

import garmentgnn.nn
from garmentgnn.nn import LAYERS, SATConv, _graph
from garmentgnn.nn.functional import csr_kernels

from conftest import random_graph

NAMES = sorted(LAYERS)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("nodes", [0, 5])
def test_graph_without_edges_gives_empty_or_skip_outputs(name, nodes):
    torch.manual_seed(0)
    layer = LAYERS[name](6, 4, 2, edge_dim=3).eval()
    x = torch.randn(nodes, 6)
    ei, e = torch.empty(2, 0, dtype=torch.long), torch.empty(0, 3)
    out, e_out, (ei_out, alpha) = layer(x, ei, e, return_attention_weights=True,
                                        return_edge_attr=True)
    assert out.shape == (nodes, 8) and torch.isfinite(out).all()
    assert e_out.shape == (0, 3) and alpha.shape == (0, 2) and ei_out.shape == (2, 0)
    if nodes and name != "structure_aware":  # no messages: what the skip and biases give
        ref = layer(x, torch.tensor([[0], [1]]), torch.randn(1, 3))
        torch.testing.assert_close(out[2:], ref[2:])


@pytest.mark.parametrize("name", NAMES)
def test_overflowing_features_raise_instead_of_returning_nan(name):
    torch.manual_seed(0)
    ei = random_graph(8, 20, seed=1)
    x, e = torch.randn(8, 6) * 1e20, torch.randn(ei.size(1), 3)
    layer = LAYERS[name](6, 4, 2, edge_dim=3).eval()
    raw = LAYERS[name](6, 4, 2, edge_dim=3, check_finite=False).eval()
    raw.load_state_dict(layer.state_dict())
    out = raw(x, ei, e)
    if torch.isfinite(out).all():  # this layer copes with the range: nothing to report
        torch.testing.assert_close(layer(x, ei, e), out)
        return
    with pytest.raises(ValueError, match=r"`x`.*overflowed"):
        layer(x, ei, e)


@pytest.mark.parametrize("name", NAMES)
def test_nan_inputs_are_named(name):
    ei = random_graph(6, 10, seed=2)
    x, e = torch.randn(6, 6), torch.randn(ei.size(1), 3)
    layer = LAYERS[name](6, 4, 2, edge_dim=3)
    x[1, 2] = float("nan")
    with pytest.raises(ValueError, match="`x`: contains 1 NaN/inf"):
        layer(x, ei, e)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("args,kwargs,arg", [
    ((6, 4, 0), {}, "heads"),
    ((6, 4, -2), {}, "heads"),
    ((6, 4, True), {}, "heads"),
    ((0, 4), {}, "in_channels"),
    (((6, -3), 4), {}, "in_channels"),
    (("6", 4), {}, "in_channels"),
    ((6, 0), {}, "out_channels"),
    ((6, 4), {"edge_dim": 0}, "edge_dim"),
    ((6, 4), {"dropout": 1.0}, "dropout"),
])
def test_bad_constructor_arguments_raise_value_error(name, args, kwargs, arg):
    kwargs = {"edge_dim": 3, **kwargs}
    with pytest.raises(ValueError, match=f"`{arg}`"):
        LAYERS[name](*args, **kwargs)


def test_sat_needs_edge_dim_and_keyword_options():
    with pytest.raises(ValueError, match="`edge_dim`"):
        SATConv(6, 4, 2)
    with pytest.raises(TypeError):  # options after `concat` are keyword-only
        SATConv(6, 4, 2, True, 3)
    with pytest.raises(ValueError, match="`edge_out_channels`"):
        SATConv(6, 4, 2, edge_dim=3, edge_out_channels=0)


def test_plan_is_built_once_per_graph_and_follows_in_place_edits():
    torch.manual_seed(0)
    ei = random_graph(10, 40, seed=3)  # unsorted
    e = torch.randn(ei.size(1), 3)
    x = torch.randn(10, 6)
    layer = SATConv(6, 4, 2, edge_dim=3).eval()
    out = layer(x, ei, e)
    plan = _graph._PLANS[id(ei)][2]
    assert plan.perm is not None  # unsorted edges: sorted internally for the kernels
    layer(x, ei, e)
    assert _graph._PLANS[id(ei)][2] is plan  # reused
    with torch.inference_mode():  # a plan first built in inference mode serves autograd
        ei2 = ei.clone()
        layer(x, ei2, e)
    layer.train()
    layer(x, ei2, e).sum().backward()
    layer.eval()
    ei[:, [0, 1]] = ei[:, [1, 0]]  # an in-place edit invalidates the cached plan
    e[[0, 1]] = e[[1, 0]]
    torch.testing.assert_close(layer(x, ei, e), out, atol=1e-5, rtol=1e-5)
    assert _graph._PLANS[id(ei)][2] is not plan
    key = id(ei)
    del ei
    assert key not in _graph._PLANS  # freed with its tensor


def test_no_process_wide_warning_filters_from_import_or_calls():
    """Running every module of garmentgnn.nn again (as an import does) and calling a
    layer on the sparse kernels leave ``warnings.filters`` as they were."""
    with warnings.catch_warnings():
        warnings.resetwarnings()  # no filters at all while the modules run
        for path in sorted(Path(garmentgnn.nn.__file__).parent.glob("*.py")):
            probe = types.ModuleType("garmentgnn_nn_probe")
            sys.modules[probe.__name__] = probe
            try:
                exec(compile(path.read_text(), str(path), "exec"), probe.__dict__)
            finally:
                del sys.modules[probe.__name__]
            assert warnings.filters == [], path.name
    before = list(warnings.filters)
    ei = random_graph(10, 40, seed=5)
    layer = SATConv(6, 4, 2, edge_dim=3)
    layer(torch.randn(10, 6), ei, torch.randn(ei.size(1), 3)).sum().backward()
    assert warnings.filters == before


_BAD_INDEX = """
import torch
from garmentgnn.nn import LAYERS
for name in sorted(LAYERS):
    for bad in (-1, 5, 100000):
        layer = LAYERS[name](8, 4, 2, edge_dim=3, validate=False)
        ei = torch.tensor([[0, 1, bad], [1, 2, 3]])
        try:
            layer(torch.randn(5, 8), ei, torch.randn(3, 3))
            print(name, bad, "no error")
        except ValueError as e:
            print(name, bad, e)
"""


def test_out_of_range_index_with_validate_false_is_an_error_not_a_crash():
    """``validate=False``, index -1 / 5 / 100000 on 5 nodes: SATConv died with SIGSEGV
    (-1) or returned numbers read past the node features (5).  In a subprocess, so a
    crash fails this test instead of ending the run."""
    root = Path(__file__).resolve().parents[1]
    r = subprocess.run([sys.executable, "-c", _BAD_INDEX], capture_output=True, text=True,
                       timeout=300, env={"PYTHONPATH": str(root / "src"), "OMP_NUM_THREADS": "1",
                                         "PATH": "/usr/bin:/bin"})
    assert r.returncode == 0, r.stderr[-800:]
    lines = r.stdout.splitlines()
    assert len(lines) == 3 * len(NAMES), r.stdout
    for line in lines:
        name, bad, msg = line.split(" ", 2)
        assert msg.startswith("`edge_index`: source indices span"), line
        assert bad + "]" in msg or "[" + bad + "," in msg, line


def _inputs():
    torch.manual_seed(0)
    ei = random_graph(6, 14, seed=2)
    return torch.randn(6, 8), ei, torch.randn(ei.size(1), 3)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("case, error, words", [
    ("x float64, edge_attr float32", TypeError, ["`x`", "float64", "weights are torch.float32"]),
    ("edge_attr float64", TypeError, ["`edge_attr`", "float64", "x's torch.float32"]),
    ("7 columns for in_channels=8", ValueError, ["`x`", "7 columns", "in_channels=8"]),
    ("integer features", TypeError, ["`x`", "floating-point", "torch.int64"]),
    ("integer edge features", TypeError, ["`edge_attr`", "floating-point"]),
    ("x on meta, layer on cpu", ValueError, ["`x`", "meta", "cpu"]),
])
def test_feature_dtype_width_and_device_are_named(name, case, error, words):
    """Where torch said ``mat1 and mat2 must have the same dtype`` or ``shapes cannot be
    multiplied``, the layer names the argument and the width / dtype it expects."""
    layer = LAYERS[name](8, 4, 2, edge_dim=3)
    x, ei, e = _inputs()
    x, e = {"x float64, edge_attr float32": (x.double(), e),
            "edge_attr float64": (x, e.double()),
            "7 columns for in_channels=8": (x[:, :7], e),
            "integer features": (x.long(), e),
            "integer edge features": (x, e.long()),
            "x on meta, layer on cpu": (x.to("meta"), e)}[case]
    with pytest.raises(error) as info:
        layer(x, ei, e)
    msg = str(info.value)
    assert all(w in msg for w in words), msg


def test_feature_checks_leave_lazy_widths_and_float64_layers_alone():
    """Oracle: a float64 layer on float64 inputs, a lazy (-1) layer and mixed dtypes
    under autocast run as before."""
    x, ei, e = _inputs()
    layer = SATConv(8, 4, 2, edge_dim=3).double()
    assert layer(x.double(), ei, e.double()).dtype == torch.float64
    assert SATConv(-1, 4, 2, edge_dim=3)(x[:, :7], ei, e).shape == (6, 8)
    with torch.autocast("cpu", dtype=torch.bfloat16):  # ops pick their dtypes: a mix is fine
        assert SATConv(8, 4, 2, edge_dim=3)(x, ei, e.bfloat16()).shape == (6, 8)


@pytest.mark.parametrize("name", NAMES)
def test_more_parallel_edges_than_node_pairs_match_the_message_route(name):
    """Three self-loops on one node (found by the fuzz suite): torch's sparse sampling
    raised ``only sparse compressed tensors with the same number of specified elements``.
    Oracle: the message route (no sparse kernels)."""
    torch.manual_seed(0)
    layer = LAYERS[name](8, 4, 2, edge_dim=3).eval()
    x, ei, e = torch.randn(1, 8), torch.zeros(2, 3, dtype=torch.long), torch.randn(3, 3)
    out = layer(x, ei, e)
    with csr_kernels(False):
        ref = layer(x, ei, e)
    torch.testing.assert_close(out, ref)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("layout, words", [
    ("3 sparse", ["3 sparse, 0 dense", "(5, 5, 3)"]),
    ("2 sparse + 2 dense", ["2 sparse, 2 dense", "(5, 5, 3, 2)"]),
    ("batched CSR", ["2 sparse, 0 dense and 1 batch", "(2, 5, 5)"]),
])
def test_a_sparse_adjacency_of_another_layout_is_named(name, layout, words):
    """A sparse adj_t of three sparse dimensions was read as a 3-row index: SATConv and
    both GT layers indexed uninitialised memory (a different IndexError each run, or a
    wrong answer), the other two raised PyG's words about `edge_index`."""
    idx = torch.tensor([[0, 1, 3, 4, 2], [1, 2, 4, 0, 2]])
    adj = {"3 sparse": lambda: torch.sparse_coo_tensor(
               torch.cat([idx, torch.tensor([[0, 1, 2, 0, 1]])]), torch.randn(5), (5, 5, 3)),
           "2 sparse + 2 dense": lambda: torch.sparse_coo_tensor(idx, torch.randn(5, 3, 2),
                                                                 (5, 5, 3, 2)),
           "batched CSR": lambda: torch.ones(2, 5, 5).to_sparse_csr()}[layout]()
    layer = LAYERS[name](8, 4, heads=2, edge_dim=3)
    with pytest.raises(ValueError) as err:
        layer(torch.randn(5, 8), adj, torch.randn(5, 3))
    msg = str(err.value)
    assert msg.startswith("`edge_index`: a sparse adj_t needs 2 sparse dimensions"), msg
    assert all(w in msg for w in words), msg


@pytest.mark.parametrize("name", NAMES)
def test_a_hybrid_sparse_adjacency_still_carries_the_edge_features(name):
    idx = torch.tensor([[0, 1, 3, 4, 2], [1, 2, 4, 0, 2]])
    feats = torch.randn(5, 3)
    layer = LAYERS[name](8, 4, heads=2, edge_dim=3).eval()
    x = torch.randn(5, 8)
    hybrid = layer(x, torch.sparse_coo_tensor(idx, feats, (5, 5, 3)))
    plain = layer(x, idx.flip(0), feats)
    hybrid, plain = (o[0] if isinstance(o, tuple) else o for o in (hybrid, plain))
    torch.testing.assert_close(hybrid, plain)
