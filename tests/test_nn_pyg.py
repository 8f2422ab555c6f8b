"""Every layer as a PyG user meets it: the checks of PyG's own TransformerConv and
GATv2Conv tests (shapes, bipartite, sparse adjacency, attention weights), lazy
widths, ``torch_geometric.nn.Sequential``, ``to_hetero`` and ``torch.compile``."""
from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from torch_geometric.data import HeteroData
from torch_geometric.nn import Sequential, TransformerConv, to_hetero
from torch_geometric.utils import to_torch_csc_tensor

from garmentgnn.geometry import edge_features, faces_to_edge_index, grid_mesh
from garmentgnn.nn import (LAYERS, EdgeTransformerConv, GATBaselineConv, GraphTransformerConv,
                           SATConv, StructureAwareTransformerConv)

CLASSES = [SATConv, GraphTransformerConv, EdgeTransformerConv, StructureAwareTransformerConv,
           GATBaselineConv]
NEEDS_EDGES = {SATConv, EdgeTransformerConv}
IDS = [c.__name__ for c in CLASSES]


def edge_dims(cls):
    return [8] if cls in NEEDS_EDGES else [None, 8]


@pytest.mark.parametrize("cls", CLASSES, ids=IDS)
@pytest.mark.parametrize("concat", [True, False])
def test_pyg_style_conv(cls, concat):
    """Adapted from PyG's test_transformer_conv / test_gatv2_conv."""
    torch.manual_seed(0)
    for edge_dim in edge_dims(cls):
        x1, x2 = torch.randn(4, 8), torch.randn(2, 8)
        edge_index = torch.tensor([[0, 1, 2, 3], [0, 0, 1, 1]])
        edge_attr = torch.randn(edge_index.size(1), edge_dim) if edge_dim else None
        out_channels, heads = 16, 2
        width = out_channels * (heads if concat else 1)

        conv = cls(8, out_channels, heads, concat=concat, edge_dim=edge_dim).eval()
        assert str(conv).startswith(f"{cls.__name__}(8, {out_channels}, heads={heads}")
        out = conv(x1, edge_index, edge_attr)
        assert isinstance(out, torch.Tensor) and out.size() == (4, width)
        adj = to_torch_csc_tensor(edge_index, size=(4, 4))
        torch.testing.assert_close(conv(x1, adj.t(), edge_attr), out, atol=1e-6, rtol=1e-5)

        result = conv(x1, edge_index, edge_attr, return_attention_weights=True)
        torch.testing.assert_close(result[0], out)
        assert result[1][0].size() == (2, 4) and result[1][1].size() == (4, heads)
        assert result[1][1].min() >= 0 and result[1][1].max() <= 1
        # PyG semantics: any bool asks for the weights
        assert len(conv(x1, edge_index, edge_attr, return_attention_weights=False)) == 2
        out_e, e_out = conv(x1, edge_index, edge_attr, return_edge_attr=True)
        torch.testing.assert_close(out_e, out)
        assert e_out is None if edge_dim is None else e_out.size(0) == 4

        # bipartite message passing
        conv = cls((8, 8), out_channels, heads, concat=concat, edge_dim=edge_dim).eval()
        out = conv((x1, x2), edge_index, edge_attr)
        assert out.size() == (2, width)
        adj = to_torch_csc_tensor(edge_index, size=(4, 2))
        torch.testing.assert_close(conv((x1, x2), adj.t(), edge_attr), out, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("cls", CLASSES, ids=IDS)
def test_lazy_widths_equal_explicit_ones(cls):
    """``-1`` and ``(-1, -1)`` are inferred from the first call; with the weights of the
    explicit layer loaded the outputs agree."""
    torch.manual_seed(1)
    x_src, x_dst = torch.randn(6, 5), torch.randn(3, 7)
    ei = torch.tensor([[0, 1, 2, 3, 4, 5, 0], [0, 0, 1, 1, 2, 2, 2]])
    e = torch.randn(7, 4)
    lazy = cls((-1, -1), 3, 2, edge_dim=4).eval()
    out = lazy((x_src, x_dst), ei, e)
    assert out.shape == (3, 6)
    explicit = cls((5, 7), 3, 2, edge_dim=4).eval()
    explicit.load_state_dict(lazy.state_dict())
    torch.testing.assert_close(explicit((x_src, x_dst), ei, e), out)
    single = cls(-1, 3, 2, edge_dim=4)
    assert single(torch.randn(6, 5), ei, e).shape == (6, 6)
    assert sum(p.numel() for p in single.parameters()) > 0  # all initialised


@pytest.mark.parametrize("cls", CLASSES, ids=IDS)
def test_swapped_into_a_transformer_conv_model_by_one_line(cls):
    """The same user model with TransformerConv or ours: same signature, same call."""
    x = torch.randn(10, 8)
    ei = torch.tensor([[i for i in range(10)] + [(i + 3) % 10 for i in range(10)],
                       [(i + 1) % 10 for i in range(10)] + [i for i in range(10)]])
    e = torch.randn(ei.size(1), 3)
    for conv_cls in (TransformerConv, cls):
        conv = conv_cls(8, 4, 2, edge_dim=3)  # the one line
        out = F.relu(conv(x, ei, e))
        assert out.shape == (10, 8)


def mesh_task(n: int = 7, seed: int = 0):
    """A bumpy sheet; target: the umbrella Laplacian of the heights (needs the mesh)."""
    g = torch.Generator().manual_seed(seed)
    pos, faces = grid_mesh(n, n)
    pos[:, 2] = 0.3 * torch.sin(3 * pos[:, 0] + 6.28 * torch.rand(1, generator=g)) \
        * torch.cos(2 * pos[:, 1])
    ei = faces_to_edge_index(faces, pos.size(0))
    z = pos[:, 2:] * 10
    deg = torch.zeros(pos.size(0)).index_add_(0, ei[1], torch.ones(ei.size(1)))
    mean = torch.zeros_like(z).index_add_(0, ei[1], z[ei[0]]) / deg[:, None]
    return z, ei, edge_features(pos, ei), (z - mean) * 10


def train(model, data, steps: int = 40, lr: float = 2e-2) -> tuple:
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    losses = []
    for _ in range(steps):
        loss = sum(F.mse_loss(model(*inp), y) for *inp, y in data) / len(data)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    return losses[0], min(losses[-5:])


@pytest.mark.parametrize("name", sorted(LAYERS))
def test_two_layer_sequential_trains(name):
    torch.manual_seed(0)
    cls = LAYERS[name]
    model = Sequential("x, edge_index, edge_attr", [
        (torch.nn.Linear(1, 16), "x -> x"),
        (cls(16, 4, 4, edge_dim=4), "x, edge_index, edge_attr -> x"),
        torch.nn.ELU(),
        (cls(16, 4, 4, edge_dim=4), "x, edge_index, edge_attr -> x"),
        torch.nn.ELU(),
        (torch.nn.Linear(16, 1), "x -> x"),
    ])
    data = [mesh_task(seed=s)[:4] for s in range(2)]
    first, last = train(model, [(z, ei, e, y) for z, ei, e, y in data])
    assert last < 0.5 * first


def hetero_task(seed: int = 0) -> HeteroData:
    """Two node types; 'vertex' receives two edge types (mesh edges and edges from 'probe'
    nodes); the target needs both."""
    z, ei, e, y = mesh_task(seed=seed)
    g = torch.Generator().manual_seed(seed + 10)
    data = HeteroData()
    n_probe = 12
    data["vertex"].x = z
    data["probe"].x = torch.randn(n_probe, 3, generator=g)
    src = torch.randint(0, n_probe, (z.size(0),), generator=g)
    dst = torch.arange(z.size(0))
    data["vertex", "mesh", "vertex"].edge_index = ei
    data["vertex", "mesh", "vertex"].edge_attr = e
    data["probe", "hits", "vertex"].edge_index = torch.stack([src, dst])
    data["probe", "hits", "vertex"].edge_attr = torch.randn(dst.numel(), 4, generator=g)
    data["vertex", "rev", "probe"].edge_index = torch.stack([dst, src])
    data["vertex", "rev", "probe"].edge_attr = torch.randn(dst.numel(), 4, generator=g)
    data["vertex"].y = y + data["probe"].x[src, :1]
    return data


class HeteroNet(torch.nn.Module):
    def __init__(self, cls):
        super().__init__()
        self.conv1 = cls((-1, -1), 4, 4, edge_dim=4)
        self.conv2 = cls((-1, -1), 4, 4, edge_dim=4)
        self.lin = torch.nn.Linear(16, 1)

    def forward(self, x, edge_index, edge_attr):
        x = F.elu(self.conv1(x, edge_index, edge_attr))
        x = F.elu(self.conv2(x, edge_index, edge_attr))
        return self.lin(x)


@pytest.mark.parametrize("name", sorted(LAYERS))
def test_to_hetero_with_two_edge_types_into_one_node_type_trains(name):
    torch.manual_seed(0)
    data = hetero_task()
    model = to_hetero(HeteroNet(LAYERS[name]), data.metadata(), aggr="sum")
    with torch.no_grad():  # initialise the lazy widths
        model(data.x_dict, data.edge_index_dict, data.edge_attr_dict)
    opt = torch.optim.Adam(model.parameters(), lr=2e-2)
    losses = []
    for _ in range(40):
        out = model(data.x_dict, data.edge_index_dict, data.edge_attr_dict)
        loss = F.mse_loss(out["vertex"], data["vertex"].y)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert min(losses[-5:]) < 0.5 * losses[0]


@pytest.mark.parametrize("name", sorted(LAYERS))
@pytest.mark.parametrize("order", ["sorted", "unsorted"])
def test_torch_compile_has_no_graph_breaks(name, order, mesh_graph):
    pos, _, ei, e = mesh_graph
    if order == "unsorted":
        perm = torch.randperm(ei.size(1), generator=torch.Generator().manual_seed(0))
        ei, e = ei[:, perm], e[perm]
    x = torch.cat([pos, pos.flip(-1)], -1)
    torch.manual_seed(0)
    layer = LAYERS[name](6, 4, 2, edge_dim=4).eval()
    torch._dynamo.reset()
    explained = torch._dynamo.explain(layer)(x, ei, e, return_attention_weights=True,
                                             return_edge_attr=True)
    assert explained.graph_break_count == 0, explained.break_reasons
    assert explained.graph_count == 1
