"""Garments: the Garment container, procedural templates on capsule bodies, OBJ/PLY/GLB I/O.

Oracles are independent of the code under test: the analytic capsule distance of
``CapsuleBodyModel.capsules`` and a brute-force point-to-triangle distance for collisions,
trimesh for topology, deformation gradients computed here with numpy.
"""
import copy
import logging

import numpy as np
import pytest
import scipy.sparse as sp
import torch
import trimesh
from scipy.sparse.csgraph import connected_components
from scipy.spatial import ConvexHull

from garmentgnn.body.capsule import CapsuleBodyModel
from garmentgnn.garments import (Garment, dress, jumpsuit, load_garment, make_garment,
                                 save_garment, skirt, trousers, tshirt)

SHAPES = ("thin", "regular", "fat")
KINDS = ("skirt", "trousers", "dress", "tshirt", "jumpsuit")
#: openings of each template: skirt hem+waist, trousers waist+2 legs, dress (straps)
#: hem+neck+2 armholes, T-shirt hem+neck+2 sleeves, jumpsuit neck+2 sleeves+2 legs
OPENINGS = {"skirt": 2, "trousers": 3, "dress": 4, "tshirt": 4, "jumpsuit": 5}
MARGIN = 0.01
MODEL = CapsuleBodyModel()


@pytest.fixture(scope="module")
def bodies():
    return {s: MODEL(s) for s in SHAPES}


_CACHE = {}


@pytest.fixture(scope="module")
def garments(bodies):
    def get(kind, shape, **kw):
        key = (kind, shape, tuple(sorted(kw.items())))
        if key not in _CACHE:
            _CACHE[key] = make_garment(kind, bodies[shape], resolution="low", **kw)
        return _CACHE[key]
    return get


# -- oracles --------------------------------------------------------------------------
def capsule_distance(points, shape):
    """Analytic distance to the union of the body's capsules (negative inside)."""
    P = np.asarray(points, dtype=np.float64)
    out = np.full(len(P), np.inf)
    for _, s, e, r in MODEL.capsules(shape):
        s, e = s.double().numpy(), e.double().numpy()
        ab = e - s
        t = np.clip(((P - s) @ ab) / (ab @ ab), 0.0, 1.0)
        out = np.minimum(out, np.linalg.norm(P - (s + t[:, None] * ab), axis=1) - r)
    return out


def tessellation_depth(body, shape):
    """How far the body mesh's facets lie inside their analytic capsule (the mesh is
    inscribed): the garment is placed against the mesh, so the analytic oracle must
    allow this much.  The capsule body concatenates one equal-sized mesh per capsule."""
    V, F = body.vertices.double().numpy(), body.faces.numpy()
    caps = MODEL.capsules(shape)
    per = len(F) // len(caps)
    depth = 0.0
    for k, (_, s, e, r) in enumerate(caps):
        tri = V[F[k * per:(k + 1) * per]]
        pts = np.concatenate([tri.mean(1), 0.5 * (tri[:, 0] + tri[:, 1]),
                              0.5 * (tri[:, 1] + tri[:, 2]), 0.5 * (tri[:, 2] + tri[:, 0])])
        s, e = s.double().numpy(), e.double().numpy()
        t = np.clip(((pts - s) @ (e - s)) / ((e - s) @ (e - s)), 0.0, 1.0)
        d = np.linalg.norm(pts - (s + t[:, None] * (e - s)), axis=1) - r
        depth = max(depth, float(-d.min()))
    return depth


def mesh_distance(points, V, F):
    """Brute-force unsigned distance from points to a triangle mesh."""
    A, B, C = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    n = np.cross(B - A, C - A)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    out = []
    for p in points:
        d_plane = ((p - A) * n).sum(1)
        q = p - d_plane[:, None] * n
        # inside test with barycentric signs
        c0 = (np.cross(B - A, q - A) * n).sum(1)
        c1 = (np.cross(C - B, q - B) * n).sum(1)
        c2 = (np.cross(A - C, q - C) * n).sum(1)
        inside = (c0 >= 0) & (c1 >= 0) & (c2 >= 0)
        best = np.where(inside, np.abs(d_plane), np.inf)
        for a, b in ((A, B), (B, C), (C, A)):
            ab = b - a
            t = np.clip(((p - a) * ab).sum(1) / (ab * ab).sum(1), 0, 1)
            best = np.minimum(best, np.linalg.norm(p - (a + t[:, None] * ab), axis=1))
        out.append(best.min())
    return np.array(out)


