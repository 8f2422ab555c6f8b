"""Signed distance to a body mesh (GarTrans Eq. 10) and vertex-to-joint distances.

Oracles: trimesh's per-triangle closest point (``trimesh.triangles.closest_point``,
brute force over all faces: ``trimesh.proximity`` needs rtree, which is not installed),
a generalised winding number written here in numpy for inside/outside, and analytic
distances of a box and a sphere.
"""
import warnings

import numpy as np
import pytest
import scipy.spatial.distance
import torch
import trimesh
from torch.utils._python_dispatch import TorchDispatchMode

from garmentgnn import geometry as G
from garmentgnn.geometry import distance as dist_mod

D = torch.float64


def _brute_unsigned(m: trimesh.Trimesh, pts: np.ndarray):
    """Exact closest point on the mesh: trimesh per-triangle closest point, min over faces."""
    P, F = len(pts), len(m.faces)
    tri = np.tile(m.triangles, (P, 1, 1))
    q = trimesh.triangles.closest_point(tri, np.repeat(pts, F, 0)).reshape(P, F, 3)
    d = np.linalg.norm(q - pts[:, None], axis=-1)
    i = d.argmin(1)
    return d[np.arange(P), i], q[np.arange(P), i]


def _winding_number(m: trimesh.Trimesh, pts: np.ndarray) -> np.ndarray:
    """Generalised winding number (Van Oosterom & Strackee solid angles), ~1 inside."""
    a = m.triangles[None, :, 0] - pts[:, None]
    b = m.triangles[None, :, 1] - pts[:, None]
    c = m.triangles[None, :, 2] - pts[:, None]
    la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
    num = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
    den = (la * lb * lc + np.einsum("pfi,pfi->pf", a, b) * lc
           + np.einsum("pfi,pfi->pf", b, c) * la + np.einsum("pfi,pfi->pf", c, a) * lb)
    return (2 * np.arctan2(num, den)).sum(1) / (4 * np.pi)


def _points_around(m: trimesh.Trimesh, n: int, seed: int, spread: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    lo, hi = m.bounds
    c, ext = (lo + hi) / 2, (hi - lo) / 2
    return c + rng.uniform(-1, 1, size=(n, 3)) * ext * spread


SEEDS = {"icosphere": 11, "capsule": 12, "torus": 13}
MESHES = {
    "icosphere": lambda: trimesh.creation.icosphere(subdivisions=2, radius=0.8),
    "capsule": lambda: trimesh.creation.capsule(height=1.0, radius=0.3, count=[16, 16]),
    "torus": lambda: trimesh.creation.torus(major_radius=1.0, minor_radius=0.3,
                                            major_sections=24, minor_sections=12),
}


def test_closest_point_on_triangle_matches_trimesh_all_regions():
    rng = np.random.default_rng(0)
    n = 4000
    tri = rng.normal(size=(n, 3, 3))
    pts = rng.normal(size=(n, 3)) * 2.0
    q, bary, region = G.closest_point_on_triangle(
        torch.tensor(pts), *(torch.tensor(tri[:, k]) for k in range(3)))
    ref = trimesh.triangles.closest_point(tri, pts)
    np.testing.assert_allclose(q.numpy(), ref, atol=1e-9)
    assert set(region.tolist()) == set(range(7))  # face, 3 vertices, 3 edges all visited
    assert bool((bary >= -1e-12).all()) and torch.allclose(bary.sum(-1), torch.ones(n, dtype=D))


@pytest.mark.parametrize("name", sorted(MESHES))
def test_signed_distance_matches_oracles(name):
    m = MESHES[name]()
    pts = _points_around(m, 60, seed=SEEDS[name], spread=1.4)
    d_ref, q_ref = _brute_unsigned(m, pts)
    w = _winding_number(m, pts)
    inside = w > 0.5
    assert inside.any() and (~inside).any()
    sd = G.signed_distance(torch.tensor(pts), torch.tensor(m.vertices), torch.tensor(m.faces))
    np.testing.assert_allclose(np.abs(sd.distance.numpy()), d_ref, atol=1e-10)
    np.testing.assert_allclose(sd.closest.numpy(), q_ref, atol=1e-8)
    np.testing.assert_array_equal(sd.distance.numpy() < 0, inside)
    np.testing.assert_allclose(sd.normal.norm(dim=-1).numpy(), 1.0, atol=1e-12)
    # the sign is that of (p - q) . n at the returned normal
    dots = ((torch.tensor(pts) - sd.closest) * sd.normal).sum(-1)
    assert bool(((dots >= 0) == (sd.distance >= 0)).all())


def test_signed_distance_box_edges_and_corners_analytic():
    """Points near edges and corners (where the closest face's normal gives wrong signs)."""
    h = np.array([1.0, 0.5, 0.75])
    m = trimesh.creation.box(extents=2 * h)
    rng = np.random.default_rng(2)
    pts = rng.uniform(-1.4, 1.4, size=(400, 3)) * h
    q = np.abs(pts) - h
    ref = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(1), 0)
    sd = G.signed_distance(torch.tensor(pts), torch.tensor(m.vertices), torch.tensor(m.faces))
    np.testing.assert_allclose(sd.distance.numpy(), ref, atol=1e-12)
    corner = torch.tensor([[1.2, 0.7, 0.95]], dtype=D)  # closest point is a corner
    out = G.signed_distance(corner, torch.tensor(m.vertices), torch.tensor(m.faces))
    torch.testing.assert_close(out.closest, torch.tensor([h.tolist()], dtype=D))
    assert out.distance.item() == pytest.approx(np.sqrt(3 * 0.2 ** 2))
    # vertex pseudo-normal of a cube corner: all three faces get angle pi/2
    torch.testing.assert_close(out.normal, torch.ones(1, 3, dtype=D) / np.sqrt(3))


