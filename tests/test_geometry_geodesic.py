"""Geodesic distances (graph Dijkstra, heat method) and Nystroem spectral features (§3.1)."""
import numpy as np
import pytest
import scipy.linalg
import scipy.sparse as sp
import torch
import trimesh
from scipy.sparse.csgraph import dijkstra

from garmentgnn import geometry as G

D = torch.float64


def _dense_geodesics(m: trimesh.Trimesh) -> np.ndarray:
    """All-pairs edge-graph distances, built independently from trimesh's edges."""
    n = len(m.vertices)
    e, w = m.edges_unique, m.edges_unique_length
    g = sp.coo_matrix((w, (e[:, 0], e[:, 1])), shape=(n, n))
    return dijkstra(g, directed=False)


@pytest.fixture(scope="module")
def sheet300():
    """~300-vertex bumpy rectangular sheet (no symmetry, distinct top eigenvalues)."""
    pos, faces = G.grid_mesh(20, 15, size=(1.0, 0.6), dtype=D)
    g = torch.Generator().manual_seed(0)
    pos = pos + 0.02 * torch.randn(pos.shape, generator=g, dtype=D)
    m = trimesh.Trimesh(pos.numpy(), faces.numpy(), process=False)
    return pos, faces, m


def test_graph_geodesics_match_scipy_dijkstra():
    m = trimesh.creation.icosphere(2)
    rng = np.random.default_rng(1)
    m = trimesh.Trimesh(m.vertices + 0.03 * rng.normal(size=m.vertices.shape), m.faces,
                        process=False)
    ref = _dense_geodesics(m)
    src = [0, 7, 100]
    d = G.graph_geodesic_distances(torch.tensor(m.vertices), torch.tensor(m.faces), src)
    assert isinstance(d, torch.Tensor) and d.shape == (3, len(m.vertices)) and d.dtype == D
    np.testing.assert_allclose(d.numpy(), ref[src], rtol=1e-12)
    dn = G.graph_geodesic_distances(m.vertices, m.faces, np.array([5]))  # numpy in, numpy out
    assert isinstance(dn, np.ndarray)
    np.testing.assert_allclose(dn, ref[[5]], rtol=1e-12)
    d32 = G.graph_geodesic_distances(torch.tensor(m.vertices, dtype=torch.float32),
                                     torch.tensor(m.faces), 0)
    assert d32.dtype == torch.float32 and d32.shape == (1, len(m.vertices))


def test_graph_geodesics_disconnected_is_inf():
    pos, faces = G.grid_mesh(3, 3, dtype=D)
    pos2 = torch.cat([pos, pos + 5.0])
    faces2 = torch.cat([faces, faces + 9])
    d = G.graph_geodesic_distances(pos2, faces2, [0])
    assert torch.isinf(d[0, 9:]).all() and torch.isfinite(d[0, :9]).all()


def test_heat_method_on_sphere_matches_great_circle():
    r = 1.5
    m = trimesh.creation.icosphere(subdivisions=4, radius=r)
    src = [0, 1234]
    d = G.heat_geodesic_distances(torch.tensor(m.vertices), torch.tensor(m.faces), src).numpy()
    u = m.vertices / r
    gc = r * np.arccos(np.clip(u[src] @ u.T, -1.0, 1.0))
    err = np.abs(d - gc)
    assert err.max() < 0.02 * np.pi * r  # a few percent of the largest distance
    assert err.mean() < 0.01 * np.pi * r
    assert np.allclose(d[[0, 1], src], 0.0)
    # the edge-graph distance zig-zags: the heat method is markedly more accurate
    dg = G.graph_geodesic_distances(m.vertices, m.faces, src)
    assert np.abs(dg - gc).mean() > 2 * err.mean()


def test_heat_method_on_flat_sheet_matches_euclidean():
    pos, faces = G.grid_mesh(25, 20, size=(1.0, 0.8), dtype=D)
    src = [12 * 20 + 10, 0]
    solver = G.HeatGeodesicSolver(pos, faces)
    d = solver(src)
    eu = np.linalg.norm(pos.numpy()[None] - pos.numpy()[src][:, None], axis=-1)
    assert np.abs(d - eu).max() < 0.05 and np.abs(d - eu).mean() < 0.015


def test_cotan_laplacian_properties():
    m = trimesh.creation.icosphere(2)
    L, M = G.cotan_laplacian(m.vertices, m.faces)
    assert abs(L - L.T).max() < 1e-12
    np.testing.assert_allclose(L @ np.ones(len(m.vertices)), 0.0, atol=1e-12)
    assert M.sum() == pytest.approx(m.area, rel=1e-12)
    # linear functions are harmonic on a flat mesh (interior rows)
    pos, faces = G.grid_mesh(6, 5, dtype=D)
    Lf, _ = G.cotan_laplacian(pos, faces)
    bnd = G.boundary_vertex_mask(faces, 30).numpy()
    lin = pos.numpy() @ np.array([0.3, -1.2, 0.0])
    np.testing.assert_allclose((Lf @ lin)[~bnd], 0.0, atol=1e-12)


def test_farthest_point_sampling_is_deterministic_and_farthest(sheet300):
    pos, faces, m = sheet300
    lm, dist = G.farthest_point_sampling(pos, faces, 12, seed=3)
    lm2, _ = G.farthest_point_sampling(pos, faces, 12, seed=3)
    assert torch.equal(lm, lm2) and len(set(lm.tolist())) == 12
    assert dist.shape == (12, pos.size(0))
    ref = _dense_geodesics(m)
    np.testing.assert_allclose(dist.numpy(), ref[lm.numpy()], rtol=1e-12)
    for i in range(1, 12):  # every landmark maximises the distance to the previous ones
        mind = ref[lm[:i].numpy()].min(0)
        assert mind[lm[i]] == pytest.approx(mind.max())
    lm3, _ = G.farthest_point_sampling(pos, faces, 12, seed=4)
    lm4, _ = G.farthest_point_sampling(pos, faces, 12, start=int(lm[0]))
    assert torch.equal(lm4, lm) and not torch.equal(lm3, lm)