def deformation_singular_values(V, F, uv_corners):
    """Singular values of (dp1 dp2)(du dv)^-1 per face (Eq. 14), numpy only."""
    P = V[F]
    Ds = np.stack([P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]], -1)  # [F, 3, 2]
    Dm = np.stack([uv_corners[:, 1] - uv_corners[:, 0], uv_corners[:, 2] - uv_corners[:, 0]], -1)
    return np.linalg.svd(Ds @ np.linalg.inv(Dm), compute_uv=False)


def boundary_loops(F):
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    u, c = np.unique(e, axis=0, return_counts=True)
    b = u[c == 1]
    if len(b) == 0:
        return 0
    n = F.max() + 1
    g = sp.coo_matrix((np.ones(len(b)), (b[:, 0], b[:, 1])), shape=(n, n))
    _, lab = connected_components(g, directed=False)
    return len(np.unique(lab[np.unique(b)]))


def uv_mismatch_across_edges(F, face_uv):
    """For every interior edge, how far the two faces' corner UVs at its ends disagree."""
    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    U = np.concatenate([face_uv[:, [0, 1]], face_uv[:, [1, 2]], face_uv[:, [2, 0]]])
    swap = E[:, 0] > E[:, 1]
    E = np.where(swap[:, None], E[:, ::-1], E)
    U = np.where(swap[:, None, None], U[:, ::-1], U)
    order = np.lexsort((E[:, 1], E[:, 0]))
    E, U = E[order], U[order]
    same = (E[1:] == E[:-1]).all(1)
    return np.abs(U[1:][same] - U[:-1][same]).max((1, 2))


# -- Garment container ----------------------------------------------------------------
def _tiny():
    V = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=torch.float32)
    F = torch.tensor([[0, 1, 2], [1, 3, 2]])
    return V, F, V[:, :2].clone()


def test_garment_defaults_and_rest_frame():
    V, F, uv = _tiny()
    g = Garment(V, F, uv, name="sheet")
    assert g.face_uv.shape == (2, 3, 2) and g.kind == "other"
    torch.testing.assert_close(g.face_uv, uv[F])
    Dinv, area = g.rest_frame()
    torch.testing.assert_close(area, torch.full((2,), 0.5))
    W = g.deformation_gradient(V * torch.tensor([2.0, 1.0, 1.0]))
    torch.testing.assert_close(W[:, :, 0].norm(dim=-1), torch.full((2,), 2.0))
    coords, uvf = g.uv_layout()
    assert coords.shape == (4, 2) and uvf.shape == (2, 3)


@pytest.mark.parametrize("bad, match", [
    (dict(vertices=torch.zeros(0, 3)), "non-empty"),
    (dict(faces=torch.zeros(0, 3, dtype=torch.long)), "non-empty"),
    (dict(faces=torch.tensor([[0, 1, 7]])), "outside"),
    (dict(vertices=torch.tensor([[0, 0, 0], [1, 0, 0], [0, float("nan"), 0], [1, 1, 0.0]])), "NaN"),
    (dict(uv=torch.zeros(3, 2)), "uv"),
    (dict(face_uv=torch.zeros(2, 3, 3)), "face_uv"),
    (dict(kind="hat"), "kind"),
    (dict(pinned=torch.zeros(3, dtype=torch.bool)), "pinned"),
])
def test_garment_validation(bad, match):
    V, F, uv = _tiny()
    args = dict(vertices=V, faces=F, uv=uv)
    args.update(bad)
    with pytest.raises(ValueError, match=match):
        Garment(**args)


# -- templates: topology ---------------------------------------------------------------
@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("kind", KINDS)
def test_template_is_one_oriented_manifold(garments, kind, shape):
    g = garments(kind, shape)
    V, F = g.vertices.double().numpy(), g.faces.numpy()
    m = trimesh.Trimesh(V, F, process=False)
    e = np.sort(m.edges, axis=1)
    _, cnt = np.unique(e, axis=0, return_counts=True)
    assert cnt.max() <= 2, "an edge shared by more than two faces"
    assert m.is_winding_consistent
    assert len(m.split(only_watertight=False)) == 1
    assert len(np.unique(np.sort(F, 1), axis=0)) == len(F)
    assert (m.area_faces > 1e-10).all(), "degenerate face"
    assert np.unique(F).size == len(V), "unreferenced vertex"
    # a sphere with holes: Euler characteristic 2 - openings, each opening one loop
    assert boundary_loops(F) == OPENINGS[kind]
    assert m.euler_number == 2 - OPENINGS[kind]
    assert g.kind == kind