def test_signed_distance_sphere_analytic_and_float32():
    m = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    rng = np.random.default_rng(3)
    dirs = rng.normal(size=(50, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    r = rng.uniform(0.3, 1.7, size=(50, 1))
    pts = torch.tensor(dirs * r, dtype=torch.float32)
    sd = G.signed_distance(pts, torch.tensor(m.vertices, dtype=torch.float32),
                           torch.tensor(m.faces))
    assert sd.distance.dtype == torch.float32
    np.testing.assert_allclose(sd.distance.numpy(), r[:, 0] - 1.0, atol=5e-3)  # tessellation


def test_chunking_candidates_and_batching_agree():
    m = MESHES["capsule"]()
    body = torch.tensor(m.vertices)
    faces = torch.tensor(m.faces)
    pts = torch.tensor(_points_around(m, 50, seed=5, spread=1.3))
    ref = G.signed_distance(pts, body, faces)
    for kw in ({"chunk_size": 1}, {"chunk_size": 7}, {"candidates": 16},
               {"candidates": 16, "chunk_size": 3}, {"body_edges": G.unique_edges(faces)}):
        out = G.signed_distance(pts, body, faces, **kw)
        torch.testing.assert_close(out.distance, ref.distance, rtol=0, atol=1e-12)
        torch.testing.assert_close(out.closest, ref.closest, rtol=0, atol=1e-12)
    # batched garment and body: [B, V, 3] with [B, Vb, 3]
    shift = torch.tensor([[0.0, 0.0, 0.0], [0.3, -0.2, 0.1]], dtype=D)
    bb = body.unsqueeze(0) + shift[:, None]
    pb = torch.stack([pts, pts + 0.05])
    out = G.signed_distance(pb, bb, faces, chunk_size=11)
    assert out.distance.shape == (2, 50) and out.closest.shape == (2, 50, 3)
    for i in range(2):
        one = G.signed_distance(pb[i], bb[i], faces)
        torch.testing.assert_close(out.distance[i], one.distance)
        torch.testing.assert_close(out.normal[i], one.normal)
        assert torch.equal(out.face[i], one.face)
    # one garment against a batch of bodies broadcasts
    out = G.signed_distance(pts, bb, faces)
    assert out.distance.shape == (2, 50)
    torch.testing.assert_close(out.distance[0], ref.distance)


@pytest.mark.parametrize("candidates", [None, 8])
def test_pairs_in_one_call_equal_one_call_per_pair(candidates):
    """Three garment-body pairs in one call (``point_ptr`` / ``body_ptr`` over a union
    body: a capsule, a torus, an icosphere, each moved over two frames) give each
    pair's own call: values, faces and gradients in points and bodies (brute force and the
    candidate search)."""
    meshes = [MESHES[n]() for n in ("capsule", "torus", "icosphere")]
    bodies = [torch.tensor(np.stack([m.vertices, m.vertices * 1.05 + 0.03])) for m in meshes]
    pts = [torch.tensor(np.stack([_points_around(m, n, seed=s, spread=1.3) for s in (1, 2)]))
           for m, n in zip(meshes, (30, 0, 25))]  # the torus has no points
    pts[1] = pts[1].reshape(2, 0, 3)
    body_ptr = [0] + np.cumsum([b.shape[1] for b in bodies]).tolist()
    point_ptr = [0] + np.cumsum([p.shape[1] for p in pts]).tolist()
    faces = torch.cat([torch.tensor(m.faces) + o for m, o in zip(meshes, body_ptr)])
    P = torch.cat(pts, 1).requires_grad_(True)
    X = torch.cat(bodies, 1).requires_grad_(True)
    out = G.signed_distance(P, X, faces, candidates=candidates, point_ptr=point_ptr,
                            body_ptr=body_ptr)
    (out.distance.sum() + out.closest.sum()).backward()
    fo = np.cumsum([0] + [len(m.faces) for m in meshes])
    for n in (0, 2):
        p = pts[n].clone().requires_grad_(True)
        x = bodies[n].clone().requires_grad_(True)
        one = G.signed_distance(p, x, torch.tensor(meshes[n].faces), candidates=candidates)
        (one.distance.sum() + one.closest.sum()).backward()
        rows = slice(point_ptr[n], point_ptr[n + 1])
        torch.testing.assert_close(out.distance[:, rows], one.distance, rtol=0, atol=1e-12)
        torch.testing.assert_close(out.normal[:, rows], one.normal, rtol=0, atol=1e-12)
        assert torch.equal(out.face[:, rows], one.face + int(fo[n]))
        torch.testing.assert_close(P.grad[:, rows], p.grad, rtol=0, atol=1e-12)
        torch.testing.assert_close(X.grad[:, body_ptr[n]:body_ptr[n + 1]], x.grad, rtol=0,
                                   atol=1e-12)
    pushed = G.push_outside(P.detach(), X.detach(), faces, 0.01, candidates=candidates,
                            point_ptr=point_ptr, body_ptr=body_ptr)
    one = G.push_outside(pts[2], bodies[2], torch.tensor(meshes[2].faces), 0.01,
                         candidates=candidates)
    torch.testing.assert_close(pushed[:, point_ptr[2]:], one, rtol=0, atol=1e-12)


def test_pairs_in_one_call_refuse_bad_pointers():
    m = MESHES["icosphere"]()
    body = torch.tensor(np.concatenate([m.vertices, m.vertices + 1]))
    V = len(m.vertices)
    faces = torch.cat([torch.tensor(m.faces), torch.tensor(m.faces) + V])
    pts = torch.tensor(_points_around(m, 10, seed=3, spread=1.2))
    with pytest.raises(ValueError, match="`point_ptr`"):
        G.signed_distance(pts, body, faces, point_ptr=[0, 4], body_ptr=[0, V, 2 * V])
    with pytest.raises(ValueError, match="`body_ptr`"):
        G.signed_distance(pts, body, faces, point_ptr=[0, 4, 10], body_ptr=[0, V + 1, V])
    with pytest.raises(ValueError, match="one range per mesh"):
        G.signed_distance(pts, body, faces, point_ptr=[0, 4, 10], body_ptr=[0, 2 * V])
    crossing = faces.clone()
    crossing[0, 0] = V
    with pytest.raises(ValueError, match="joins vertices of two meshes"):
        G.signed_distance(pts, body, crossing, point_ptr=[0, 4, 10], body_ptr=[0, V, 2 * V])
    with pytest.raises(ValueError, match="has points but no faces"):
        G.signed_distance(pts, body, faces[:len(m.faces)], point_ptr=[0, 4, 10],
                          body_ptr=[0, V, 2 * V])
    cache = G.NearestFaceCache()
    with pytest.raises(ValueError, match="`cache`"):
        G.signed_distance(pts, body, faces, cache=cache, point_ptr=[0, 4, 10],
                          body_ptr=[0, V, 2 * V])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.bfloat16])
