"""The public Python API under odd shapes, dtypes, NaN/inf, empty and huge inputs."""
import math

import numpy as np
import torch
import trimesh
from hypothesis import given
from hypothesis import strategies as st

from garmentgnn.body.body import Body
from garmentgnn.body.skeleton import Skeleton
from garmentgnn.data import export
from garmentgnn.garments.garment import Garment
from garmentgnn.geometry import (edge_features, faces_to_edge_index, grid_mesh,
                                 penetration_depth, signed_distance, vertex_normals)
from garmentgnn.motion.sequence import Motion, match_joints
from garmentgnn.nn import LAYERS
from garmentgnn.physics import material
from garmentgnn.sim import SimSettings, simulate

from _fuzz import FUZZ, outcome

SPECIAL = st.sampled_from([0.0, -0.0, 1.0, -1.0, 1e-30, 1e30, 1e20, float("nan"),
                           float("inf"), -float("inf")])
DTYPES = st.sampled_from([torch.float32, torch.float64, torch.float16, torch.int64,
                          torch.bool, torch.complex64])


@st.composite
def tensors(draw, shape=None, max_len=6):
    """A tensor of a drawn (or given) shape and dtype, random values with some special
    ones (NaN, inf, huge) injected."""
    if shape is None:
        shape = tuple(draw(st.lists(st.integers(0, max_len), min_size=0, max_size=3)))
    dtype = draw(DTYPES)
    n = int(np.prod(shape)) if shape else 1
    vals = draw(st.lists(st.floats(-2, 2, allow_nan=False), min_size=n, max_size=n))
    t = torch.tensor(vals, dtype=torch.float64).reshape(shape)
    for _ in range(draw(st.integers(0, 2))):
        if n:
            t.view(-1)[draw(st.integers(0, n - 1))] = draw(SPECIAL)
    if dtype.is_complex:
        return t.to(dtype)
    if not dtype.is_floating_point:
        return torch.nan_to_num(t, 0.0, 0.0, 0.0).clamp(-5, 5).to(dtype)
    return t.to(dtype)


def finite_in(*ts):
    return all(torch.isfinite(t).all() for t in ts if t.is_floating_point())


@st.composite
def point_sets(draw):
    """Either well-formed [V, 3] float points or anything else."""
    if draw(st.booleans()):
        return draw(tensors(shape=(draw(st.integers(0, 8)), 3)))
    return draw(tensors())


BODY_POS, BODY_FACES = grid_mesh(3, 3, (0.5, 0.5), dtype=torch.float64)


@st.composite
def face_sets(draw):
    """The 3x3 grid's faces, maybe with one index or the dtype changed, or anything."""
    kind = draw(st.sampled_from(["valid", "index", "dtype", "random"]))
    f = BODY_FACES.clone()
    if kind == "index":
        f[draw(st.integers(0, len(f) - 1)), draw(st.integers(0, 2))] = draw(
            st.sampled_from([-1, 9, 2 ** 40]))
    elif kind == "dtype":
        f = f.to(draw(st.sampled_from([torch.int32, torch.int16, torch.uint8, torch.float32])))
    elif kind == "random":
        f = draw(tensors(max_len=4))
    return f


@st.composite
def grid_points(draw):
    """The grid's 9 vertices (dtype, NaN/inf drawn), or any point set."""
    if draw(st.booleans()):
        return draw(tensors(shape=(9, 3)))
    return draw(point_sets())


@FUZZ
@given(points=point_sets(), faces=face_sets())
def test_signed_distance_and_penetration(points, faces):
    for name, fn in (("signed_distance", signed_distance), ("penetration_depth",
                                                              penetration_depth)):
        res = outcome(f"geometry.{name}", fn, points, BODY_POS.to(points.dtype)
                      if points.is_floating_point() else BODY_POS, faces)
        if res is None:
            continue
        d = res.distance if name == "signed_distance" else res
        assert d.shape[-1] == points.shape[-2]
        if finite_in(points):
            assert torch.isfinite(d).all(), f"{name}: NaN from finite input"
            if name == "penetration_depth":
                assert (d >= 0).all()


@FUZZ
@given(faces=face_sets(), num_nodes=st.one_of(st.none(), st.integers(-2, 12),
                                              st.sampled_from([9, 9.0, True])))