@pytest.mark.parametrize("kind", KINDS)
def test_template_normals_point_away_from_the_body(garments, kind):
    g = garments(kind, "regular")
    V, F = g.vertices.double().numpy(), g.faces.numpy()
    c = V[F].mean(1)
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    # outward = away from the closest capsule axis point
    best, away = np.full(len(c), np.inf), np.zeros_like(c)
    for _, s, e, r in MODEL.capsules("regular"):
        s, e = s.double().numpy(), e.double().numpy()
        t = np.clip(((c - s) @ (e - s)) / ((e - s) @ (e - s)), 0, 1)
        q = s + t[:, None] * (e - s)
        d = np.linalg.norm(c - q, axis=1) - r
        m = d < best
        best[m], away[m] = d[m], (c - q)[m]
    frac = np.mean((n * away).sum(1) > 0)
    assert frac > 0.9, frac


# -- templates: placement --------------------------------------------------------------
@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("kind", KINDS)
def test_template_is_outside_the_body_by_the_margin(garments, bodies, kind, shape):
    g = garments(kind, shape)
    V = g.vertices.double().numpy()
    d = capsule_distance(V, shape)
    depth = tessellation_depth(bodies[shape], shape)
    assert depth < 0.012  # sanity: the tolerance below is the facets' sagitta, no more
    assert d.min() >= MARGIN - depth - 1e-5, (d.min(), depth)
    # against the mesh itself (what the template promises): exact, for the closest ones
    body = bodies[shape]
    closest = np.argsort(d)[:40]
    dm = mesh_distance(V[closest], body.vertices.double().numpy(), body.faces.numpy())
    assert dm.min() >= MARGIN - 1e-5, dm.min()


def test_margin_and_ease_are_respected(bodies):
    g = skirt(bodies["regular"], resolution="low", ease=0.05, margin=0.03)
    assert capsule_distance(g.vertices.double().numpy(), "regular").min() >= 0.03 - 0.007
    loose = skirt(bodies["regular"], resolution="low", ease=0.05)
    tight = skirt(bodies["regular"], resolution="low", ease=0.015)
    assert (_band_perimeter(loose, loose.info["waist_z"])
            > _band_perimeter(tight, tight.info["waist_z"]) + 0.1)


# -- templates: material coordinates ---------------------------------------------------
@pytest.mark.parametrize("kind", KINDS)
def test_rest_stretch_and_shear_are_zero(garments, kind):
    """Eq. 14 with face_uv: the rest deformation gradient is a rotation on every face."""
    for shape in ("thin", "fat"):
        g = garments(kind, shape)
        sv = deformation_singular_values(g.vertices.double().numpy(), g.faces.numpy(),
                                         g.face_uv.double().numpy())
        assert np.abs(sv - 1).max() < 2e-3
        # orientation: UV triangles are counter-clockwise like the faces (det > 0)
        fu = g.face_uv.double().numpy()
        d1, d2 = fu[:, 1] - fu[:, 0], fu[:, 2] - fu[:, 0]
        assert (d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0] > 0).all()


@pytest.mark.parametrize("flare", ["pencil", "a-line", "full"])
def test_skirt_pattern_is_the_unrolled_cone(garments, flare):
    """A skirt is a stack of cones: its pattern is continuous (face_uv agrees across
    every edge but the centre-back cut) and the per-vertex pattern is isometric."""
    g = garments("skirt", "regular", flare=flare)
    F, fu = g.faces.numpy(), g.face_uv.double().numpy()
    mism = uv_mismatch_across_edges(F, fu)
    rows = len(np.unique(np.round(g.vertices[:, 2].numpy(), 5)))
    ring = int(g.pinned.sum())  # vertices per ring (the waistband is pinned)
    panels = len(torch.unique(g.panel))  # yoke above the hips (if any) and skirt
    assert 1 <= panels <= 3
    seams = (mism > 1e-4).sum()
    # the centre-back cut (one edge per strip) and the rings between panels, nothing else
    expected = (rows - 1) + (panels - 1) * ring
    assert expected - 2 <= seams <= expected + 2, (seams, expected)
    assert np.percentile(mism, 90) < 3e-5  # elsewhere continuous (float32 UVs)
    V, uv = g.vertices.double().numpy(), g.uv.double().numpy()
    off_seam = np.abs(uv[F] - fu).max((1, 2)) < 3e-5
    assert off_seam.mean() > 0.8
    sv = deformation_singular_values(V, F[off_seam], uv[F][off_seam])
    assert np.abs(sv - 1).max() < 1e-3  # the per-vertex pattern is isometric too


