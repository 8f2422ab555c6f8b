"""Edge cases of the layers' inputs: empty graphs, overflowing features, bad constructor
arguments, the per-graph CSR plan, and no import-time side effects."""
from __future__ import annotations

import sys
import types
import warnings
from pathlib import Path

import pytest
import torch
from conftest import random_graph

import garmentgnn.nn
from garmentgnn.nn import LAYERS, SATConv, _graph

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
