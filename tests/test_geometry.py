"""garmentgnn.geometry: connectivity, normals, edge lengths, dihedral angles, curvature,
and argument validation.  Oracles: trimesh, numpy references, analytic shapes."""
import math

import numpy as np
import pytest
import torch
import trimesh

from garmentgnn import geometry as G
from garmentgnn.geometry._index import gather_rows, scatter_rows

D = torch.float64


def _t(x, dtype=D):
    return torch.as_tensor(np.asarray(x), dtype=dtype)


def _f(faces):
    return torch.as_tensor(np.asarray(faces), dtype=torch.long)


@pytest.fixture(scope="module")
def noisy_sphere():
    """A closed, irregular (non-uniform, some obtuse triangles) mesh."""
    m = trimesh.creation.icosphere(subdivisions=2)
    rng = np.random.default_rng(0)
    v = m.vertices * (1.0 + 0.1 * rng.uniform(-1, 1, size=(len(m.vertices), 1)))
    v = v + 0.02 * rng.normal(size=v.shape)
    return trimesh.Trimesh(v, m.faces, process=False)


@pytest.fixture(scope="module")
def noisy_sheet():
    pos, faces = G.grid_mesh(9, 7, size=(1.0, 0.8), dtype=D)
    g = torch.Generator().manual_seed(3)
    pos = pos + 0.03 * torch.randn(pos.shape, generator=g, dtype=D)
    return pos, faces


# ---------------------------------------------------------------------------
# connectivity
# ---------------------------------------------------------------------------
def test_unique_edges_match_trimesh(noisy_sphere):
    m = noisy_sphere
    topo = G.unique_edges(_f(m.faces), len(m.vertices))
    ours = {tuple(e) for e in topo.edges.tolist()}
    ref = {tuple(sorted(e)) for e in m.edges_unique.tolist()}
    assert ours == ref and len(ours) == topo.edges.size(0)
    assert bool((topo.counts == 2).all())  # closed manifold
    # face_edges[f, k] is the edge (f[k], f[k+1])
    f = _f(m.faces)
    for k in range(3):
        e = topo.edges[topo.face_edges[:, k]]
        pair = torch.sort(torch.stack([f[:, k], f[:, (k + 1) % 3]], 1), 1).values
        assert torch.equal(e, pair)


def test_unique_edges_grid_boundary_counts():
    nx, ny = 5, 4
    _, faces = G.grid_mesh(nx, ny)
    topo = G.unique_edges(faces, nx * ny)
    n_edges = (nx - 1) * ny + nx * (ny - 1) + (nx - 1) * (ny - 1)
    assert topo.edges.size(0) == n_edges
    assert int((topo.counts == 1).sum()) == 2 * (nx - 1) + 2 * (ny - 1)
    bnd = G.boundary_vertex_mask(faces, nx * ny)
    assert int(bnd.sum()) == 2 * nx + 2 * ny - 4


def test_face_adjacency_matches_trimesh(noisy_sphere):
    m = noisy_sphere
    f = _f(m.faces)
    adj = G.face_adjacency(f, len(m.vertices))
    assert adj.faces.shape == (len(m.face_adjacency), 2)
    def key(a, b):
        return (min(a, b), max(a, b))

    ref = {}
    for (f1, f2), e, un in zip(m.face_adjacency.tolist(), m.face_adjacency_edges.tolist(),
                               m.face_adjacency_unshared.tolist()):
        ref[key(f1, f2)] = (tuple(sorted(e)), {(f1, un[0]), (f2, un[1])})
    for (f1, f2), e, o in zip(adj.faces.tolist(), adj.edges.tolist(), adj.opposite.tolist()):
        edge, opp = ref[key(f1, f2)]
        assert tuple(sorted(e)) == edge
        assert {(f1, o[0]), (f2, o[1])} == opp
        # the shared edge is oriented as face f1 traverses it
        row = m.faces[f1].tolist()
        i = row.index(e[0])
        assert row[(i + 1) % 3] == e[1]


