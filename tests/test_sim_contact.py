"""Rigid colliders and Coulomb friction of the reference simulator, against analytic
answers: a patch on an inclined plane sticks for mu > tan(theta) and slides with
acceleration g (sin(theta) - mu cos(theta)) otherwise; friction on a flat floor only
removes kinetic energy and stops a sliding patch after v0^2 / (2 mu g); a sheet dropped
on a sphere comes to rest outside it; a rotated scene gives the rotated answer."""
import math
from dataclasses import replace

import pytest
import torch

from garmentgnn.garments import Garment
from garmentgnn.geometry import (axis_angle_to_matrix, grid_mesh, plane_distance,
                                 sphere_distance)
from garmentgnn.motion import Motion
from garmentgnn.physics import friction_energy, friction_hessian, material
from garmentgnn.sim import ClothSystem, Plane, SimSettings, Sphere, simulate, step
from garmentgnn.sim.system import Contact

G = 9.81
COTTON = material("cotton")


def still(frames: int) -> Motion:
    return Motion(torch.zeros(frames, 1, 3), torch.zeros(frames, 3), ["root"], 30.0)


def patch_on_plane(normal: torch.Tensor, tangent: torch.Tensor, n: int = 3, size: float = 0.1,
                   margin: float = COTTON.collision_margin) -> Garment:
    """An ``n x n`` square patch lying on the plane through the origin with unit
    ``normal``, one side along ``tangent``, at the collision margin."""
    pos, faces = grid_mesh(n, n, (size, size))
    side = torch.cross(normal, tangent, dim=0)
    P = pos[:, :1].double() * tangent + pos[:, 1:2].double() * side + margin * normal
    return Garment(P.float(), faces, pos[:, :2].clone())


def incline(mu: float, theta: float = 30.0, frames: int = 16):
    """Mean downhill displacement ``[T]`` of a patch on a ``theta``-degree incline."""
    th = math.radians(theta)
    normal = torch.tensor([math.sin(th), 0.0, math.cos(th)], dtype=torch.float64)
    down = torch.tensor([math.cos(th), 0.0, -math.sin(th)], dtype=torch.float64)
    g = patch_on_plane(normal, down)
    res = simulate(g, None, still(frames), replace(COTTON, friction=mu),
                   SimSettings(substeps=4, friction=True),
                   colliders=Plane((0.0, 0.0, 0.0), normal.tolist()))
    assert res.ok, res.message
    return res, (res.positions.double() - res.positions[0].double()).mean(1) @ down


def test_patch_sticks_when_mu_exceeds_tan_theta():
    res, d = incline(mu=0.8)  # tan(30 deg) = 0.577
    # the contact force is lagged by one substep, so the first substep slides freely
    # (g sin(theta) h^2 ~ 0.3 mm); afterwards only the smoothed-static creep remains
    # (below friction_velocity = 1 mm/s)
    assert float(d[-1]) < 2e-3
    creep = float(d[-1] - d[3]) / ((len(d) - 4) / 30.0)
    assert creep < 1e-3
    assert float(res.penetration.max()) < 1e-4


@pytest.mark.parametrize("mu", [0.0, 0.2, 0.4])
def test_patch_slides_with_coulomb_acceleration(mu):
    _, d = incline(mu)
    expected = G * (math.sin(math.radians(30)) - mu * math.cos(math.radians(30)))
    # constant acceleration: second differences of the frames after touchdown
    acc = (d[6:] - 2 * d[5:-1] + d[4:-2]) * 30.0 ** 2
    assert torch.allclose(acc, torch.full_like(acc, expected), rtol=0.03, atol=0.03), acc
    if mu == 0.4:  # and friction makes the difference
        assert float(d[-1]) < 0.5 * float(incline(0.0)[1][-1])


def test_mu_zero_never_evaluates_friction(monkeypatch):
    def boom(*a, **k):
        raise AssertionError("friction evaluated with mu = 0")
    monkeypatch.setattr(ClothSystem, "friction", boom)
    monkeypatch.setattr(ClothSystem, "friction_blocks", boom)
    res0, d0 = incline(mu=0.0, frames=6)
    monkeypatch.undo()
    # friction vanishes continuously: a tiny mu gives nearly the same trajectory
    res1, d1 = incline(mu=1e-9, frames=6)
    assert torch.allclose(res0.positions, res1.positions, atol=1e-6)


