"""Losses (Eqs. 7-13) and table metrics on hand-computed cases."""
import math

import pytest
import torch
import trimesh

from garmentgnn.geometry import NearestFaceCache, grid_mesh, signed_distance, unique_edges
from garmentgnn.losses import (PAPER_WEIGHTS, GarTransLoss, LossInputs, NonFiniteLossError,
                               edge_loss, normal_loss, vertex_loss)
from garmentgnn.metrics import (collision_rate, curvature_error, edge_length_error, evaluate,
                                face_normal_error, vertex_distance, vertex_normal_error)
from garmentgnn.physics import ClothRest, gravity_energy, stretch_energy

D = torch.float64


def sheet(n=4):
    pos, faces = grid_mesh(n, n, dtype=D)
    return pos, faces


def tilt(pos, angle):
    """Rotate about the x axis (a rigid motion)."""
    c, s = math.cos(angle), math.sin(angle)
    R = torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]], dtype=D)
    return pos @ R.T


def test_vertex_metrics_and_losses_on_a_translation():
    pos, faces = sheet()
    moved = pos + torch.tensor([0.03, 0.0, 0.04], dtype=D)  # 5 cm everywhere
    assert float(vertex_distance(moved, pos)) == pytest.approx(5.0)
    assert float(vertex_loss(moved, pos)) == pytest.approx(0.05)
    # translation keeps normals, lengths and curvature
    assert float(vertex_normal_error(moved, pos, faces)) == pytest.approx(0.0, abs=1e-6)
    assert float(face_normal_error(moved, pos, faces)) == pytest.approx(0.0, abs=1e-6)
    assert float(edge_length_error(moved, pos, faces)) == pytest.approx(0.0, abs=1e-9)
    assert float(curvature_error(moved, pos, faces)) == pytest.approx(0.0, abs=1e-9)


def test_normal_metrics_on_a_rotation():
    pos, faces = sheet()
    rot = tilt(pos, math.radians(30))
    assert float(face_normal_error(rot, pos, faces)) == pytest.approx(30.0, abs=1e-6)
    assert float(vertex_normal_error(rot, pos, faces)) == pytest.approx(30.0, abs=1e-6)
    assert float(normal_loss(rot, pos, faces)) == pytest.approx(1 - math.cos(math.radians(30)))


def test_edge_metrics_on_a_uniform_scale():
    pos, faces = sheet()
    scaled = 1.1 * pos
    assert float(edge_length_error(scaled, pos, faces)) == pytest.approx(10.0)
    edges = unique_edges(faces, pos.shape[0]).edges
    lengths = (pos[edges[:, 1]] - pos[edges[:, 0]]).norm(dim=-1)
    expected = float(((0.1 * lengths) ** 2).sum())
    assert float(edge_loss(scaled, pos, edges)) == pytest.approx(expected)
    assert float(edge_loss(scaled, pos, edges, "mean")) == pytest.approx(expected / len(edges))


def test_curvature_error_of_a_raised_vertex():
    pos, faces = sheet(3)  # 3x3 grid: vertex 4 is the only interior vertex
    bumped = pos.clone()
    bumped[4, 2] = 0.2
    # interior defect: 2 pi - sum of angles at vertex 4, computed here directly
    tri = bumped[faces]
    total = 0.0
    for f, t in zip(faces.tolist(), tri):
        if 4 in f:
            k = f.index(4)
            a, b = t[(k + 1) % 3] - t[k], t[(k + 2) % 3] - t[k]
            total += math.acos(float((a @ b) / (a.norm() * b.norm())))
    assert float(curvature_error(bumped, pos, faces)) == pytest.approx(2 * math.pi - total)


def test_collision_rate_and_evaluate():
    body = torch.tensor([[-5.0, -5.0, 0.0], [5.0, -5.0, 0.0], [5.0, 5.0, 0.0], [-5.0, 5.0, 0.0],
                         [0.0, 0.0, -3.0]], dtype=D)
    body_faces = torch.tensor([[0, 1, 2], [0, 2, 3], [0, 4, 1], [1, 4, 2], [2, 4, 3], [3, 4, 0]])
    pos, faces = sheet()
    z = torch.zeros(pos.shape[0], dtype=D)
    z[:4] = -0.01  # 4 of 16 vertices below the surface
    p = pos + torch.stack([torch.zeros_like(z), torch.zeros_like(z), z + 0.0], -1) - \
        torch.tensor([0.5, 0.5, 0.0], dtype=D)
    assert float(collision_rate(p, body, body_faces)) == pytest.approx(25.0)
    res = evaluate(p.expand(3, -1, -1), p.expand(3, -1, -1), faces, body.expand(3, -1, -1),
                   body_faces)
    assert res["E_dist"] == pytest.approx(0.0) and res["collision"] == pytest.approx(25.0)
    with pytest.raises(ValueError, match="NaN|non-finite"):
        evaluate(p * float("nan"), p, faces)