def _dense_top_eigvecs(m, sigma, k):
    Dd = _dense_geodesics(m)
    A = np.exp(-Dd ** 2 / (2 * sigma ** 2))
    lam, U = np.linalg.eigh(A)
    return lam[::-1][: k + 1], U[:, ::-1][:, :k]


@pytest.mark.parametrize("method", ["one_shot", "basic"])
def test_nystrom_with_all_landmarks_is_exact(sheet300, method):
    pos, faces, m = sheet300
    k = 6
    info = G.geodesic_nystrom_features(pos, faces, k=k, num_landmarks=pos.size(0),
                                       method=method, return_info=True)
    lam, U = _dense_top_eigvecs(m, info.sigma, k)
    assert np.all(np.diff(lam) < -1e-3 * lam[0])  # distinct eigenvalues: unique vectors
    V = info.features.numpy()
    assert V.shape == (pos.size(0), k)
    sign = np.sign((V * U).sum(0))
    np.testing.assert_allclose(V, U * sign, atol=1e-8)
    np.testing.assert_allclose(info.eigenvalues.numpy(), lam[:k], rtol=1e-10)
    # default sigma = median positive landmark distance (all pairs here)
    Dd = _dense_geodesics(m)
    assert info.sigma == pytest.approx(np.median(Dd[Dd > 0]), rel=1e-12)


def test_nystrom_with_few_landmarks_spans_top_eigenspace(sheet300):
    pos, faces, m = sheet300
    k, Z = 6, 60
    Dd = _dense_geodesics(m)
    sigma = float(np.median(Dd[Dd > 0]))
    _, U = _dense_top_eigvecs(m, sigma, k)
    for method, tol in [("one_shot", 0.15), ("basic", 0.3)]:
        V = G.geodesic_nystrom_features(pos, faces, k=k, num_landmarks=Z, sigma=sigma,
                                        method=method).numpy()
        assert scipy.linalg.subspace_angles(V, U).max() < tol
        corr = np.abs((V / np.linalg.norm(V, axis=0) * U).sum(0))
        assert corr[:3].min() > 0.99
    V = G.geodesic_nystrom_features(pos, faces, k=k, num_landmarks=Z, sigma=sigma).numpy()
    np.testing.assert_allclose(V.T @ V, np.eye(k), atol=1e-10)  # one-shot: orthonormal
    V2 = G.geodesic_nystrom_features(pos, faces, k=k, num_landmarks=Z, sigma=sigma).numpy()
    assert np.array_equal(V, V2)  # deterministic, sign-fixed


def test_nystrom_scales_without_dense_matrix():
    """10k vertices, 32 landmarks: O(N Z) memory; a dense affinity would be 800 MB."""
    m = trimesh.creation.icosphere(5)
    pos = torch.tensor(m.vertices, dtype=torch.float32)
    info = G.geodesic_nystrom_features(pos, torch.tensor(m.faces), k=4, num_landmarks=32,
                                       return_info=True)
    assert info.features.shape == (len(m.vertices), 4)
    assert info.features.dtype == torch.float32
    assert info.landmark_distances.shape == (32, len(m.vertices))
    assert torch.isfinite(info.features).all()


def test_heat_geodesic_landmarks():
    m = trimesh.creation.icosphere(3)
    info = G.geodesic_nystrom_features(m.vertices, m.faces, k=3, num_landmarks=20,
                                       geodesic="heat", return_info=True)
    u = m.vertices
    gc = np.arccos(np.clip(u[info.landmarks.numpy()] @ u.T, -1, 1))
    assert np.abs(info.landmark_distances.numpy() - gc).max() < 0.1


def test_geodesic_bad_input():
    pos, faces = G.grid_mesh(4, 4, dtype=D)
    with pytest.raises(ValueError, match="`sources`"):
        G.graph_geodesic_distances(pos, faces, [16])
    with pytest.raises(ValueError, match="`pos`.*one rest mesh"):
        G.heat_geodesic_distances(pos.expand(2, -1, -1), faces, [0])
    with pytest.raises(ValueError, match="`faces`"):
        G.graph_geodesic_distances(pos, faces + 1, [0])
    bad = pos.clone()
    bad[3, 2] = float("nan")
    with pytest.raises(ValueError, match="`pos`.*NaN"):
        G.geodesic_nystrom_features(bad, faces, k=2, num_landmarks=4)
    with pytest.raises(ValueError, match="`k`"):
        G.geodesic_nystrom_features(pos, faces, k=5, num_landmarks=4)
    with pytest.raises(ValueError, match="`num_samples`"):
        G.farthest_point_sampling(pos, faces, 17)
    with pytest.raises(ValueError, match="`geodesic`"):
        G.farthest_point_sampling(pos, faces, 3, geodesic="exact")
    with pytest.raises(ValueError, match="`sigma`"):
        G.geodesic_nystrom_features(pos, faces, k=2, num_landmarks=4, sigma=-1.0)
    with pytest.raises(TypeError, match="`pos`"):
        G.graph_geodesic_distances(np.zeros((16, 3), dtype=np.int64), faces, [0])