def sliding_patch(mu: float, v0: float = 0.5):
    """A patch on the floor ``z = 0`` sliding along +x at ``v0``: positions per step."""
    normal = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    g = patch_on_plane(normal, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    mat = replace(COTTON, friction=mu)
    system = ClothSystem(g.vertices, g.faces, mat, g.face_uv, colliders=[Plane()],
                         settings=SimSettings(friction=True))
    # start in the penalty equilibrium (the weight carried by the contact)
    x = g.vertices.double()
    x[:, 2] -= (system.mass * G / (3 * 1e6)).sqrt()
    v = torch.zeros_like(x)
    v[:, 0] = v0
    h = 1.0 / 120.0
    xs, vs = [x], [v]
    for _ in range(int(0.2 / h)):
        r = step(system, x, v, h)
        assert r.ok, r.message
        x, v = r.x, r.v
        xs.append(x)
        vs.append(v)
    return system, torch.stack(xs), torch.stack(vs)


def test_friction_is_off_unless_switched_on():
    """``SimSettings.friction`` defaults to off: mu is then ignored (the patch keeps
    sliding as without friction)."""
    normal = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    g = patch_on_plane(normal, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    system = ClothSystem(g.vertices, g.faces, replace(COTTON, friction=0.5), g.face_uv,
                         colliders=[Plane()])
    assert not system.settings.friction
    x = g.vertices.double()
    x[:, 2] -= 1e-3  # pressed into the floor: the contacts carry a normal force
    assert not system.has_friction(system.contact_planes(x, None))
    on = ClothSystem(g.vertices, g.faces, replace(COTTON, friction=0.5), g.face_uv,
                     colliders=[Plane()], settings=SimSettings(friction=True))
    assert on.has_friction(on.contact_planes(x, None))
    with pytest.raises(ValueError, match="friction"):
        SimSettings(friction=1)


def test_friction_only_removes_energy_and_stops_at_coulomb_distance():
    mu, v0 = 0.5, 0.5
    system, X, Vel = sliding_patch(mu, v0)
    ke = 0.5 * (system.mass * (Vel * Vel).sum(-1)).sum(-1)
    assert (ke[1:] <= ke[:-1] * (1 + 1e-9) + 1e-12).all()
    vx = Vel[:, :, 0].mean(1)
    h = 1.0 / 120.0
    decel = -(vx[5:12] - vx[4:11]) / h  # while sliding
    assert torch.allclose(decel, torch.full_like(decel, mu * G), rtol=0.03)
    stop = v0 ** 2 / (2 * mu * G)  # 25.5 mm
    travelled = float(X[-1, :, 0].mean() - X[0, :, 0].mean())
    assert abs(travelled - stop) < 0.05 * stop + 1e-3
    assert float(vx[-1]) < 2e-3  # at rest (within the static creep)
    # without friction it keeps going
    _, X0, V0 = sliding_patch(0.0, v0)
    assert float(V0[-1, :, 0].mean()) == pytest.approx(v0, rel=1e-3)


def test_rotated_scene_gives_rotated_answer():
    R = axis_angle_to_matrix(torch.tensor([0.3, -0.7, 0.4], dtype=torch.float64))
    th = math.radians(25)
    normal = torch.tensor([math.sin(th), 0.0, math.cos(th)], dtype=torch.float64)
    down = torch.tensor([math.cos(th), 0.0, -math.sin(th)], dtype=torch.float64)
    mat = replace(COTTON, friction=0.2)
    out = []
    for rot in (torch.eye(3, dtype=torch.float64), R):
        g = patch_on_plane(rot @ normal, rot @ down)
        st = SimSettings(substeps=4, friction=True, gravity=tuple((rot @ torch.tensor([0, 0, -G],
                                                                         dtype=torch.float64)).tolist()))
        res = simulate(g, None, still(8), mat, st,
                       colliders=Plane((0.0, 0.0, 0.0), (rot @ normal).tolist()))
        assert res.ok, res.message
        out.append(res.positions.double())
    moved = float((out[0][-1] - out[0][0]).norm(dim=-1).mean())
    assert moved > 0.02  # it slid, so the comparison tests the friction direction
    assert torch.allclose(out[0] @ R.T, out[1], atol=2e-5)


def test_sheet_dropped_on_sphere_rests_outside():
    n, frames, radius = 6, 30, 0.15
    pos, faces = grid_mesh(n, n, (0.4, 0.4))
    g = Garment(pos - torch.tensor([0.2, 0.2, -0.17]), faces, pos[:, :2].clone())
    sphere = Sphere((0.0, 0.0, 0.0), radius)
    res = simulate(g, None, still(frames), COTTON, SimSettings(substeps=4, friction=True),
                   colliders=sphere)
    assert res.ok, res.message
    P = res.positions.double()
    sd = P.norm(dim=-1) - radius
    assert float(sd.min()) > -1e-3
    # the exact penetration reported agrees with the analytic distance
    assert torch.allclose(res.penetration.double(), (-sd).clamp_min(0).amax(-1), atol=1e-6)
    ke = 0.5 * (((P[1:] - P[:-1]) * 30.0) ** 2).sum(-1).mean(-1)
    assert float(ke.max()) > 0.05  # it fell
    assert float(ke[-1]) < 2e-3 * float(ke.max())  # and came to rest on the sphere
    assert float(sd[-1, n * n // 2 + n // 2]) < 0.01  # the middle lies on top


def test_moving_sphere_pushes_and_carries_the_cloth():
    """A sphere rising under a resting patch lifts it; the patch ends above it."""
    frames = 10
    pos, faces = grid_mesh(3, 3, (0.1, 0.1))
    g = Garment(pos - torch.tensor([0.05, 0.05, -0.105]), faces, pos[:, :2].clone())
    centres = torch.zeros(frames, 3, dtype=torch.float64)
    centres[:, 2] = torch.linspace(0.0, 0.1, frames)
    res = simulate(g, None, still(frames), COTTON, SimSettings(substeps=4, friction=True),
                   colliders=Sphere(centres, 0.1))
    assert res.ok, res.message
    z = res.positions[:, 4, 2].double()
    assert float(z[-1]) > 0.19  # carried up 0.1 m (the free fall alone would lower it)
    assert float(res.penetration.max()) < 2e-3


# ------------------------------------------------------------------ the pieces
def test_friction_hessian_matches_autograd_and_is_psd():
    gen = torch.Generator().manual_seed(0)
    n = torch.nn.functional.normalize(torch.randn(8, 3, generator=gen, dtype=torch.float64), dim=-1)
    lam = torch.rand(8, generator=gen, dtype=torch.float64)
    for scale in (1e-4, 1e-2):  # below and above eps
        d = scale * torch.randn(8, 3, generator=gen, dtype=torch.float64)
        H = friction_hessian(d, n, lam, 0.4, 1e-3)
        Ha = torch.autograd.functional.hessian(
            lambda y: friction_energy(y.view(8, 3), n, lam, 0.4, 1e-3), d.reshape(-1))
        Ha = Ha.view(8, 3, 8, 3)
        assert torch.allclose(H, torch.stack([Ha[i, :, i] for i in range(8)]), atol=1e-9)
        assert float(torch.linalg.eigvalsh(H).min()) > -1e-9


def test_friction_force_is_coulomb_when_sliding():
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    d = torch.tensor([[0.03, -0.04, 0.7]], dtype=torch.float64, requires_grad=True)
    e = friction_energy(d, n, torch.tensor([2.0], dtype=torch.float64), 0.3, 1e-3)
    (grad,) = torch.autograd.grad(e, d)
    # magnitude mu * lambda, opposing the tangential motion, nothing along the normal
    assert torch.allclose(grad, 0.6 * torch.tensor([[0.6, -0.8, 0.0]], dtype=torch.float64))


def test_analytic_sdfs_against_definitions():
    gen = torch.Generator().manual_seed(1)
    p = torch.randn(50, 3, generator=gen, dtype=torch.float64).requires_grad_(True)
    c = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    sd = sphere_distance(p, c, 0.5)
    assert torch.allclose(sd.distance, (p - c).norm(dim=-1) - 0.5)
    assert torch.allclose((sd.closest - c).norm(dim=-1),
                          torch.full((50,), 0.5, dtype=torch.float64))
    (grad,) = torch.autograd.grad(sd.distance.sum(), p)
    assert torch.allclose(grad, sd.normal)
    pd = plane_distance(p, c, (0.0, 0.0, 2.0))
    assert torch.allclose(pd.distance, p[:, 2] - 0.3)
    assert torch.allclose(pd.closest[:, 2], torch.full((50,), 0.3, dtype=torch.float64))


@pytest.mark.parametrize("make,match", [
    (lambda: Sphere((0, 0, 0), 0.0), "radius"),
    (lambda: Sphere((0, 0, 0), -1.0), "radius"),
    (lambda: Sphere((0, 0, float("nan")), 1.0), "centre"),
    (lambda: Plane((0, 0, 0), (0, 0, 0)), "normal"),
    (lambda: Plane((0, 0), (0, 0, 1)), "point"),
    (lambda: sphere_distance(torch.zeros(2, 3), (0, 0, 0), 0.0), "radius"),
    (lambda: plane_distance(torch.zeros(2, 3), (0, 0, 0), (0, 0, 0)), "normal"),
    (lambda: SimSettings(friction_velocity=0.0), "friction_velocity"),
])
def test_bad_collider_input(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_colliders_must_be_colliders():
    g = patch_on_plane(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64),
                       torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    with pytest.raises(TypeError, match="colliders"):
        simulate(g, None, still(2), COTTON, colliders=["floor"])


def test_contact_is_a_named_tuple_of_the_old_layout():
    system = ClothSystem(torch.zeros(3, 3), torch.tensor([[0, 1, 2]]), COTTON,
                         colliders=Plane())
    c = system.contact_planes(torch.tensor([[0.0, 0, 0.001], [1, 0, 0.001], [0, 1, 0.5]],
                                           dtype=torch.float64))
    assert isinstance(c, Contact)
    idx, q, n, s = c[:4]
    assert idx.tolist() == [0, 1]
    assert torch.allclose(s, torch.tensor([0.001, 0.001, 0.5], dtype=torch.float64))
    assert torch.allclose(c.force, 3e6 * torch.tensor([0.001, 0.001], dtype=torch.float64) ** 2)