def test_nearest_body_vertices_match_a_dense_search(dtype):
    """The k-d tree's k nearest body vertices are the dense float64 search's, nearest
    first (random points around a moving capsule body, several frames, k from 1 to all
    vertices)."""
    m = MESHES["capsule"]()
    g = torch.Generator().manual_seed(3)
    body = torch.tensor(m.vertices).unsqueeze(0) + 0.1 * torch.randn(3, 1, 3, generator=g,
                                                                     dtype=D)
    pts = body[:, torch.randint(0, body.shape[1], (40,), generator=g)] \
        + 0.05 * torch.randn(3, 40, 3, generator=g, dtype=D)
    pts, body = pts.to(dtype), body.to(dtype)
    for k in (1, 8, body.shape[1]):
        got = dist_mod._nearest_vertices(pts, body, k)
        assert got.shape == (3, 40, k) and got.dtype == torch.long
        d = torch.cdist(pts.double(), body.double())
        ref = d.topk(k, dim=-1, largest=False)
        # same distances in the same order (ties between equidistant vertices may swap)
        torch.testing.assert_close(d.gather(-1, got), ref.values, rtol=0, atol=1e-12)
        assert (got.sort(-1).values == ref.indices.sort(-1).values).float().mean() > 0.99


@pytest.mark.parametrize("name", ["capsule", "torus"])
def test_candidate_search_picks_the_nearest_of_its_candidates(name):
    """The per-coordinate candidate search returns, for every point, a face at the
    smallest distance among the faces around its 8 nearest body vertices: each
    candidate's distance by trimesh's closest point (an independent oracle), over two
    frames of a moving body, points inside and outside."""
    m = MESHES[name]()
    body = torch.tensor(np.stack([m.vertices, m.vertices * 1.1 + 0.02]))  # [2, Vb, 3]
    faces = torch.tensor(m.faces)
    pts = torch.tensor(np.stack([_points_around(m, 200, seed=s, spread=1.4) for s in (5, 6)]))
    nn = dist_mod._nearest_vertices(pts, body, 8)
    table = dist_mod.body_topology(faces, body.shape[1])[1]
    got = dist_mod._closest_candidate(pts, dist_mod._face_corners(body, faces), nn, table)
    for b in range(2):
        mesh = trimesh.Trimesh(body[b].numpy(), m.faces, process=False)
        for i in range(pts.shape[1]):
            cand = np.unique(table[nn[b, i]].numpy())
            cand = cand[cand >= 0]
            p = np.repeat(pts[b, i].numpy()[None], len(cand), 0)
            q = trimesh.triangles.closest_point(mesh.triangles[cand], p)
            d = np.linalg.norm(q - p, axis=1)
            chosen = np.linalg.norm(trimesh.triangles.closest_point(
                mesh.triangles[[int(got[b, i])]], p[:1]) - p[:1], axis=1)[0]
            assert int(got[b, i]) in cand
            assert chosen == pytest.approx(d.min(), abs=1e-12)


