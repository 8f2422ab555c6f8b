"""UV deformation gradient (GarTrans Eq. 14)."""
import math

import pytest
import torch

from garmentgnn import geometry as G
from garmentgnn.geometry import flat_triangles

D = torch.float64


def _sheet(seed=0):
    uv, faces = G.grid_mesh(5, 4, size=(1.0, 0.7), dtype=D)
    uv = uv[:, :2]
    g = torch.Generator().manual_seed(seed)
    uv = uv + 0.02 * torch.randn(uv.shape, generator=g, dtype=D)
    return uv, faces


def test_affine_map_is_recovered_exactly():
    uv, faces = _sheet()
    g = torch.Generator().manual_seed(1)
    M = torch.randn(3, 2, generator=g, dtype=D)
    t = torch.randn(3, generator=g, dtype=D)
    pos = uv @ M.T + t
    out = G.uv_deformation_gradient(pos, faces, uv)
    assert out.grad.shape == (faces.size(0), 3, 2)
    assert bool(out.valid.all())
    torch.testing.assert_close(out.grad, M.expand_as(out.grad))


def test_rotation_and_stretch_give_known_columns():
    """Rotate the plane and stretch u by 1.5, shear-free: |W^u| = 1.5, |W^v| = 1, W^u.W^v = 0."""
    uv, faces = _sheet(2)
    R = G.axis_angle_to_matrix(torch.tensor([0.4, 1.1, -0.3], dtype=D))
    flat = torch.cat([uv * torch.tensor([1.5, 1.0], dtype=D),
                      torch.zeros(uv.size(0), 1, dtype=D)], 1)
    W = G.uv_deformation_gradient(flat @ R.T, faces, uv).grad
    torch.testing.assert_close(W[..., 0].norm(dim=-1), torch.full((faces.size(0),), 1.5, dtype=D))
    torch.testing.assert_close(W[..., 1].norm(dim=-1), torch.ones(faces.size(0), dtype=D))
    torch.testing.assert_close((W[..., 0] * W[..., 1]).sum(-1), torch.zeros(faces.size(0), dtype=D))


def test_uv_area_and_batch():
    uv, faces = _sheet(3)
    a, b, c = (uv[faces[:, k]] for k in range(3))
    shoelace = 0.5 * ((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0]).abs()
    pos = torch.cat([uv, torch.zeros(uv.size(0), 1, dtype=D)], 1)
    batch = torch.stack([pos, 2.0 * pos, pos + 1.0])
    out = G.uv_deformation_gradient(batch, faces, uv)
    torch.testing.assert_close(out.uv_area, shoelace)
    assert out.grad.shape == (3, faces.size(0), 3, 2)
    torch.testing.assert_close(out.grad[1], 2.0 * out.grad[0])
    torch.testing.assert_close(out.grad[2], out.grad[0])
    eye = torch.tensor([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]], dtype=D)
    torch.testing.assert_close(out.grad[0], eye.expand_as(out.grad[0]))


def test_separate_uv_layout_with_uv_faces():
    """Seams: the UV layout has its own vertex list, indexed by uv_faces."""
    uv, faces = _sheet(4)
    pos = torch.randn(uv.size(0), 3, generator=torch.Generator().manual_seed(5), dtype=D)
    corner_uv = uv[faces].reshape(-1, 2)  # one UV vertex per face corner
    uv_faces = torch.arange(corner_uv.size(0)).view(-1, 3)
    a = G.uv_deformation_gradient(pos, faces, uv)
    b = G.uv_deformation_gradient(pos, faces, corner_uv, uv_faces=uv_faces)
    torch.testing.assert_close(a.grad, b.grad)
    with pytest.raises(ValueError, match="`uv`.*uv_faces"):
        G.uv_deformation_gradient(pos, faces, corner_uv)