def test_face_adjacency_nonmanifold_chain():
    # three triangles on one edge (0, 1)
    faces = _f([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    adj = G.face_adjacency(faces)
    assert adj.faces.shape == (2, 2)
    assert set(map(tuple, adj.faces.tolist())) == {(0, 1), (1, 2)}


# ---------------------------------------------------------------------------
# normals and areas
# ---------------------------------------------------------------------------
def test_face_normals_and_areas_match_trimesh(noisy_sphere):
    m = noisy_sphere
    pos, f = _t(m.vertices), _f(m.faces)
    np.testing.assert_allclose(G.face_normals(pos, f).numpy(), m.face_normals, atol=1e-12)
    np.testing.assert_allclose(G.face_areas(pos, f).numpy(), m.area_faces, rtol=1e-12)


def test_vertex_normals_area_weighted_reference(noisy_sphere):
    """trimesh's vertex_normals are angle-weighted; check both weightings."""
    m = noisy_sphere
    pos, f = _t(m.vertices), _f(m.faces)
    # independent numpy reference: sum of area * unit face normal, then normalise
    acc = trimesh.geometry.index_sparse(len(m.vertices), m.faces).dot(
        m.face_normals * m.area_faces[:, None])
    ref = acc / np.linalg.norm(acc, axis=1, keepdims=True)
    np.testing.assert_allclose(G.vertex_normals(pos, f).numpy(), ref, atol=1e-12)
    np.testing.assert_allclose(G.vertex_normals(pos, f, weighting="angle").numpy(),
                               m.vertex_normals, atol=1e-12)


def test_normals_batched_and_isolated_vertex():
    pos, faces = G.grid_mesh(4, 3, dtype=D)
    pos = torch.cat([pos, torch.tensor([[5.0, 5.0, 5.0]], dtype=D)])  # isolated vertex
    R = G.axis_angle_to_matrix(torch.tensor([0.3, -0.2, 0.5], dtype=D))
    batch = torch.stack([pos, pos @ R.T])
    vn = G.vertex_normals(batch, faces)
    assert vn.shape == (2, pos.size(0), 3)
    assert torch.isfinite(vn).all()
    assert torch.equal(vn[:, -1], torch.zeros(2, 3, dtype=D))
    torch.testing.assert_close(vn[0, :-1], torch.tensor([0.0, 0.0, 1.0], dtype=D).expand(12, 3))
    torch.testing.assert_close(vn[1], G.vertex_normals(pos @ R.T, faces))
    torch.testing.assert_close(G.face_normals(batch, faces)[1], G.face_normals(pos, faces) @ R.T)


def test_degenerate_face_gives_zero_normal_and_finite_grad():
    pos = torch.tensor([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]], dtype=D,
                       requires_grad=True)
    faces = _f([[0, 1, 2], [0, 1, 3]])
    n = G.face_normals(pos, faces)
    assert torch.equal(n[0], torch.zeros(3, dtype=D))
    (n.sum() + G.vertex_normals(pos, faces).sum() + G.face_areas(pos, faces).sum()).backward()
    assert torch.isfinite(pos.grad).all()


# ---------------------------------------------------------------------------
# edge lengths and dihedral angles
# ---------------------------------------------------------------------------
def test_edge_lengths_of_grid():
    nx, ny = 4, 3
    pos, faces = G.grid_mesh(nx, ny, size=(3.0, 1.0), dtype=D)  # dx = 1, dy = 0.5
    topo = G.unique_edges(faces, nx * ny)
    ell = G.edge_lengths(pos, topo.edges)
    vals, counts = torch.unique(torch.round(ell * 1e9) / 1e9, return_counts=True)
    expect = {1.0: (nx - 1) * ny, 0.5: nx * (ny - 1), math.sqrt(1.25): (nx - 1) * (ny - 1)}
    assert len(vals) == 3
    for v, c in zip(vals.tolist(), counts.tolist()):
        key = min(expect, key=lambda k: abs(k - v))
        assert abs(key - v) < 1e-9 and expect[key] == c
    # batched, and [2, E] edge_index via .t()
    ei = G.faces_to_edge_index(faces, nx * ny)
    both = G.edge_lengths(torch.stack([pos, 2 * pos]), ei.t())
    torch.testing.assert_close(both[1], 2 * both[0])


def test_project_edge_lengths_single_edge_exact_and_rigid_fixed_point(noisy_sphere):
    """One sweep makes an isolated edge exactly its rest length, the midpoint kept; a
    rigidly moved mesh (every edge at rest length) is a fixed point."""
    pos = _t([[0.0, 0, 0], [2, 1, 2]])
    out = G.project_edge_lengths(pos, _f([[0, 1]]), _t([1.5]), iterations=1)
    assert float((out[1] - out[0]).norm()) == pytest.approx(1.5, abs=1e-12)
    torch.testing.assert_close(out.mean(0), pos.mean(0))
    v, faces = _t(noisy_sphere.vertices), _f(noisy_sphere.faces)
    edges = G.unique_edges(faces, len(v)).edges
    rest = G.edge_lengths(v, edges)
    R = G.axis_angle_to_matrix(_t([0.3, -1.1, 0.7]))
    moved = v @ R.T + _t([0.5, -2.0, 1.0])
    torch.testing.assert_close(G.project_edge_lengths(moved, edges, rest, 20), moved)


def _edge_sweeps_per_frame(pos, edges, rest, iterations, stretch_only, rho=None, warmup=5):
    """The Jacobi sweeps of ``project_edge_lengths`` written per frame, one loop over the
    edges at a time (the oracle of its batched layout); ``rho``: each sweep after
    ``warmup`` is Wang 2015's Chebyshev step, its weights from their closed-form
    recurrence."""
    out = pos.clone()
    flat, flat_rest = out.reshape(-1, *pos.shape[-2:]), rest.expand(
        *pos.shape[:-2], rest.shape[-1]).reshape(-1, rest.shape[-1])
    deg = torch.bincount(edges.flatten(), minlength=pos.shape[-2]).clamp_min(1)
    for f in range(flat.shape[0]):
        p = before = flat[f]
        omega = None
        for sweep in range(iterations):
            move = torch.zeros_like(p)
            for k, (i, j) in enumerate(edges.tolist()):
                d = p[j] - p[i]
                length = d.norm()
                if stretch_only and not length > flat_rest[f, k]:
                    continue
                c = 0.5 * (1.0 - flat_rest[f, k] / length) * d
                move[i] += c
                move[j] -= c
            jacobi = p + move / deg.unsqueeze(-1)
            if rho is None or sweep < warmup:
                before, p = p, jacobi
                continue
            omega = 2 / (2 - rho ** 2) if omega is None else 1 / (1 - rho ** 2 * omega / 4)
            before, p = p, before + omega * (jacobi - before)
        flat[f] = p
    return out


@pytest.mark.parametrize("stretch_only,rho,sweeps", [(False, None, 3), (True, None, 3),
                                                     (False, 0.9, 8)])
def test_project_edge_lengths_batched_matches_per_frame_loop(stretch_only, rho, sweeps):
    """Frames ``[2, 3, V, 3]`` with rest lengths per frame ``[3, E]`` (broadcast over the
    first dimension) give the per-frame loop's positions (plain sweeps, and Chebyshev's
    after its warm-up), and gradients that agree with finite differences."""
    g = torch.Generator().manual_seed(0)
    pos = torch.rand(2, 3, 6, 3, generator=g, dtype=D)
    edges = torch.tensor([[0, 1], [1, 2], [2, 0], [2, 3], [3, 4], [4, 5], [5, 3], [1, 4]])
    rest = 0.3 + 0.4 * torch.rand(3, len(edges), generator=g, dtype=D)
    out = G.project_edge_lengths(pos, edges, rest, sweeps, stretch_only=stretch_only,
                                 chebyshev=rho)
    torch.testing.assert_close(out, _edge_sweeps_per_frame(pos, edges, rest, sweeps,
                                                           stretch_only, rho))
    x = pos[:1].clone().requires_grad_()
    assert torch.autograd.gradcheck(
        lambda p: G.project_edge_lengths(p, edges, rest, sweeps - 1, stretch_only=stretch_only,
                                         chebyshev=rho), (x,))


def test_project_edge_lengths_chebyshev_converges_faster_and_keeps_rigid_motion(noisy_sphere):
    """On a sphere (edges about 0.3) with 0.03 of noise on every vertex, 100 Chebyshev
    sweeps leave less mean edge-length error than 300 plain ones; a rigidly moved mesh
    stays a fixed point; bad ``chebyshev`` values and ``stretch_only`` with it are
    refused."""
    v, faces = _t(noisy_sphere.vertices), _f(noisy_sphere.faces)
    edges = G.unique_edges(faces, len(v)).edges
    rest = G.edge_lengths(v, edges)
    g = torch.Generator().manual_seed(1)
    noisy = v + 0.03 * torch.randn(v.shape, generator=g, dtype=D)

    def err(p):
        return float(((G.edge_lengths(p, edges) - rest).abs() / rest).mean())
    fast = err(G.project_edge_lengths(noisy, edges, rest, 100, chebyshev=0.99))
    plain = err(G.project_edge_lengths(noisy, edges, rest, 300))
    assert fast < plain < err(noisy)
    R = G.axis_angle_to_matrix(_t([0.3, -1.1, 0.7]))
    moved = v @ R.T + _t([0.5, -2.0, 1.0])
    torch.testing.assert_close(G.project_edge_lengths(moved, edges, rest, 20, chebyshev=0.99),
                               moved)
    for bad in (0.0, 1.0, -0.5, True, "0.9"):
        with pytest.raises(ValueError, match="chebyshev"):
            G.project_edge_lengths(noisy, edges, rest, 10, chebyshev=bad)
    with pytest.raises(ValueError, match="stretch_only"):
        G.project_edge_lengths(noisy, edges, rest, 10, stretch_only=True, chebyshev=0.9)


def test_project_edge_lengths_converges_and_stretch_only(noisy_sphere):
    """A uniformly stretched mesh (5%) is pulled back to its rest lengths, the mean
    error falling every sweep (Jacobi sweeps are slow: under 1% after 1000);
    ``stretch_only`` leaves a uniformly compressed mesh as it is and only lowers the
    stretched edges of a mixed one."""
    v, faces = _t(noisy_sphere.vertices), _f(noisy_sphere.faces)
    edges = G.unique_edges(faces, len(v)).edges
    rest = G.edge_lengths(v, edges)

    def err(p):
        return ((G.edge_lengths(p, edges) - rest).abs() / rest)
    p, errs = 1.05 * v, []
    for _ in range(8):
        p = G.project_edge_lengths(p, edges, rest, 1)
        errs.append(float(err(p).mean()))
    assert all(b < a for a, b in zip(errs, errs[1:])) and errs[0] < 0.05
    assert float(err(G.project_edge_lengths(1.05 * v, edges, rest, 1000)).max()) < 0.01
    small = 0.9 * v
    torch.testing.assert_close(G.project_edge_lengths(small, edges, rest, 5, stretch_only=True),
                               small)
    g = torch.Generator().manual_seed(0)
    mixed = v * (1 + 0.05 * torch.randn(v.shape[0], 1, generator=g, dtype=D))
    ratio = G.edge_lengths(mixed, edges) / rest
    after = G.edge_lengths(G.project_edge_lengths(mixed, edges, rest, 10, stretch_only=True),
                           edges) / rest
    assert float(after.max()) < float(ratio.max()) - 0.02
    assert float(after.min()) < 1.0 and float(ratio.min()) < 1.0


def test_project_edge_lengths_gradcheck_batched_and_errors(noisy_sheet):
    pos, faces = noisy_sheet
    edges = G.unique_edges(faces, pos.shape[0]).edges
    rest = 0.97 * G.edge_lengths(pos, edges)
    x = pos[:20].clone().requires_grad_(True)
    sub = edges[(edges < 20).all(1)]
    assert torch.autograd.gradcheck(
        lambda p: G.project_edge_lengths(p, sub, rest[(edges < 20).all(1)], 3), (x,))
    both = G.project_edge_lengths(torch.stack([pos, pos + 1.0]), edges, rest, 4)
    torch.testing.assert_close(both[1], both[0] + 1.0)
    with pytest.raises(ValueError, match="iterations"):
        G.project_edge_lengths(pos, edges, rest, -1)
    with pytest.raises(ValueError, match="rest_lengths"):
        G.project_edge_lengths(pos, edges, rest[:-1], 1)


def _hinge(alpha, up=False):
    """Faces (0,1,2) flat in z=0, normal +z, and (1,0,3) rotated about the x axis by
    ``alpha`` downwards (a ridge, convex) or upwards (a valley)."""
    s = 1.0 if up else -1.0
    pos = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0.5, 1, 0],
                        [0.5, -math.cos(alpha), s * math.sin(alpha)]], dtype=D)
    return pos, _f([[0, 1, 2], [1, 0, 3]])