def test_candidate_search_is_an_approximation_for_large_triangles():
    """Documented failure mode: a point above the middle of a huge triangle."""
    big = torch.tensor([[-10.0, -10, 0], [10, -10, 0], [0, 10, 0], [5, 5, 0.5], [6, 5, 0.5],
                        [5, 6, 0.5]], dtype=D)
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]])
    p = torch.tensor([[0.0, 0.0, 0.1]], dtype=D)
    exact = G.signed_distance(p, big, faces)
    assert exact.distance.item() == pytest.approx(0.1)
    approx = G.signed_distance(p, big, faces, candidates=1)
    assert approx.distance.abs().item() > 0.1


def test_signed_distance_gradcheck_and_gradient_is_normal():
    m = trimesh.creation.icosphere(subdivisions=1)
    body = torch.tensor(m.vertices)
    faces = torch.tensor(m.faces)
    rng = np.random.default_rng(4)
    dirs = rng.normal(size=(12, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    pts = torch.tensor(dirs * np.r_[np.full(6, 0.6), np.full(6, 1.4)][:, None])
    x = pts.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: G.signed_distance(p, body, faces).distance, (x,))
    # wrt the body as well (fixed sign, smooth region)
    b = body.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda y: G.signed_distance(pts, y, faces).distance, (b,))
    # grad s = (p - q) / s: equals the normal where the closest point is inside a face
    out = G.signed_distance(x, body, faces)
    out.distance.sum().backward()
    unit = (pts - out.closest.detach()) / out.distance.detach().unsqueeze(-1)
    torch.testing.assert_close(x.grad, unit)