@pytest.mark.float_sensitive
def test_zero_area_uv_triangle_is_masked_without_nan():
    uv = torch.tensor([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [0.0, 1.0]], dtype=D)
    faces = torch.tensor([[0, 1, 2], [0, 1, 3]])  # first is collinear in UV
    pos = torch.randn(4, 3, generator=torch.Generator().manual_seed(6), dtype=D,
                      ).requires_grad_(True)
    uvr = uv.clone().requires_grad_(True)
    out = G.uv_deformation_gradient(pos, faces, uvr)
    assert out.valid.tolist() == [False, True]
    assert torch.equal(out.grad[0], torch.zeros(3, 2, dtype=D))
    assert out.uv_area[0].item() == 0.0
    (out.grad.square().sum() + out.uv_area.sum()).backward()
    assert torch.isfinite(pos.grad).all() and torch.isfinite(uvr.grad).all()


def test_deformation_gradient_gradcheck():
    uv, faces = _sheet(7)
    pos = torch.randn(uv.size(0), 3, generator=torch.Generator().manual_seed(8), dtype=D)
    p = pos.clone().requires_grad_(True)
    u = uv.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x, y: G.uv_deformation_gradient(x, faces, y).grad,
                                     (p, u))
    # Eq. 12-13 style energies are differentiable through it as well
    def stretch_shear(x):
        out = G.uv_deformation_gradient(x, faces, uv)
        W = out.grad
        s = out.uv_area * ((W[..., 0].norm(dim=-1) - 1) ** 2 + (W[..., 1].norm(dim=-1) - 1) ** 2)
        h = out.uv_area * (W[..., 0] * W[..., 1]).sum(-1) ** 2
        return (s + h).sum()
    assert torch.autograd.gradcheck(stretch_shear, (p,))


def test_rest_frame_precompute_matches():
    uv, faces = _sheet(9)
    pos = torch.randn(2, uv.size(0), 3, generator=torch.Generator().manual_seed(10), dtype=D)
    frame = G.uv_rest_frame(uv, faces)
    torch.testing.assert_close(G.deformation_gradient(pos, faces, frame.inverse),
                               G.uv_deformation_gradient(pos, faces, uv).grad)
    # inverse really inverts Dm
    d1 = uv[faces[:, 1]] - uv[faces[:, 0]]
    d2 = uv[faces[:, 2]] - uv[faces[:, 0]]
    Dm = torch.stack([d1, d2], -1)
    torch.testing.assert_close(Dm @ frame.inverse, torch.eye(2, dtype=D).expand_as(Dm))
    assert math.isclose(frame.area.sum().item(), 0.7, rel_tol=0.05)


def test_uv_bad_input():
    uv, faces = _sheet()
    pos = torch.zeros(uv.size(0), 3, dtype=D)
    with pytest.raises(ValueError, match="`uv`.*shape"):
        G.uv_deformation_gradient(pos, faces, pos)
    bad = uv.clone()
    bad[0, 0] = float("inf")
    with pytest.raises(ValueError, match="`uv`.*NaN or inf"):
        G.uv_deformation_gradient(pos, faces, bad)
    with pytest.raises(ValueError, match="`uv_faces`"):
        G.uv_deformation_gradient(pos, faces, uv, uv_faces=faces + 100)
    with pytest.raises(ValueError, match="`inverse`"):
        G.deformation_gradient(pos, faces, torch.zeros(3, 2, 2, dtype=D))


def test_flat_triangles_are_isometric_and_counter_clockwise():
    tri = torch.randn(50, 3, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    flat = flat_triangles(tri)
    for a, b in [(0, 1), (1, 2), (2, 0)]:
        torch.testing.assert_close((flat[:, a] - flat[:, b]).norm(dim=-1),
                                   (tri[:, a] - tri[:, b]).norm(dim=-1))
    e1, e2 = flat[:, 1] - flat[:, 0], flat[:, 2] - flat[:, 0]
    assert (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] > 0).all()