@pytest.mark.parametrize("alpha", [0.0, 0.3, 1.0, math.pi / 2, 2.5, 3.0])
def test_dihedral_angle_of_folded_hinge(alpha):
    pos, faces = _hinge(alpha)
    th = G.dihedral_angles(pos, faces)
    assert th.shape == (1,)
    assert th.item() == pytest.approx(alpha, abs=1e-12)  # convex fold: positive
    pos, faces = _hinge(alpha, up=True)
    assert G.dihedral_angles(pos, faces).item() == pytest.approx(-alpha, abs=1e-12)
    assert G.dihedral_angles(pos, faces, signed=False).item() == pytest.approx(alpha, abs=1e-7)


def test_dihedral_unsigned_matches_trimesh_and_sphere_is_convex(noisy_sphere):
    m = noisy_sphere
    pos, f = _t(m.vertices), _f(m.faces)
    adj = G.face_adjacency(f, len(m.vertices))
    ours = dict(zip((tuple(sorted(p)) for p in adj.faces.tolist()),
                    G.dihedral_angles(pos, f, adj, signed=False).tolist()))
    for (a, b), ang in zip(m.face_adjacency.tolist(), m.face_adjacency_angles):
        assert ours[(min(a, b), max(a, b))] == pytest.approx(ang, abs=1e-7)
    sph = trimesh.creation.icosphere(2)
    assert bool((G.dihedral_angles(_t(sph.vertices), _f(sph.faces)) > 0).all())