def test_gartrans_loss_weights_phases_and_nan():
    pos, faces = sheet()
    rest = ClothRest.from_mesh(pos, faces, pos[faces][..., :2])
    mass = rest.vertex_masses(0.2, pos.shape[0])
    gt = pos.expand(2, -1, -1)
    pred = (1.1 * pos).expand(2, -1, -1).clone().requires_grad_(True)
    loss = GarTransLoss(enabled=["vert", "stretch", "gravity"])
    total, terms = loss(LossInputs(pred=pred, faces=faces, gt=gt, mass=mass, rest=rest))
    assert set(terms) == {"vert", "stretch", "gravity"}
    assert float(terms["vert"]) == pytest.approx(100 * float(vertex_loss(1.1 * pos, pos)))
    assert float(terms["stretch"]) == pytest.approx(float(stretch_energy(1.1 * pos, rest, 5.0)))
    assert float(terms["gravity"]) == pytest.approx(0.1 * float(gravity_energy(1.1 * pos, mass)))
    total.backward()
    assert torch.isfinite(pred.grad).all()
    # the paper's second phase scales the supervised terms by 0.05
    loss.supervised_scale = 0.05
    _, terms2 = loss(LossInputs(pred=pred, faces=faces, gt=gt, mass=mass, rest=rest))
    assert float(terms2["vert"]) == pytest.approx(0.05 * float(terms["vert"]))
    # no material coordinates -> stretch/shear left out; no body -> no collision
    loss.set_enabled(["stretch", "shear", "collision"])
    _, terms3 = loss(LossInputs(pred=pred, faces=faces))
    assert terms3 == {}
    bad = pred.detach().clone()
    bad[0, 0, 0] = float("nan")
    loss.set_enabled(["vert"])
    with pytest.raises(NonFiniteLossError, match="vert"):
        loss(LossInputs(pred=bad, faces=faces, gt=gt))
    with pytest.raises(ValueError, match="weights"):
        GarTransLoss(weights={"wrinkles": 1.0})
    assert PAPER_WEIGHTS["edge"] == 15.0 and PAPER_WEIGHTS["shear"] == 2.0


def test_curvature_term_is_the_metric_and_its_gradient():
    """The extra ``curv`` term is ``k_curv`` times E_curv (its hand-computed test is
    above), off by default, scaled with the supervised terms, zero at the ground truth
    and on a rigid motion of it (the angle defect is intrinsic), and its gradient
    matches finite differences."""
    pos, faces = sheet(4)
    gt = pos.clone()
    gt[5, 2], gt[10, 2] = 0.15, -0.1
    bumped = gt.clone()
    bumped[6, 2] = 0.2
    assert PAPER_WEIGHTS["curv"] == 0.0 and "curv" not in GarTransLoss().enabled
    loss = GarTransLoss(weights={"curv": 30.0}, enabled=["curv"])
    _, terms = loss(LossInputs(pred=bumped.unsqueeze(0), faces=faces, gt=gt.unsqueeze(0)))
    assert float(terms["curv"]) == pytest.approx(30 * float(curvature_error(bumped, gt, faces)))
    assert float(terms["curv"]) > 0
    for same in (gt, tilt(gt, 0.7) + 1.0):
        _, t0 = loss(LossInputs(pred=same.unsqueeze(0), faces=faces, gt=gt.unsqueeze(0)))
        assert float(t0["curv"]) == pytest.approx(0.0, abs=1e-12)
    loss.supervised_scale = 0.05
    _, t5 = loss(LossInputs(pred=bumped.unsqueeze(0), faces=faces, gt=gt.unsqueeze(0)))
    assert float(t5["curv"]) == pytest.approx(0.05 * float(terms["curv"]))
    x = bumped.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda p: loss(LossInputs(pred=p.unsqueeze(0), faces=faces, gt=gt.unsqueeze(0)))[0], (x,))
    with pytest.raises(ValueError, match="gt"):
        loss(LossInputs(pred=bumped.unsqueeze(0), faces=faces))