def test_faces_to_edge_index(faces, num_nodes):
    ei = outcome("geometry.faces_to_edge_index", faces_to_edge_index, faces, num_nodes)
    if ei is not None:
        assert ei.dim() == 2 and ei.shape[0] == 2 and ei.dtype == torch.long
        if ei.numel():
            # oracle: every face edge in both directions, nothing else
            f = faces.long()
            want = {(int(a), int(b)) for tri in f.tolist() for a, b in
                    ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0]))}
            want |= {(b, a) for a, b in want}
            assert set(map(tuple, ei.t().tolist())) == want


@FUZZ
@given(pos=grid_points(), faces=face_sets())
def test_normals_and_edge_features(pos, faces):
    n = outcome("geometry.vertex_normals", vertex_normals, pos, faces)
    if n is not None and finite_in(pos):
        assert torch.isfinite(n).all()
    ei = faces_to_edge_index(BODY_FACES, 9)
    if pos.dim() == 2 and pos.shape[0] == 9:
        f = outcome("geometry.edge_features", edge_features, pos, ei)
        if f is not None and finite_in(pos):
            assert torch.isfinite(f).all()


@FUZZ
@given(rot=tensors(), tr=tensors(), names=st.lists(st.text(max_size=3), max_size=4),
       fps=st.one_of(SPECIAL, st.integers(-3, 120)))
def test_motion_construction(rot, tr, names, fps):
    m = outcome("motion.Motion", Motion, rot, tr, names, fps)
    if m is not None:
        assert torch.isfinite(m.rotations).all() and m.fps > 0
        r = outcome("motion.Motion.resample", m.resample, 24.0)
        if r is not None:
            assert torch.isfinite(r.rotations).all()


@FUZZ
@given(order=st.permutations(["a", "b", "c"]), extra=st.lists(st.sampled_from(["a", "x", "b"]),
                                                              max_size=2))
def test_match_joints_by_name(order, extra):
    names = list(order) + list(extra)
    rot = torch.arange(len(names) * 3, dtype=torch.float32).view(1, -1, 3) / 10
    m = outcome("motion.Motion", Motion, rot, torch.zeros(1, 3), names)
    if m is None:
        return
    out = outcome("motion.match_joints", match_joints, m, ["a", "b", "c"])
    if out is not None:  # oracle: each joint's rotation is the one stored under its name
        for k, n in enumerate("abc"):
            assert torch.equal(out[0, k], rot[0, names.index(n)])


SETTINGS = {"fps": SPECIAL, "substeps": st.integers(-2, 5), "max_newton": st.integers(-1, 3),
            "tol": SPECIAL, "membrane": st.sampled_from(["stvk", "x", ""]),
            "max_refinements": st.integers(-2, 3), "contact_radius": SPECIAL,
            "max_penetration": SPECIAL, "distance_candidates": st.one_of(st.none(),
                                                                         st.integers(-1, 9)),
            "gravity": st.sampled_from([(0, 0, -9.81), (0, 0), (float("nan"), 0, 0)]),
            "line_search_steps": st.integers(-1, 4), "collision_power": st.integers(1, 4)}


@FUZZ
@given(kw=st.fixed_dictionaries({}, optional=SETTINGS))
def test_sim_settings(kw):
    s = outcome("sim.SimSettings", SimSettings, **kw)
    if s is not None:
        assert s.fps > 0 and math.isfinite(s.fps) and s.max_refinements >= 0
        assert s.max_penetration > 0 and s.contact_radius >= 0 and s.substeps >= 1


@FUZZ
@given(P=st.one_of(tensors(shape=(2, 3, 3)), tensors()), start=SPECIAL)
def test_write_pc2(tmp_path_factory, P, start):
    p = tmp_path_factory.mktemp("pc2") / "x.pc2"
    out = outcome("data.write_pc2", export.write_pc2, p, P.numpy() if not P.is_complex()
                  else P, start_frame=start)
    if out is not None:  # oracle: an independent reader of the documented layout
        raw = p.read_bytes()
        sig, ver, n, sf, sr, ns = export.PC2_HEADER.unpack(raw[:export.PC2_HEADER.size])
        assert sig == b"POINTCACHE2\0" and (ns, n) == tuple(P.shape[:2])
        data = np.frombuffer(raw[export.PC2_HEADER.size:], "<f4").reshape(ns, n, 3)
        assert np.array_equal(data, P.numpy().astype("<f4")) and np.isfinite(data).all()