def _box_sdf(pts: np.ndarray, h: np.ndarray) -> np.ndarray:
    q = np.abs(pts) - h
    return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(1), 0)


def test_push_outside_box_analytic():
    """Inside or within the margin -> exactly ``margin`` outside (analytic box SDF);
    farther out -> unchanged; faces, edges and corners alike."""
    h = np.array([1.0, 0.5, 0.75])
    m = trimesh.creation.box(extents=2 * h)
    rng = np.random.default_rng(5)
    # shallow points (depth < 0.2, less than half the box's smallest half-extent)
    pts = rng.uniform(-1.3, 1.3, size=(600, 3)) * h
    pts = pts[_box_sdf(pts, h) > -0.2]
    margin = 0.01
    before = _box_sdf(pts, h)
    out = G.push_outside(torch.tensor(pts), torch.tensor(m.vertices), torch.tensor(m.faces),
                         margin, candidates=None).numpy()
    after = _box_sdf(out, h)
    moved = before < margin
    assert moved.sum() > 100 and (~moved).sum() > 100
    np.testing.assert_allclose(after[moved], margin, atol=1e-12)
    np.testing.assert_array_equal(out[~moved], pts[~moved])
    # the move is the shortest one: along the SDF gradient, by margin - s
    np.testing.assert_allclose(np.linalg.norm(out - pts, axis=1)[moved],
                               (margin - before)[moved], atol=1e-12)


