"""Energy terms against analytic values and finite differences."""
import math

import pytest
import torch

from garmentgnn.body import CapsuleBodyModel
from garmentgnn.garments import make_garment
from garmentgnn.geometry import grid_mesh
from garmentgnn.physics import (MATERIALS, ClothRest, Material, bending_energy,
                                collision_energy, gravity_energy, inertia_energy, material,
                                shear_energy, stretch_energy, stvk_energy)

D = torch.float64


def sheet(n=5, size=1.0):
    pos, faces = grid_mesh(n, n, size=(size, size), dtype=D)
    # material coordinates = the sheet's own (x, y): u along x (warp), v along y (weft)
    return pos, faces, ClothRest.from_mesh(pos, faces, pos[faces][..., :2])


def apply(pos, M):
    """Affine map of the z=0 sheet: (x, y) -> M (x, y)."""
    return pos[:, :2] @ M.T


def test_rest_state_has_zero_membrane_and_bending_energy():
    pos, faces, rest = sheet()
    for f in (lambda p: stretch_energy(p, rest, 1e4), lambda p: shear_energy(p, rest, 1e4),
              lambda p: stvk_energy(p, rest, 1e4, 2e4), lambda p: bending_energy(p, rest, 1.0)):
        assert abs(float(f(pos))) < 1e-18


def test_uniform_stretch_and_shear_analytic():
    pos, faces, rest = sheet(size=2.0)
    area = 4.0
    s = 1.3  # stretch along u (x) by s: W^u = (s, 0, 0), W^v = (0, 1, 0)
    p = apply(pos, torch.tensor([[s, 0.0], [0.0, 1.0], [0.0, 0.0]], dtype=D))
    assert float(stretch_energy(p, rest, 10.0)) == pytest.approx(10.0 * area * (s - 1) ** 2)
    assert float(shear_energy(p, rest, 10.0)) == pytest.approx(0.0, abs=1e-12)
    g = (s * s - 1) / 2  # StVK: G = diag(g, 0)
    assert float(stvk_energy(p, rest, 3.0, 5.0)) == pytest.approx(
        area * (3.0 * g * g + 2.5 * g * g))
    gam = 0.2  # simple shear: W^u = (1, 0, 0), W^v = (gam, 1, 0)
    p = apply(pos, torch.tensor([[1.0, gam], [0.0, 1.0], [0.0, 0.0]], dtype=D))
    assert float(shear_energy(p, rest, 7.0)) == pytest.approx(7.0 * area * gam ** 2)
    assert float(stretch_energy(p, rest, 7.0)) == pytest.approx(
        7.0 * area * (math.sqrt(1 + gam ** 2) - 1) ** 2)
    # rigid motions cost nothing
    R = torch.tensor([[0.0, -1.0, 0.0], [0.6, 0.0, 0.8], [0.8, 0.0, -0.6]], dtype=D)
    p = pos @ R.T + torch.tensor([1.0, 2.0, 3.0], dtype=D)
    for f in (stretch_energy, shear_energy):
        assert float(f(p, rest, 1e5)) == pytest.approx(0.0, abs=1e-15)


def test_bending_hinge_analytic():
    # two right triangles sharing the edge (0,0,0)-(0,1,0), folded by angle phi
    phi = 0.4
    pos = torch.tensor([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]],
                       dtype=D)
    faces = torch.tensor([[0, 2, 1], [0, 1, 3]])
    rest = ClothRest.from_mesh(pos, faces)
    folded = pos.clone()
    folded[3] = torch.tensor([-math.cos(phi), 0.0, math.sin(phi)], dtype=D)
    A = 0.5 + 0.5  # both rest areas
    expected = 2.0 * 1.0 ** 2 / (4 * A) * phi ** 2 / 2
    assert float(bending_energy(folded, rest, 2.0)) == pytest.approx(expected, rel=1e-9)


def test_gravity_inertia_and_masses():
    pos, faces, rest = sheet(size=2.0)
    m = rest.vertex_masses(0.25, pos.size(0))
    assert float(m.sum()) == pytest.approx(0.25 * 4.0)
    lifted = pos + torch.tensor([0.0, 0.0, 0.5], dtype=D)
    # Eq. 11: raising the cloth by 0.5 m costs m g h
    dE = gravity_energy(lifted, m) - gravity_energy(pos, m)
    assert float(dE) == pytest.approx(1.0 * 9.81 * 0.5)
    x = lifted.clone().requires_grad_(True)
    inertia_energy(x, pos, m, dt=0.1).backward()
    torch.testing.assert_close(x.grad, m[:, None] * (lifted - pos) / 0.01)
    with pytest.raises(ValueError, match="dt"):
        inertia_energy(pos, pos, m, dt=0.0)


def test_collision_against_a_flat_body():
    # body: a large square at z = 0 facing +z; points at known heights
    body = torch.tensor([[-5.0, -5.0, 0.0], [5.0, -5.0, 0.0], [5.0, 5.0, 0.0], [-5.0, 5.0, 0.0],
                         [0.0, 0.0, -3.0]], dtype=D)
    body_faces = torch.tensor([[0, 1, 2], [0, 2, 3], [0, 4, 1], [1, 4, 2], [2, 4, 3], [3, 4, 0]])
    z = torch.tensor([0.01, 0.001, -0.002], dtype=D)
    pts = torch.stack([torch.zeros(3, dtype=D), torch.zeros(3, dtype=D), z], -1)
    pen = torch.relu(0.002 - z)
    e1 = collision_energy(pts, body, body_faces, margin=0.002, stiffness=1.5)
    assert float(e1) == pytest.approx(1.5 * float(pen.sum()))
    e3 = collision_energy(pts, body, body_faces, margin=0.002, stiffness=1e5, power=3)
    assert float(e3) == pytest.approx(1e5 * float((pen ** 3).sum()))


@pytest.mark.parametrize("term", ["stretch", "shear", "stvk", "bending"])
def test_gradcheck(term):
    pos, faces, rest = sheet(n=3)
    g = torch.Generator().manual_seed(0)
    x = (pos + 0.05 * torch.randn(pos.shape, generator=g, dtype=D)).requires_grad_(True)
    f = {"stretch": lambda p: stretch_energy(p, rest, 3.0),
         "shear": lambda p: shear_energy(p, rest, 3.0),
         "stvk": lambda p: stvk_energy(p, rest, 3.0, 2.0),
         "bending": lambda p: bending_energy(p, rest, 3.0)}[term]
    assert torch.autograd.gradcheck(f, (x,))


def test_batched_frames_and_garment_rest_is_stress_free():
    body = CapsuleBodyModel()("regular")
    g = make_garment("skirt", body, resolution="low")
    rest = ClothRest.from_mesh(g.vertices.double(), g.faces, g.face_uv.double())
    frames = g.vertices.double().expand(4, -1, -1)
    e = stretch_energy(frames, rest, 1e4)
    assert e.shape == (4,)
    # the templates' material coordinates are isometric to the rest shape
    assert float(e[0]) < 1e-3 * 1e4 * float(rest.uv_area.sum())
    torch.testing.assert_close(e, e[:1].expand(4))


def test_materials():
    assert set(MATERIALS) == {"silk", "cotton", "denim", "leather"}
    stiff = material("silk").scaled(1000)
    assert stiff.stretch == pytest.approx(1000 * MATERIALS["silk"].stretch)
    with pytest.raises(ValueError, match="material"):
        material("kevlar")
    with pytest.raises(ValueError, match="density"):
        Material(density=0.0, stretch=1, shear=1, bending=0, lame_mu=1, lame_lambda=0)