@FUZZ
@given(scale=st.sampled_from([1e-3, 1.0, 10.0, 1000.0]),
       offset=st.sampled_from([0.0, 0.3, 10.0]), special=st.one_of(st.none(), SPECIAL),
       frames=st.integers(0, 3), fps=st.sampled_from([30.0, 24.0]),
       names=st.sampled_from([["root"], ["Root"], ["root", "x"]]),
       body=st.booleans(), bad_face=st.booleans())
def test_simulate_odd_garments(scale, offset, special, frames, fps, names, body, bad_face):
    pos, faces = grid_mesh(3, 3, (0.2, 0.2), dtype=torch.float32)
    uv = pos[:, :2].clone()
    pos = (pos + torch.tensor([-0.1, -0.1, 0.16])) * scale + torch.tensor([offset, 0.0, 0.0])
    if special is not None:
        pos[4, 2] = special
    if bad_face:
        faces = faces.clone()
        faces[0, 0] = 99
    g = outcome("sim.simulate (garment)", Garment, pos, faces, uv)
    if g is None:
        return
    ico = trimesh.creation.icosphere(subdivisions=1, radius=0.15)
    v = torch.tensor(ico.vertices, dtype=torch.float32)
    b = Body(v, torch.tensor(ico.faces), Skeleton(["root"], torch.tensor([-1])),
             torch.zeros(1, 3), torch.ones(len(v), 1)) if body else None
    S = len(names)
    m = outcome("sim.simulate (motion)", Motion, torch.zeros(frames, S, 3),
                torch.zeros(frames, 3), names, fps)
    if m is None:
        return
    res = outcome("sim.simulate", simulate, g, b, m, material("silk"))
    if res is not None:
        assert res.positions.shape == (frames, 9, 3) or not res.ok
        assert torch.isfinite(res.positions).all()
        assert res.penetration.shape[0] == res.positions.shape[0]


# ------------------------------------------------------------------ layers
LAYER_NAMES = st.sampled_from(["sat", "gt", "gt_edge", "structure_aware", "gat"])


@FUZZ
@given(name=LAYER_NAMES, nodes=st.integers(0, 6), width=st.sampled_from([8, 7, 9]),
       edges=st.lists(st.tuples(st.integers(-2, 7), st.integers(-2, 7)), max_size=10),
       x_dtype=DTYPES, e_dtype=DTYPES, e_width=st.sampled_from([3, 2]),
       validate=st.booleans(), special=st.booleans(), valid=st.booleans(), data=st.data())
def test_fuzz_layers(name, nodes, width, edges, x_dtype, e_dtype, e_width, validate, special,
                     valid, data):
    """Every layer of ``garmentgnn.nn`` (built for 8 input and 3 edge columns, float32)
    with node and edge features of any dtype and width, indices from -2 to 7 (on 0-6
    nodes), ``validate`` on or off, and NaN / inf / 1e30 values: a clear error naming the
    argument, or (finite, in-range, float32 inputs of the built widths) a finite output
    of shape ``[nodes, 8]`` -- never a crash or torch's own message."""
    if valid:  # half the cases well-formed, so the oracle of the results is exercised
        x_dtype = e_dtype = torch.float32
        width, e_width = 8, 3
        edges = [(a % nodes, b % nodes) for a, b in edges] if nodes else []
    torch.manual_seed(0)
    layer = LAYERS[name](8, 4, 2, edge_dim=3, validate=validate)
    x = data.draw(tensors(shape=(nodes, width))).to(x_dtype) if special else \
        torch.randn(nodes, width).to(x_dtype)
    ei = torch.tensor(edges, dtype=torch.long).reshape(-1, 2).t().contiguous()
    e = torch.randn(ei.size(1), e_width).to(e_dtype)
    out = outcome("nn layers", layer, x, ei, e)
    if out is not None:
        assert x_dtype == e_dtype == torch.float32 and width == 8 and e_width == 3
        assert ei.numel() == 0 or (0 <= int(ei.min()) and int(ei.max()) < nodes)
        assert out.shape == (nodes, 8) and torch.isfinite(out).all()