@pytest.mark.parametrize("kind", KINDS)
def test_pattern_is_mostly_continuous(garments, kind):
    """face_uv is a sewing pattern, not a soup of triangles: across most interior edges
    both faces agree on the UV of the shared corners."""
    g = garments(kind, "regular")
    mism = uv_mismatch_across_edges(g.faces.numpy(), g.face_uv.double().numpy())
    assert np.mean(mism < 5e-3) > 0.8


def test_pinned_waistband(garments):
    for kind in ("skirt", "trousers"):
        g = garments(kind, "regular")
        z = g.vertices[:, 2]
        assert g.pinned is not None and int(g.pinned.sum()) >= 8
        assert torch.allclose(z[g.pinned], z[g.pinned].max().expand(int(g.pinned.sum())), atol=1e-5)
        assert float(z[g.pinned].max()) == pytest.approx(float(z.max()), abs=1e-4)


# -- templates: sizing -----------------------------------------------------------------
def _band_perimeter(g, z, half=0.012):
    V = g.vertices.double().numpy()
    m = np.abs(V[:, 2] - z) <= half
    hull = trimesh.convex.convex_hull(np.concatenate([V[m], V[m] + [0, 0, 1e-3]]))
    xy = hull.vertices[:, :2]
    h = ConvexHull(xy)
    return h.area  # perimeter in 2D


@pytest.mark.parametrize("kind, height", [("skirt", "waist_z"), ("trousers", "waist_z"),
                                          ("tshirt", "armpit_z"), ("dress", "waist_z")])
def test_fatter_body_gets_a_larger_garment(garments, kind, height):
    per = []
    for shape in SHAPES:
        g = garments(kind, shape)
        per.append(_band_perimeter(g, g.info[height] - 0.03))
    assert per[0] < per[1] < per[2], per


def test_resolution_sets_the_vertex_count(bodies):
    low = skirt(bodies["regular"], resolution="low")
    med = skirt(bodies["regular"], resolution="medium")
    assert 700 <= low.num_vertices <= 1400
    assert 3200 <= med.num_vertices <= 5000
    n = skirt(bodies["regular"], resolution=2000).num_vertices
    assert 1600 <= n <= 2500
    high = tshirt(bodies["regular"], resolution="high")
    assert high.num_vertices >= 14000
    assert high.num_vertices < 20000
    sv = deformation_singular_values(high.vertices.double().numpy(), high.faces.numpy(),
                                     high.face_uv.double().numpy())
    assert np.abs(sv - 1).max() < 2e-3
    assert capsule_distance(high.vertices.double().numpy(), "regular").min() > 0


def test_lengths_flares_and_options(garments, bodies):
    hems = [garments("skirt", "regular", length=L).vertices[:, 2].min().item()
            for L in ("mini", "knee", "midi", "long")]
    assert hems == sorted(hems, reverse=True)
    metres = garments("skirt", "regular", length=0.3)
    assert metres.info["waist_z"] - metres.info["hem_z"] == pytest.approx(0.3)
    hem = {f: _band_perimeter(garments("skirt", "regular", flare=f),
                              garments("skirt", "regular", flare=f).info["hem_z"] + 0.01)
           for f in ("pencil", "a-line", "full")}
    assert hem["pencil"] < hem["a-line"] < hem["full"]
    shorts = garments("trousers", "regular", length="shorts")
    assert shorts.vertices[:, 2].min() > garments("trousers", "regular").vertices[:, 2].min() + 0.3
    long_sleeves = garments("tshirt", "regular", sleeves="long")
    short = garments("tshirt", "regular")
    assert long_sleeves.vertices[:, 0].abs().max() > short.vertices[:, 0].abs().max() + 0.03
    tank = garments("tshirt", "regular", sleeves="none")
    assert boundary_loops(tank.faces.numpy()) == 4
    assert tank.vertices[:, 0].abs().max() < short.vertices[:, 0].abs().max() - 0.05
    for top in ("strapless", "sleeveless"):
        d = garments("dress", "regular", top=top)
        assert boundary_loops(d.faces.numpy()) == {"strapless": 2, "sleeveless": 4}[top]
        sv = deformation_singular_values(d.vertices.double().numpy(), d.faces.numpy(),
                                         d.face_uv.double().numpy())
        assert np.abs(sv - 1).max() < 2e-3


