"""Explainer masks, message hooks, attention weights and higher-order gradients behave
the same on sorted and unsorted edges and on the fused and message routes."""
from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from conftest import random_graph
from test_sat_conv import reference_sat
from torch_geometric.explain import Explainer
from torch_geometric.explain.algorithm import AttentionExplainer, GNNExplainer
from torch_geometric.explain.algorithm.utils import clear_masks, set_masks
from torch_geometric.nn import TransformerConv

from garmentgnn.geometry import edge_features, faces_to_edge_index, grid_mesh
from garmentgnn.nn import LAYERS, GraphTransformerConv, SATConv
from garmentgnn.nn._sparse import csr_kernels

NAMES = sorted(LAYERS)
ORDERS = ["sorted", "unsorted"]


def graph(order: str, seed: int = 0, n: int = 6):
    """A small mesh graph (sorted by target, as faces_to_edge_index gives it) or the
    same edges shuffled; ``perm`` maps shuffled positions to sorted ones."""
    pos, faces = grid_mesh(n, n)
    pos = pos + 0.05 * torch.randn(pos.shape, generator=torch.Generator().manual_seed(seed))
    ei = faces_to_edge_index(faces, pos.size(0))
    e = edge_features(pos, ei)
    x = torch.cat([pos, torch.randn(pos.size(0), 3, generator=torch.Generator().manual_seed(1))],
                  -1)
    perm = torch.arange(ei.size(1))
    if order == "unsorted":
        perm = torch.randperm(ei.size(1), generator=torch.Generator().manual_seed(seed + 7))
    return x, ei[:, perm], e[perm], perm


def hard_mask(model, mask, edge_index):
    set_masks(model, mask, edge_index, apply_sigmoid=False)


@pytest.mark.parametrize("order", ORDERS)
def test_sat_masked_edge_contributes_nothing(order):
    """SATConv with an explainer's mask of 0 on one edge equals the loop reference with
    that edge's whole message (value and edge-value term) removed."""
    torch.manual_seed(0)
    ei = random_graph(9, 25, seed=3, sort=order == "sorted")
    x, e = torch.randn(9, 6), torch.randn(ei.size(1), 3)
    conv = SATConv(6, 4, 2, edge_dim=3).eval()
    drop = 5
    mask = torch.ones(ei.size(1))
    mask[drop] = 0.0
    hard_mask(conv, mask, ei)
    out = conv(x, ei, e)
    clear_masks(conv)
    ref, _, _ = reference_sat(conv, x, ei, e, drop=drop)
    torch.testing.assert_close(out.double(), ref, atol=1e-5, rtol=1e-5)
    full, _, _ = reference_sat(conv, x, ei, e)
    assert (ref - full).abs().max() > 1e-3  # the edge mattered


@pytest.mark.parametrize("order", ORDERS)
def test_gt_masked_like_pyg_transformer_conv(order):
    """Under the same edge mask GraphTransformerConv equals TransformerConv with the
    same weights (PyG's semantics: the mask scales each edge's message)."""
    torch.manual_seed(3)
    ours = GraphTransformerConv(8, 4, 2).eval()
    pyg = TransformerConv(8, 4, 2, root_weight=True).eval()
    with torch.no_grad():
        for name in ("lin_query", "lin_key", "lin_value"):
            getattr(ours, name).load_state_dict(getattr(pyg, name).state_dict())
        ours.lin_out.weight.copy_(torch.eye(8))
        ours.lin_out.bias.zero_()
        pyg.lin_skip.weight.copy_(torch.eye(8))
        pyg.lin_skip.bias.zero_()
    x = torch.randn(9, 8)
    ei = random_graph(9, 25, seed=4, sort=order == "sorted")
    mask = torch.rand(ei.size(1), generator=torch.Generator().manual_seed(0))
    mask[::3] = 0.0
    for m in (ours, pyg):
        hard_mask(m, mask, ei)
    torch.testing.assert_close(ours(x, ei), pyg(x, ei), atol=1e-5, rtol=0)


