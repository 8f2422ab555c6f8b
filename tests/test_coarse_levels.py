"""Coarse levels of a mesh graph (:func:`garmentgnn.geometry.coarse_levels`) and the
MGN-style simulator that also runs on them.  Oracles: scipy's shortest paths and
connected components on the level below (independence, maximality, the hop rule, the
components kept), each garment of a batch alone, and autograd (a gradient in every
parameter but the declared frozen edge outputs)."""
import numpy as np
import pytest
import torch
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, shortest_path

from garmentgnn.geometry import coarse_levels, faces_to_edge_index, grid_mesh
from garmentgnn.models import EncodeProcessDecode, MGNStyle
from garmentgnn.training import RolloutModule
from test_mgn import root, windows  # noqa: F401 (a fixture)


def sphere(subdivisions=3):
    m = trimesh.creation.icosphere(subdivisions)
    faces = torch.as_tensor(m.faces)
    return faces_to_edge_index(faces, len(m.vertices)), len(m.vertices)


def graph(edge_index, n):
    e = edge_index.numpy()
    return coo_matrix((np.ones(e.shape[1]), (e[0], e[1])), shape=(n, n)).tocsr()


def nodes_of(edge_index):
    return set(edge_index.flatten().tolist())


@pytest.mark.parametrize("mesh", ["sphere", "grid"])
def test_each_level_is_a_maximal_independent_set_joined_within_three_hops(mesh):
    if mesh == "sphere":
        ei, n = sphere()
    else:
        pos, faces = grid_mesh(17, 11)
        ei, n = faces_to_edge_index(faces, len(pos)), len(pos)
    levels = coarse_levels(ei, n, 3)
    below, below_nodes = ei, set(range(n))
    for edges in levels:
        chosen = nodes_of(edges)
        hops = shortest_path(graph(below, n), unweighted=True, directed=False)
        sub = sorted(below_nodes)
        # independent: no two chosen nodes are neighbours below; maximal: every other
        # node of the level below has a chosen neighbour
        c = sorted(chosen)
        assert (hops[np.ix_(c, c)] != 1).all()
        rest = sorted(below_nodes - chosen)
        assert rest and (hops[np.ix_(rest, c)] == 1).any(axis=1).all()
        # joined exactly when within three hops below
        want = {(u, v) for u in c for v in c if u != v and hops[u, v] <= 3}
        got = set(map(tuple, edges.t().tolist()))
        assert got == want
        # the components below are kept
        k_below = connected_components(graph(below, n)[np.ix_(sub, sub)])[0]
        k_level = connected_components(graph(edges, n)[np.ix_(c, c)])[0]
        assert k_level == k_below
        assert len(chosen) < len(below_nodes) / 2
        below, below_nodes = edges, chosen


def test_a_batch_gets_each_graphs_own_levels():
    a, na = sphere(2)
    pos, faces = grid_mesh(9, 7)
    b, nb = faces_to_edge_index(faces, len(pos)), len(pos)
    batched = coarse_levels(torch.cat([a, b + na], 1), na + nb, 2,
                            batch=torch.cat([torch.zeros(na), torch.ones(nb)]).long())
    for lvl, (ea, eb) in enumerate(zip(coarse_levels(a, na, 2), coarse_levels(b, nb, 2))):
        got = set(map(tuple, batched[lvl].t().tolist()))
        assert got == set(map(tuple, ea.t().tolist())) | set(
            map(tuple, (eb + na).t().tolist()))


def test_bad_arguments_are_refused():
    ei, n = sphere(1)
    with pytest.raises(ValueError, match="`levels`"):
        coarse_levels(ei, n, -1)
    with pytest.raises(ValueError, match="`edge_index`"):
        coarse_levels(ei, n - 1, 1)
    with pytest.raises(ValueError, match="`batch`"):
        coarse_levels(ei, n, 1, batch=torch.ones(n).long().flip(0).cumsum(0).flip(0))
    with pytest.raises(ValueError, match="`levels`: 2 coarse levels need 4 blocks"):
        EncodeProcessDecode(5, 4, 3, hidden=8, layers=3, heads=2, levels=2)
    net = EncodeProcessDecode(5, 4, 3, hidden=8, layers=2, heads=2, levels=1)
    with pytest.raises(ValueError, match="`coarse`"):
        net(torch.randn(4, 5), torch.tensor([[0, 1], [1, 0]]), torch.randn(2, 4))


def test_the_blocks_alternate_and_the_last_is_the_meshs():
    net = EncodeProcessDecode(5, 4, 3, hidden=8, layers=8, heads=2, levels=2)
    assert net.block_levels == [2, 0, 1, 0, 2, 0, 1, 0]
    assert "levels=2" in repr(net)


def test_the_frozen_edge_outputs_are_what_gets_no_gradient():
    """With coarse levels, each edge set's last block has its edge output frozen: exactly
    the parameters autograd leaves without a gradient when all are trainable."""
    torch.manual_seed(0)
    net = EncodeProcessDecode(5, 4, 3, hidden=8, layers=4, heads=2, levels=1)
    frozen = {n for n, p in net.named_parameters() if not p.requires_grad}
    assert {n.split(".")[1] for n in frozen} == {"2", "3"}  # convs 2 (coarse) and 3 (mesh)
    for p in net.parameters():
        p.requires_grad_(True)
    ei, n = sphere(1)
    (coarse,) = coarse_levels(ei, n, 1)
    out = net(torch.randn(n, 5), ei, torch.randn(ei.shape[1], 4),
              coarse=[(coarse, torch.randn(coarse.shape[1], 4))])
    out.square().sum().backward()
    assert frozen == {n for n, p in net.named_parameters() if p.grad is None}


def test_the_simulator_with_coarse_levels_learns_in_every_branch(root):  # noqa: F811
    torch.manual_seed(0)
    batch = windows(root)[[0, 6]]
    model = MGNStyle(hidden=16, layers=4, heads=2, body_radius=0.2, coarse_levels=1)
    module = RolloutModule(model, stats_steps=0, noise=1e-3, rollout=1)
    loss, _ = module.window_loss(batch)
    loss.backward()
    dead = [n for n, p in model.named_parameters()
            if p.requires_grad and (p.grad is None or not p.grad.abs().sum() > 0)]
    assert not dead
    assert any(n.startswith("network.coarse_encs.0.") for n, _ in model.named_parameters())
    assert model.coarse_norms[0].count > 0  # its inputs' statistics were taken


def test_a_batch_with_coarse_levels_is_its_garments_alone(root):  # noqa: F811
    torch.manual_seed(0)
    items = windows(root)
    model = MGNStyle(hidden=16, layers=4, heads=2, body_radius=0.2, coarse_levels=2).eval()
    both = items[[0, 6]]
    m = model.scene_motion(both)
    x0, x1 = both.gt[0], both.gt[1]
    with torch.no_grad():
        got = model(both, m, 2, x0, x1)
    start = 0
    for i in (0, 6):
        one = items[[i]]
        V = one.num_vertices
        mo = model.scene_motion(one)
        with torch.no_grad():
            alone = model(one, mo, 2, one.gt[0], one.gt[1])
        assert torch.allclose(got[start:start + V], alone, atol=1e-5)
        start += V
    assert len(m.coarse_edges) == 2