@pytest.mark.parametrize("fn, kwargs, match", [
    (skirt, dict(length="ankle-ish"), "length"),
    (skirt, dict(length=-1.0), "length"),
    (skirt, dict(flare="huge"), "flare"),
    (skirt, dict(flare=-0.1), "flare"),
    (skirt, dict(resolution="ultra"), "resolution"),
    (skirt, dict(resolution=10), "resolution"),
    (skirt, dict(ease=-0.01), "ease"),
    (trousers, dict(margin=float("nan")), "margin"),
    (tshirt, dict(sleeves="puffy"), "sleeves"),
    (tshirt, dict(neckline="v"), "neckline"),
    (dress, dict(top="halter"), "top"),
    (dress, dict(top="straps", sleeves="short"), "sleeves"),
    (jumpsuit, dict(length="ankle-ish"), "length"),
])
def test_template_arguments_are_checked(bodies, fn, kwargs, match):
    with pytest.raises(ValueError, match=match):
        fn(bodies["regular"], **kwargs)


def test_body_without_roles_is_rejected(bodies):
    b = copy.copy(bodies["regular"])
    sk = copy.copy(b.skeleton)
    sk.roles = {k: v for k, v in sk.roles.items() if k != "l_knee"}
    b.skeleton = sk
    with pytest.raises(ValueError, match="l_knee"):
        skirt(b, resolution="low")
    with pytest.raises(ValueError, match="kind"):
        make_garment("hat", bodies["regular"])


# -- I/O ----------------------------------------------------------------------------------
def test_obj_round_trip(garments, tmp_path):
    g = garments("skirt", "thin")
    p = save_garment(tmp_path / "skirt.obj", g)
    h = load_garment(p)
    torch.testing.assert_close(h.vertices, g.vertices, atol=1e-6, rtol=0)
    assert torch.equal(h.faces, g.faces)
    torch.testing.assert_close(h.face_uv, g.face_uv, atol=1e-6, rtol=0)
    torch.testing.assert_close(h.uv, g.uv, atol=1e-6, rtol=0)
    assert h.kind == "skirt" and h.name == g.name and h.info["uv"] == "file"
    assert torch.equal(h.pinned, g.pinned)
    # the OBJ shares vt between corners that agree (the skirt's pattern is continuous)
    vt = sum(1 for line in p.read_text().splitlines() if line.startswith("vt "))
    assert vt < 0.6 * 3 * g.num_faces
    with pytest.raises(ValueError, match="OBJ"):
        save_garment(tmp_path / "skirt.ply", g)


def _write_obj(path, V, F, vt=None, ft=None, extra=""):
    lines = [f"v {x} {y} {z}" for x, y, z in V]
    if vt is not None:
        lines += [f"vt {u} {v}" for u, v in vt]
        lines += [f"f {a + 1}/{ta + 1} {b + 1}/{tb + 1} {c + 1}/{tc + 1}"
                  for (a, b, c), (ta, tb, tc) in zip(F, ft)]
    else:
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in F]
    path.write_text("\n".join(lines) + "\n" + extra)
    return path


def _sheet(n=4):
    V, F = [], []
    for i in range(n):
        for j in range(n):
            V.append((0.1 * i, 0.0, 0.1 * j + 1.0))
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
            F += [(a, b, c), (a, c, d)]
    return np.array(V), np.array(F)