def test_dihedral_gradcheck(noisy_sheet):
    pos, faces = noisy_sheet
    adj = G.face_adjacency(faces)
    x = pos.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: G.dihedral_angles(p, faces, adj), (x,))


# ---------------------------------------------------------------------------
# curvature
# ---------------------------------------------------------------------------
def test_angle_defect_matches_trimesh(noisy_sphere):
    m = noisy_sphere
    pos, f = _t(m.vertices), _f(m.faces)
    defect = G.angle_defect(pos, f)
    np.testing.assert_allclose(defect.numpy(), m.vertex_defects, atol=1e-12)
    # trimesh's curvature *measure* at radius 0 is the (un-normalised) defect
    meas = trimesh.curvature.discrete_gaussian_curvature_measure(m, m.vertices[:20], 0.0)
    np.testing.assert_allclose(defect[:20].numpy(), meas, atol=1e-12)
    assert defect.sum().item() == pytest.approx(4 * math.pi, abs=1e-9)  # Gauss-Bonnet


def test_angle_defect_difference_matches_trimesh_on_interior_vertices(noisy_sheet):
    pos, faces = noisy_sheet
    bumped = pos.clone()
    bumped[..., 2] += 0.05 * torch.sin(3 * pos[..., 0])
    interior = ~G.boundary_vertex_mask(faces, pos.size(0)).numpy()
    ref = [trimesh.Trimesh(p.numpy(), faces.numpy(), process=False).vertex_defects
           for p in (bumped, pos)]
    expect = np.abs(ref[0] - ref[1])[interior].mean()
    assert expect > 1e-3
    assert G.angle_defect_difference(bumped, pos, faces).item() == pytest.approx(expect, rel=1e-10)
    both = G.angle_defect_difference(torch.stack([bumped, pos]), torch.stack([pos, pos]), faces)
    assert both.shape == (2,) and both[1].item() == 0.0
    with pytest.raises(ValueError, match="same shape"):
        G.angle_defect_difference(bumped, pos[:-1], faces)