def test_push_outside_sphere_float32_and_gradient():
    m = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    X, F = torch.tensor(m.vertices), torch.tensor(m.faces)
    rng = np.random.default_rng(6)
    dirs = rng.normal(size=(40, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    pts = torch.tensor(dirs * rng.uniform(0.7, 0.99, size=(40, 1)))  # all inside
    out32 = G.push_outside(pts.float(), X.float(), F, 0.005)
    assert out32.dtype == torch.float32 and torch.isfinite(out32).all()
    s = G.signed_distance(out32.double(), X, F, candidates=None).distance
    np.testing.assert_allclose(s.numpy(), 0.005, atol=1e-5)
    # differentiable, finite differences (float64)
    p = pts[:5].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda q: G.push_outside(q, X, F, 0.005, candidates=None),
                                    (p,), atol=1e-6)
    with pytest.raises(ValueError, match="margin"):
        G.push_outside(pts, X, F, -0.1)


def test_winding_number_box_and_sphere_analytic():
    # axis-aligned box: grid-aligned vertices and edges (the rays must miss them)
    h = np.array([1.0, 0.5, 0.75])
    m = trimesh.creation.box(extents=2 * h)
    rng = np.random.default_rng(21)
    pts = rng.uniform(-1.3, 1.3, size=(3000, 3)) * h
    pts = pts[np.abs(np.abs(pts) - h).min(1) > 1e-6]
    ref = (np.abs(pts) < h).all(1)
    assert ref.any() and (~ref).any()
    for cell in (None, 0.1, 5.0):
        wn = G.WindingNumber(m.vertices, m.faces, cell=cell)
        w = wn(pts)
        assert w.dtype == np.int64 and set(np.unique(w)) == {0, 1}
        np.testing.assert_array_equal(w == 1, ref)
        np.testing.assert_array_equal(wn.inside(pts), ref)
    # rays along vertical edges and through vertices and face diagonals of the box
    out = np.stack(np.meshgrid([-1.0, 0.0, 1.0], [-0.5, 0.0, 0.5], [-2.0, 2.0],
                               indexing="ij"), -1).reshape(-1, 3)
    inn = np.array([[0.0, 0.0, 0.2], [0.5, 0.25, -0.3], [-0.5, 0.25, 0.0], [0.0, 0.0, -0.7]])
    assert not wn.inside(out).any() and wn.inside(inn).all()
    # sphere: the icosphere lies between radius ~0.997 (face planes) and 1 (vertices)
    s = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    dirs = rng.normal(size=(2000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    r = rng.uniform(0.0, 2.0, size=2000)
    keep = (r < 0.99) | (r > 1.0)
    p = torch.tensor(dirs[keep] * r[keep, None], dtype=torch.float32)
    wn = G.WindingNumber(torch.tensor(s.vertices), torch.tensor(s.faces))
    ins = wn.inside(p)  # a tensor in, a tensor out
    assert isinstance(ins, torch.Tensor) and ins.dtype == torch.bool
    np.testing.assert_array_equal(ins.numpy(), r[keep] < 0.99)
    assert wn(p.view(2, -1, 3)).shape == (2, p.size(0) // 2)


def test_winding_number_overlapping_pieces_and_orientation():
    """Two overlapping closed boxes (like a capsule body): 2 in the overlap, inside the
    union; reversed faces count -1 and are still inside."""
    a = trimesh.creation.box(extents=[2.0, 2.0, 2.0])
    b = trimesh.creation.box(extents=[2.0, 2.0, 2.0])
    V = np.concatenate([a.vertices, b.vertices + [1.0, 0.5, 0.25]])
    F = np.concatenate([a.faces, b.faces + len(a.vertices)])
    rng = np.random.default_rng(22)
    pts = rng.uniform(-1.5, 2.5, size=(3000, 3))
    in_a = (np.abs(pts) < 1).all(1)
    in_b = (np.abs(pts - [1.0, 0.5, 0.25]) < 1).all(1)
    wn = G.WindingNumber(V, F, cell=0.3)
    np.testing.assert_array_equal(wn(pts), in_a.astype(int) + in_b)
    np.testing.assert_array_equal(wn.inside(pts), in_a | in_b)
    flipped = G.WindingNumber(V, F[:, ::-1].copy())
    np.testing.assert_array_equal(flipped(pts), -(in_a.astype(int) + in_b))
    np.testing.assert_array_equal(flipped.inside(pts), in_a | in_b)
    # the torus oracle (generalised winding number) agrees on a non-convex mesh
    t = MESHES["torus"]()
    q = _points_around(t, 400, seed=23, spread=1.2)
    np.testing.assert_array_equal(G.WindingNumber(t.vertices, t.faces).inside(q),
                                  _winding_number(t, q) > 0.5)
    with pytest.raises(ValueError, match="`cell`"):
        G.WindingNumber(V, F, cell=0.0)
    with pytest.raises(ValueError, match="winding numbers.*one rest mesh"):
        G.WindingNumber(torch.tensor(V)[None], torch.tensor(F))


def test_is_closed_mesh_against_trimesh_watertight():
    """Closed means every edge in exactly two faces: trimesh's ``is_watertight`` is the
    oracle on whole meshes, on holed ones and on two disjoint closed pieces."""
    box, sphere = trimesh.creation.box(), trimesh.creation.icosphere(subdivisions=2)
    two = np.concatenate([box.faces, sphere.faces + len(box.vertices)])
    holed = sphere.faces[1:]
    tripled = np.concatenate([box.faces, box.faces[:1]])  # an edge in three faces
    for faces, V in ((box.faces, box.vertices), (sphere.faces, sphere.vertices),
                     (two, np.concatenate([box.vertices, sphere.vertices])),
                     (holed, sphere.vertices), (tripled, box.vertices)):
        want = trimesh.Trimesh(V, faces, process=False).is_watertight
        assert G.is_closed_mesh(torch.from_numpy(faces)) == want
    assert G.is_closed_mesh(torch.zeros(0, 3, dtype=torch.long)) is False


def test_vertex_joint_distances():
    g = torch.Generator().manual_seed(0)
    pos = torch.randn(2, 30, 3, generator=g, dtype=D)
    joints = torch.randn(2, 5, 3, generator=g, dtype=D)
    d = G.vertex_joint_distances(pos, joints)
    assert d.shape == (2, 30, 5)
    for i in range(2):
        np.testing.assert_allclose(d[i].numpy(),
                                   scipy.spatial.distance.cdist(pos[i].numpy(), joints[i].numpy()))
    # one vertex set against a batch of skeletons broadcasts
    np.testing.assert_allclose(G.vertex_joint_distances(pos[0], joints).numpy()[1],
                               scipy.spatial.distance.cdist(pos[0].numpy(), joints[1].numpy()))
    x = pos[0].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: G.vertex_joint_distances(p, joints[0]), (x,))
    same = torch.cat([joints[0, :1], pos[0, 1:]]).requires_grad_(True)  # zero distance
    G.vertex_joint_distances(same, joints[0]).sum().backward()
    assert torch.isfinite(same.grad).all()


def test_distance_bad_input():
    m = trimesh.creation.icosphere(1)
    body, faces = torch.tensor(m.vertices), torch.tensor(m.faces)
    pts = torch.zeros(4, 3, dtype=D)
    bad = pts.clone()
    bad[0, 0] = float("nan")
    with pytest.raises(ValueError, match="`points`.*NaN"):
        G.signed_distance(bad, body, faces)
    with pytest.raises(ValueError, match="`body_faces`.*42"):
        G.signed_distance(pts, body, faces + 1)
    with pytest.raises(ValueError, match="`body_pos`.*empty"):
        G.signed_distance(pts, body[:0], faces)
    with pytest.raises(ValueError, match="`body_pos`.*broadcast"):
        G.signed_distance(pts.expand(3, 4, 3), body.expand(2, 42, 3), faces)
    with pytest.raises(TypeError, match="`body_pos`.*dtype"):
        G.signed_distance(pts, body.float(), faces)
    with pytest.raises(ValueError, match="`chunk_size`"):
        G.signed_distance(pts, body, faces, chunk_size=0)
    with pytest.raises(ValueError, match="`joints`.*shape"):
        G.vertex_joint_distances(pts, torch.zeros(5, 2, dtype=D))


@pytest.mark.slow
def test_compiled_candidate_search_matches_eager():
    """``compiled=True`` (torch.compile of the candidate search) gives the eager
    distances, closest points and projection, batched and not, in float32 and 64."""
    m = MESHES["capsule"]()
    for dtype in (torch.float64, torch.float32):
        body = torch.tensor(m.vertices, dtype=dtype)
        faces = torch.tensor(m.faces)
        pts = torch.tensor(_points_around(m, 300, seed=7, spread=1.3), dtype=dtype)
        for p, b in ((pts, body), (torch.stack([pts, pts + 0.03]), body.expand(2, -1, -1))):
            ref = G.signed_distance(p, b, faces, candidates=8)
            out = G.signed_distance(p, b, faces, candidates=8, compiled=True)
            tol = 1e-12 if dtype == torch.float64 else 1e-6
            torch.testing.assert_close(out.distance, ref.distance, rtol=0, atol=tol)
            torch.testing.assert_close(out.closest, ref.closest, rtol=0, atol=tol)
            torch.testing.assert_close(G.push_outside(p, b, faces, 0.01, compiled=True),
                                       G.push_outside(p, b, faces, 0.01), rtol=0, atol=tol)


def test_compiled_search_falls_back_to_eager_with_a_warning(monkeypatch):
    """Where torch.compile cannot build the search (e.g. no C++ compiler), the call
    warns once and returns the eager result."""
    def broken_compile(fn, **kw):
        def run(*a, **k):
            raise RuntimeError("no compiler")
        return run
    monkeypatch.setattr(dist_mod, "_COMPILED", {})
    monkeypatch.setattr(torch, "compile", broken_compile)
    m = MESHES["capsule"]()
    body, faces = torch.tensor(m.vertices), torch.tensor(m.faces)
    pts = torch.tensor(_points_around(m, 40, seed=3, spread=1.3))
    with pytest.warns(RuntimeWarning, match="compiled distance search unavailable"):
        out = G.signed_distance(pts, body, faces, candidates=8, compiled=True)
    ref = G.signed_distance(pts, body, faces, candidates=8)
    torch.testing.assert_close(out.distance, ref.distance, rtol=0, atol=0)
    assert dist_mod._COMPILED.get("failed")


def test_compiled_search_runs_eager_under_a_dispatch_mode(monkeypatch):
    """Under a ``TorchDispatchMode`` (a FLOP or operator counter) the compiled search is
    not entered: the eager search answers, with no warning, and the compiled one stays in
    use afterwards (entering it under the mode had left it eager for the process)."""
    def never(*args):
        raise AssertionError("the compiled search ran under a dispatch mode")

    class Count(TorchDispatchMode):  # an operator counter, as a profiler runs
        calls = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            Count.calls += 1
            return func(*args, **(kwargs or {}))
    monkeypatch.setattr(dist_mod, "_COMPILED", {"fn": never})
    m = MESHES["capsule"]()
    body, faces = torch.tensor(m.vertices), torch.tensor(m.faces)
    pts = torch.tensor(_points_around(m, 40, seed=3, spread=1.3))
    ref = G.signed_distance(pts, body, faces, candidates=8)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with Count():
            out = G.signed_distance(pts, body, faces, candidates=8, compiled=True)
    torch.testing.assert_close(out.distance, ref.distance, rtol=0, atol=0)
    assert Count.calls > 0 and not dist_mod._COMPILED.get("failed")


def test_body_topology_is_kept_by_faces_content():
    """The body topology comes back for faces of the same values in a new tensor (the
    faces of every batch), equals a fresh ``unique_edges`` and vertex-face table, and is
    built anew for other faces; one built in inference mode serves a differentiable
    distance afterwards, the same as without the cache."""
    m = MESHES["capsule"]()
    faces = torch.tensor(m.faces)
    nv = len(m.vertices)
    with torch.inference_mode():
        topo, table = dist_mod.body_topology(faces.clone(), nv)
    fresh = G.unique_edges(faces, nv)
    torch.testing.assert_close(topo.edges, fresh.edges)
    torch.testing.assert_close(topo.face_edges, fresh.face_edges)
    torch.testing.assert_close(table, dist_mod._vertex_face_table(faces, nv))
    again = dist_mod.body_topology(faces.clone(), nv)
    assert again[0] is topo and again[1] is table
    flipped = faces[:, [0, 2, 1]]
    other = dist_mod.body_topology(flipped, nv)
    assert other[0] is not topo
    torch.testing.assert_close(other[0].face_edges, G.unique_edges(flipped, nv).face_edges)
    body = torch.tensor(m.vertices, dtype=D)
    pts = torch.tensor(_points_around(m, 50, seed=3, spread=1.2), dtype=D).requires_grad_()
    sd = G.signed_distance(pts, body, faces, candidates=8)
    ref = G.signed_distance(pts, body, faces, candidates=8,
                            body_edges=G.unique_edges(faces, nv))
    torch.testing.assert_close(sd.distance, ref.distance, rtol=0, atol=0)
    g, = torch.autograd.grad(sd.distance.sum(), pts)
    g_ref, = torch.autograd.grad(ref.distance.sum(), pts)
    torch.testing.assert_close(g, g_ref, rtol=0, atol=0)