@pytest.mark.parametrize("problem, match", [
    ("nonmanifold", "non-manifold"),
    ("degenerate", "degenerate"),
    ("duplicate", "duplicate"),
    ("nan", "NaN"),
    ("range", "out of range"),
    ("empty", "empty"),
    ("corrupt", "cannot parse"),
    ("binary", "cannot parse"),
    ("badtex", "texture vertex"),
])
def test_loader_rejects_bad_meshes(tmp_path, problem, match):
    V, F = _sheet()
    path = tmp_path / f"{problem}.obj"
    if problem == "nonmanifold":
        V = np.concatenate([V, [[0.05, 0.1, 1.05]]])
        F = np.concatenate([F, [[0, 5, len(V) - 1]]])  # a third face on interior edge 0-5
        _write_obj(path, V, F)
    elif problem == "degenerate":
        V = np.concatenate([V, [[0.05, 0.0, 1.0]]])  # on the segment 0-4 (collinear)
        F = np.concatenate([F, [[0, len(V) - 1, 4]]])
        _write_obj(path, V, F)
    elif problem == "duplicate":
        _write_obj(path, V, np.concatenate([F, F[3:4, [1, 2, 0]]]))
    elif problem == "nan":
        V = V.copy()
        V[5, 1] = np.nan
        _write_obj(path, V, F)
    elif problem == "range":
        _write_obj(path, V, np.concatenate([F, [[0, 1, 99]]]))
    elif problem == "empty":
        path.write_text("# nothing here\n")
    elif problem == "corrupt":
        path.write_text("v 0 0 0\nv 1 0 zero\nf 1 2 3\n")
    elif problem == "binary":
        path.write_bytes(bytes(range(256)) * 4)
    elif problem == "badtex":
        ft = F.copy()
        ft[0, 0] = 40
        _write_obj(path, V, F, vt=V[:, [0, 2]], ft=ft)
    with pytest.raises(ValueError, match=match) as err:
        load_garment(path)
    assert path.name in str(err.value)