@pytest.mark.parametrize("r", [1.0, 2.5])
def test_gaussian_curvature_of_sphere(r):
    m = trimesh.creation.icosphere(subdivisions=3, radius=r)
    K = G.gaussian_curvature(_t(m.vertices), _f(m.faces))
    np.testing.assert_allclose(K.numpy(), 1.0 / r ** 2, rtol=0.02)


def test_mixed_areas_partition_surface(noisy_sphere, noisy_sheet):
    m = noisy_sphere
    A = G.mixed_voronoi_areas(_t(m.vertices), _f(m.faces))
    assert A.sum().item() == pytest.approx(m.area, rel=1e-12)
    assert bool((A > 0).all())
    pos, faces = noisy_sheet
    ang = G.face_angles(pos, faces)
    assert bool((ang > math.pi / 2).any())  # exercises the obtuse branch
    assert G.mixed_voronoi_areas(pos, faces).sum().item() == pytest.approx(
        G.face_areas(pos, faces).sum().item(), rel=1e-12)


def _voronoi_area_acute(p, i):
    """Area of the Voronoi cell of corner i in an acute triangle: the quadrilateral
    (p_i, midpoint of p_i p_j, circumcentre, midpoint of p_i p_k), by the shoelace rule."""
    a, b, c = p
    d = 2 * (a[0] * (b[1] - c[1]) + b[0] * (c[1] - a[1]) + c[0] * (a[1] - b[1]))
    ux = ((a @ a) * (b[1] - c[1]) + (b @ b) * (c[1] - a[1]) + (c @ c) * (a[1] - b[1])) / d
    uy = ((a @ a) * (c[0] - b[0]) + (b @ b) * (a[0] - c[0]) + (c @ c) * (b[0] - a[0])) / d
    o = np.array([ux, uy])
    j, k = (i + 1) % 3, (i + 2) % 3
    quad = np.array([p[i], (p[i] + p[j]) / 2, o, (p[i] + p[k]) / 2])
    x, y = quad[:, 0], quad[:, 1]
    return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def test_mixed_areas_single_triangles():
    acute = np.array([[0.0, 0.0], [1.0, 0.1], [0.4, 0.8]])
    pos = torch.tensor(np.c_[acute, np.zeros(3)], dtype=D)
    faces = _f([[0, 1, 2]])
    assert bool((G.face_angles(pos, faces) < math.pi / 2).all())
    A = G.mixed_voronoi_areas(pos, faces).numpy()
    np.testing.assert_allclose(A, [_voronoi_area_acute(acute, i) for i in range(3)],
                               rtol=1e-12)
    obtuse = torch.tensor([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.3, 0.2, 0.0]], dtype=D)
    area = 0.5 * 2.0 * 0.2
    A = G.mixed_voronoi_areas(obtuse, faces).numpy()  # obtuse at vertex 2
    np.testing.assert_allclose(A, [area / 4, area / 4, area / 2], rtol=1e-12)