@pytest.mark.parametrize("name", NAMES)
def test_masks_hooks_and_attention_agree_on_both_orders_and_routes(name):
    """Soft masks give the same outputs (permuted) on both edge orders; a mask of ones
    changes nothing; hooked messages are the same messages; attention weights agree."""
    torch.manual_seed(0)
    layer = LAYERS[name](6, 4, 2, edge_dim=4).eval()
    x, ei_s, e_s, _ = graph("sorted")
    _, ei_u, e_u, perm = graph("unsorted")
    soft = torch.randn(ei_s.size(1), generator=torch.Generator().manual_seed(2))

    ref, (_, alpha_s) = layer(x, ei_s, e_s, return_attention_weights=True)
    _, (_, alpha_u) = layer(x, ei_u, e_u, return_attention_weights=True)
    torch.testing.assert_close(alpha_u, alpha_s[perm], atol=1e-6, rtol=0)
    with csr_kernels(False):  # the message route
        torch.testing.assert_close(layer(x, ei_u, e_u), ref, atol=1e-5, rtol=1e-5)

    outs = []
    for ei, e, m in ((ei_s, e_s, soft), (ei_u, e_u, soft[perm])):
        set_masks(layer, m, ei, apply_sigmoid=True)
        outs.append(layer(x, ei, e))
        clear_masks(layer)
    torch.testing.assert_close(outs[0], outs[1], atol=1e-5, rtol=1e-5)
    assert (outs[0] - ref).abs().max() > 1e-3
    hard_mask(layer, torch.ones(ei_u.size(1)), ei_u)
    torch.testing.assert_close(layer(x, ei_u, e_u), ref, atol=1e-5, rtol=1e-5)
    clear_masks(layer)

    target = layer.gat if name == "gat" else layer  # GATv2Conv passes the messages
    seen = []
    handle = target.register_message_forward_hook(lambda mod, inp, out: seen.append(out))
    out_s = layer(x, ei_s, e_s)
    out_u = layer(x, ei_u, e_u)
    handle.remove()
    torch.testing.assert_close(out_s, ref, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(out_u, ref, atol=1e-5, rtol=1e-5)
    msgs_s, msgs_u = seen[-2], seen[-1]
    assert msgs_s.size(0) == ei_s.size(1)
    torch.testing.assert_close(msgs_u, msgs_s[perm], atol=1e-6, rtol=1e-5)


class TwoLayer(torch.nn.Module):
    def __init__(self, name: str):
        super().__init__()
        self.conv1 = LAYERS[name](6, 4, 2, edge_dim=4)
        self.conv2 = LAYERS[name](8, 1, 2, concat=False, edge_dim=4)

    def forward(self, x, edge_index, edge_attr):
        return self.conv2(F.elu(self.conv1(x, edge_index, edge_attr)), edge_index, edge_attr)


def receptive_edges(ei, node: int, hops: int) -> torch.Tensor:
    """Edges whose message can reach ``node`` within ``hops`` rounds of message passing."""
    reach = torch.zeros(int(ei.max()) + 1, dtype=torch.bool)
    reach[node] = True
    for _ in range(hops - 1):
        reach[ei[0, reach[ei[1]]]] = True
    return reach[ei[1]]


@pytest.mark.parametrize("name", NAMES)
def test_gnn_explainer_masks_the_receptive_field_on_both_orders(name):
    hops = 2 * (LAYERS[name](4, 4).k_hops + 1 if name == "structure_aware" else 1)
    node = 17
    supports = []
    for order in ORDERS:
        torch.manual_seed(0)
        model = TwoLayer(name).eval()
        x, ei, e, perm = graph(order)
        explainer = Explainer(model, algorithm=GNNExplainer(epochs=3),
                              explanation_type="model", edge_mask_type="object",
                              node_mask_type=None,
                              model_config=dict(mode="regression", task_level="node",
                                                return_type="raw"))
        mask = explainer(x, ei, index=node, edge_attr=e).edge_mask
        assert torch.equal(mask > 0, receptive_edges(ei, node, hops))
        supports.append(mask > 0)
    assert torch.equal(supports[1], supports[0][perm])


@pytest.mark.parametrize("name", NAMES)
def test_attention_explainer_returns_the_attention_on_both_orders(name):
    masks = []
    for order in ORDERS:
        torch.manual_seed(0)
        model = TwoLayer(name).eval()
        x, ei, e, perm = graph(order)
        explainer = Explainer(model, algorithm=AttentionExplainer(), explanation_type="model",
                              edge_mask_type="object",
                              model_config=dict(mode="regression", task_level="node",
                                                return_type="raw"))
        mask = explainer(x, ei, edge_attr=e).edge_mask
        # oracle: the largest weight over heads and layers, from return_attention_weights
        h, (_, a1) = model.conv1(x, ei, e, return_attention_weights=True)
        _, (_, a2) = model.conv2(F.elu(h), ei, e, return_attention_weights=True)
        oracle = torch.maximum(a1.max(-1).values, a2.max(-1).values)
        torch.testing.assert_close(mask, oracle.detach(), atol=1e-6, rtol=0)
        masks.append(mask)
    torch.testing.assert_close(masks[1], masks[0][perm], atol=1e-6, rtol=0)


@pytest.mark.parametrize("name", ["sat", "gt", "gt_edge"])
@pytest.mark.parametrize("order", ORDERS)
@pytest.mark.parametrize("kernels", [True, False])
def test_double_backward(name, order, kernels):
    """Gradients of gradients (e.g. a gradient penalty) on the fused kernels and on the
    message route, checked by finite differences."""
    torch.manual_seed(0)
    ei = random_graph(5, 8, seed=4, sort=order == "sorted")
    layer = LAYERS[name](3, 2, 2, edge_dim=2).double().eval()
    x = torch.randn(5, 3, dtype=torch.float64, requires_grad=True)
    e = torch.randn(ei.size(1), 2, dtype=torch.float64, requires_grad=True)
    with csr_kernels(kernels):
        assert torch.autograd.gradgradcheck(lambda a, b: layer(a, ei, b), (x, e))