def test_loader_rejects_other_formats_and_missing_files(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_garment(tmp_path / "nope.obj")
    bad = tmp_path / "broken.ply"
    bad.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n")
    with pytest.raises(ValueError, match="broken.ply"):
        load_garment(bad)
    with pytest.raises(ValueError, match="uv_fallback"):
        load_garment(bad, uv_fallback="magic")


def test_repair_fixes_duplicate_and_degenerate_faces(tmp_path, caplog):
    V, F = _sheet()
    nV = len(V)
    V = np.concatenate([V, [[0.05, 0.0, 1.0]], V[4:5] + 1e-12, [[5.0, 5.0, 5.0]]])
    F = np.concatenate([F,
                        F[2:3, [2, 0, 1]],          # duplicate face (rotated)
                        [[0, nV, 4]],               # degenerate: collinear vertices
                        [[3, 3, 7]],                # degenerate: repeated index
                        ])
    F[0] = np.where(F[0] == 4, nV + 1, F[0])  # uses a near-duplicate of vertex 4
    path = _write_obj(tmp_path / "messy.obj", V, F)
    with pytest.raises(ValueError, match="degenerate"):
        load_garment(path)
    with caplog.at_level(logging.INFO, logger="garmentgnn.garments.io"):
        g = load_garment(path, repair=True)
    rep = g.info["repair"]
    assert rep["duplicate_faces"] == 1
    assert rep["degenerate_faces"] == 2
    assert rep["merged_vertices"] == 1
    assert rep["unreferenced_vertices"] == 2  # the collinear helper and the far vertex
    assert g.num_vertices == 16 and g.num_faces == 18
    assert "repaired" in caplog.text
    m = trimesh.Trimesh(g.vertices.numpy(), g.faces.numpy(), process=False)
    assert m.is_winding_consistent and len(m.split(only_watertight=False)) == 1
    # NaN coordinates: fatal on a used vertex, dropped with repair on an unused one
    Vb = np.concatenate([_sheet()[0], [[np.nan, 0.0, 0.0]]])
    nan_path = _write_obj(tmp_path / "nan.obj", Vb, _sheet()[1])
    with pytest.raises(ValueError, match="NaN"):
        load_garment(nan_path)
    assert load_garment(nan_path, repair=True).info["repair"]["unreferenced_vertices"] == 1
    Fb = np.concatenate([_sheet()[1], [[0, 1, 16]]])
    with pytest.raises(ValueError, match="NaN"):
        load_garment(_write_obj(tmp_path / "nan2.obj", Vb, Fb), repair=True)
    # non-manifold edges are never "repaired"
    Vn = np.concatenate([_sheet()[0], [[0.05, 0.1, 1.05]]])
    Fn = np.concatenate([_sheet()[1], [[0, 5, 16]]])
    with pytest.raises(ValueError, match="non-manifold"):
        load_garment(_write_obj(tmp_path / "nm.obj", Vn, Fn), repair=True)


def test_uv_fallback_is_isometric(tmp_path):
    V, F = _sheet()
    V = V + np.array([0.0, 1.0, 0.0]) * (V[:, :1] ** 2)  # bend it
    path = _write_obj(tmp_path / "plain.obj", V, F)
    g = load_garment(path)
    assert g.info["uv"] == "isometric"
    sv = deformation_singular_values(g.vertices.double().numpy(), g.faces.numpy(),
                                     g.face_uv.double().numpy())
    assert np.abs(sv - 1).max() < 1e-5
    planar = load_garment(path, uv_fallback="planar")
    sv = deformation_singular_values(planar.vertices.double().numpy(), planar.faces.numpy(),
                                     planar.face_uv.double().numpy())
    assert np.abs(sv - 1).max() > 0.05  # a projection is not isometric on a bent sheet
    with pytest.raises(ValueError, match="no UV"):
        load_garment(path, uv_fallback="error")


def test_obj_uvs_per_corner_and_unit_scaling(tmp_path):
    V, F = _sheet()
    # a texture atlas in [0, 1]: 0.3 m sheet -> UVs 0..1 (scaled by 1/0.3)
    vt = V[:, [0, 2]] / 0.3
    vt[:, 1] -= vt[:, 1].min()
    g = load_garment(_write_obj(tmp_path / "tex.obj", V, F, vt=vt, ft=F))
    assert g.info["uv_scale"] == pytest.approx(0.3, rel=1e-6)
    sv = deformation_singular_values(g.vertices.double().numpy(), g.faces.numpy(),
                                     g.face_uv.double().numpy())
    assert np.abs(sv - 1).max() < 1e-5
    raw = load_garment(tmp_path / "tex.obj", uv_scale=None)
    assert "uv_scale" not in raw.info
    # per-corner UVs: a seam (two vt for one vertex) survives
    ft = F.copy()
    vt2 = np.concatenate([vt, vt[5:6] + 0.5])
    ft[0] = np.where(F[0] == 5, len(vt), F[0])
    seam = load_garment(_write_obj(tmp_path / "seam.obj", V, F, vt=vt2, ft=ft), uv_scale=None)
    corners = seam.face_uv[(seam.faces == 5).any(1)]
    assert len(torch.unique(corners.reshape(-1, 2), dim=0)) > 1 + 5  # two UV copies of v5


def test_glb_and_ply_with_uv_seams_are_welded(tmp_path):
    """Formats with per-vertex UVs duplicate vertices along UV seams; the loader welds
    them back into one manifold tube and keeps each corner's UV."""
    n, rows = 12, 5
    ang = np.linspace(0, 2 * np.pi, n + 1)  # n+1 columns: the last duplicates the first
    V, uv = [], []
    for j in range(rows):
        for i in range(n + 1):
            V.append((0.1 * np.cos(ang[i]), 0.1 * np.sin(ang[i]), 0.05 * j))
            uv.append((0.1 * ang[i], 0.05 * j))
    V, uv = np.array(V), np.array(uv)
    F = []
    for j in range(rows - 1):
        for i in range(n):
            a, b = j * (n + 1) + i, j * (n + 1) + i + 1
            c, d = b + n + 1, a + n + 1
            F += [(a, b, c), (a, c, d)]
    F = np.array(F)
    mesh = trimesh.Trimesh(V, F, process=False,
                           visual=trimesh.visual.TextureVisuals(uv=uv))
    for ext in ("glb", "ply"):
        path = tmp_path / f"tube.{ext}"
        mesh.export(path)
        g = load_garment(path, uv_scale=None)
        assert g.num_vertices == n * rows, ext  # seam duplicates welded
        m = trimesh.Trimesh(g.vertices.numpy(), g.faces.numpy(), process=False)
        assert boundary_loops(g.faces.numpy()) == 2 and m.is_winding_consistent
        if g.info["uv"] == "file":  # UVs survived the format round trip
            sv = deformation_singular_values(g.vertices.double().numpy(), g.faces.numpy(),
                                             g.face_uv.double().numpy())
            assert np.abs(sv - 1).max() < 0.02  # chords vs arcs of a 12-gon