def test_curvature_boundary_handling(noisy_sheet):
    pos, faces = G.grid_mesh(6, 5, dtype=D)
    bnd = G.boundary_vertex_mask(faces, pos.size(0))
    K = G.gaussian_curvature(pos, faces)
    assert torch.equal(K, torch.zeros_like(K))  # flat interior, boundary zeroed
    d = G.angle_defect(pos, faces)  # boundary: pi - sum (turning angle)
    torch.testing.assert_close(d[bnd].sum(), torch.tensor(2 * math.pi, dtype=D))
    assert G.angle_defect(pos, faces, boundary="zero")[bnd].abs().max() == 0
    # Gauss-Bonnet for a (bumpy) disk: sum of defects = 2 pi chi = 2 pi
    p2, f2 = noisy_sheet
    assert G.angle_defect(p2, f2).sum().item() == pytest.approx(2 * math.pi, abs=1e-9)
    Kb = G.gaussian_curvature(p2, f2, boundary="turning")
    b2 = G.boundary_vertex_mask(f2, p2.size(0))
    assert torch.isfinite(Kb).all() and (Kb[b2] != 0).any()
    assert torch.equal(G.gaussian_curvature(p2, f2)[b2], torch.zeros(int(b2.sum()), dtype=D))


# ---------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------
def test_bad_inputs_raise_with_argument_name():
    pos, faces = G.grid_mesh(3, 3, dtype=D)
    bad = pos.clone()
    bad[1, 0] = float("nan")
    for fn in (G.face_normals, G.face_areas, G.vertex_normals, G.angle_defect,
               G.gaussian_curvature, G.dihedral_angles, G.mixed_voronoi_areas):
        with pytest.raises(ValueError, match="`pos`.*NaN"):
            fn(bad, faces)
        with pytest.raises(ValueError, match=r"`faces`.*\[0, 9\)"):
            fn(pos, torch.cat([faces, torch.tensor([[0, 1, 9]])]))
        with pytest.raises(ValueError, match="`pos`.*empty"):
            fn(pos[:0], faces)
        with pytest.raises(ValueError, match="`faces`.*no faces"):
            fn(pos, faces[:0])
    with pytest.raises(TypeError, match="`faces`.*integer"):
        G.face_normals(pos, faces.double())
    with pytest.raises(TypeError, match="`pos`.*torch.Tensor"):
        G.face_normals(pos.numpy(), faces)
    with pytest.raises(ValueError, match="`pos`.*shape"):
        G.face_normals(pos[:, :2], faces)
    with pytest.raises(ValueError, match="`faces`.*-1"):
        G.unique_edges(faces - 1)
    with pytest.raises(ValueError, match="`weighting`"):
        G.vertex_normals(pos, faces, weighting="mean")
    with pytest.raises(ValueError, match="`edges`"):
        G.edge_lengths(pos, G.faces_to_edge_index(faces, 9))  # [2, E] instead of [E, 2]