def dipping_cap(body: trimesh.Trimesh):
    """``(pred, faces, body vertices, body faces)``, float64: an 8 x 8 sheet 0.3 m wide
    bent into a cap, its top 0.2 m above the origin, dipping into ``body`` (a mesh
    around the origin); ``pred [2, V, 3]``: two equal frames, requiring grad."""
    bv = torch.tensor(body.vertices, dtype=torch.float64)
    bf = torch.tensor(body.faces, dtype=torch.long)
    pos, faces = grid_mesh(8, 8, (0.3, 0.3), dtype=torch.float64)
    pos = pos - torch.tensor([0.15, 0.15, 0.0], dtype=torch.float64)
    pos[:, 2] = 0.2 - 5 * (pos[:, 0] ** 2 + pos[:, 1] ** 2)
    return pos.unsqueeze(0).repeat(2, 1, 1).requires_grad_(True), faces, bv, bf


def test_collision_term_with_candidate_faces_equals_the_exact_search():
    """The loss searches only the faces around the nearest body vertices; for a cloth
    close to a convex body that is the exact nearest face, so the term (and its
    gradient) equals the brute-force one."""
    pred, faces, bv, bf = dipping_cap(trimesh.creation.icosphere(subdivisions=3, radius=0.2))
    terms = {}
    for cand in (8, None):
        loss = GarTransLoss(enabled=["collision"], distance_candidates=cand)
        total, t = loss(LossInputs(pred=pred, faces=faces, body_pos=bv.expand(2, -1, -1),
                                   body_faces=bf))
        terms[cand] = (t["collision"].detach(), torch.autograd.grad(total, pred)[0])
    assert float(terms[None][0]) > 0  # some of the cap is inside: the term is active
    torch.testing.assert_close(terms[8][0], terms[None][0], rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(terms[8][1], terms[None][1], rtol=1e-9, atol=1e-12)


def test_collision_term_through_a_face_cache_equals_the_exact_search():
    """``LossInputs.face_cache``: the term's search runs through the cache (the model's
    projection built it on the same frames) and equals the brute force, gradient too."""
    pred, faces, bv, bf = dipping_cap(trimesh.creation.box(extents=[0.4, 0.4, 0.4]))  # 12 faces
    cache = NearestFaceCache(k=4)
    cache.nearest(pred, bv.expand(2, -1, -1), bf)
    out = {}
    for fc in (None, cache):
        loss = GarTransLoss(enabled=["collision"], distance_candidates=None)
        total, t = loss(LossInputs(pred=pred, faces=faces, body_pos=bv.expand(2, -1, -1),
                                   body_faces=bf, face_cache=fc))
        out[fc is None] = (t["collision"].detach(), torch.autograd.grad(total, pred)[0])
    assert float(out[True][0]) > 0 and cache.stats.calls == 2
    torch.testing.assert_close(out[False][0], out[True][0], rtol=0, atol=1e-12)
    torch.testing.assert_close(out[False][1], out[True][1], rtol=0, atol=1e-12)


@pytest.mark.parametrize("batch", [(), (3,)])
def test_collision_rate_closed_body_matches_exact_signed_distance(batch):
    """Closed bodies are scored by winding number: the same share as the exact
    nearest-face sign (``signed_distance(...) < 0``), on points around a closed,
    outward mesh (trimesh's icosphere), batched or not."""
    ico = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    body = torch.tensor(ico.vertices, dtype=D)
    body_faces = torch.tensor(ico.faces, dtype=torch.long)
    g = torch.Generator().manual_seed(0)
    pts = torch.randn(*batch, 400, 3, generator=g, dtype=D)
    pts = pts / pts.norm(dim=-1, keepdim=True) * (0.2 + 0.2 * torch.rand(*batch, 400, 1,
                                                                          generator=g, dtype=D))
    bodies = body.expand(*batch, -1, -1) if batch else body
    exact = 100.0 * (signed_distance(pts, bodies, body_faces).distance < 0).to(D).mean(-1)
    got = collision_rate(pts, bodies, body_faces)
    assert got.shape == exact.shape and torch.equal(got, exact)
    assert 10.0 < float(exact.mean()) < 90.0  # both sides are populated