# ---------------------------------------------------------------------------
# batching: [B, V, 3] with shared faces equals per-mesh calls
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("fn", [
    G.face_normals, G.face_areas, G.face_angles, G.vertex_normals,
    lambda p, f: G.vertex_normals(p, f, weighting="angle"), G.dihedral_angles,
    lambda p, f: G.dihedral_angles(p, f, signed=False), G.face_cotangents,
    G.mixed_voronoi_areas, G.angle_defect, G.gaussian_curvature,
    lambda p, f: G.edge_lengths(p, G.unique_edges(f).edges),
], ids=["face_normals", "face_areas", "face_angles", "vertex_normals", "vn_angle",
        "dihedral", "dihedral_unsigned", "cotangents", "mixed_areas", "angle_defect",
        "gaussian_curvature", "edge_lengths"])
def test_batched_equals_per_mesh(fn, noisy_sheet):
    pos, faces = noisy_sheet
    g = torch.Generator().manual_seed(11)
    batch = torch.stack([pos, pos + 0.05 * torch.randn(pos.shape, generator=g, dtype=D),
                         2.0 * pos.flip(-1)])
    out = fn(batch, faces)
    assert out.shape[0] == 3
    for i in range(3):
        torch.testing.assert_close(out[i], fn(batch[i], faces))
    two = fn(batch.view(3, 1, *pos.shape).expand(3, 2, *pos.shape), faces)  # [3, 2, V, 3]
    torch.testing.assert_close(two[:, 1], out)


def test_full_precision_lifts_low_precision_only_under_autocast():
    x, lo, wide = torch.randn(4, 4), torch.randn(4, 4).bfloat16(), torch.randn(4, 4).double()
    with G.full_precision(x) as up:  # no autocast: nothing changes
        assert up(lo) is lo and up(wide) is wide and (x @ x).dtype == torch.float32
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert (x @ x).dtype == torch.bfloat16  # what autocast does outside
        with G.full_precision(x) as up:
            assert (x @ x).dtype == torch.float32  # autocast off inside
            assert up(lo).dtype == torch.float32 and up(wide).dtype == torch.float64
            torch.testing.assert_close(up(lo), lo.float(), rtol=0, atol=0)
        assert (x @ x).dtype == torch.bfloat16  # and back on after


@pytest.mark.parametrize("shape", [(7, 3), (2, 7, 3), (2, 4, 7, 5)])
@pytest.mark.parametrize("index_shape", [(5,), (4, 3)])
def test_vertex_major_row_gather_and_scatter_equal_indexing(shape, index_shape):
    """``gather_rows`` is ``x[..., index, :]`` and ``scatter_rows`` is ``index_add`` along
    the vertex axis (repeated indices summed), values and gradients, unbatched and
    batched, for flat and ``[F, 3]``-shaped indices."""
    g = torch.Generator().manual_seed(0)
    x = torch.randn(shape, dtype=D, generator=g, requires_grad=True)
    index = torch.randint(0, 7, index_shape, generator=g)
    index.view(-1)[:2] = 3  # a repeated row
    got = gather_rows(x, index)
    assert torch.equal(got, x[..., index, :])
    assert torch.autograd.gradcheck(lambda x: gather_rows(x, index), (x,))
    src = torch.randn(*shape[:-2], *index_shape, shape[-1], dtype=D, generator=g,
                      requires_grad=True)
    ref = torch.zeros(*shape[:-2], 7, shape[-1], dtype=D).index_add(
        len(shape) - 2, index.reshape(-1), src.reshape(*shape[:-2], -1, shape[-1]))
    torch.testing.assert_close(scatter_rows(src, index, 7), ref, rtol=0, atol=1e-14)
    assert torch.autograd.gradcheck(lambda s: scatter_rows(s, index, 7), (src,))
