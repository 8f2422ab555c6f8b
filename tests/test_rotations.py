"""Rotation conversions vs scipy.spatial.transform.Rotation (uppercase orders = intrinsic)."""
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from garmentgnn.geometry import (axis_angle_to_matrix, euler_to_matrix, matrix_to_axis_angle,
                                 matrix_to_euler, unwrap_axis_angle)

D = torch.float64
TAIT_BRYAN = ["XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"]


def _unit(n, seed):
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_axis_angle_to_matrix_matches_scipy():
    rv = np.random.default_rng(0).normal(size=(200, 3)) * 1.5
    R = axis_angle_to_matrix(torch.tensor(rv)).numpy()
    np.testing.assert_allclose(R, Rotation.from_rotvec(rv).as_matrix(), atol=1e-12)
    # batched shape [..., 3] -> [..., 3, 3]
    assert axis_angle_to_matrix(torch.zeros(4, 5, 3)).shape == (4, 5, 3, 3)


# Angles near 0 and near pi, where a naive acos(trace) / (w / 2 sin) inverse fails.
_ANGLES = [0.0, 1e-12, 1e-7, 1e-4, 0.5, 2.0, np.pi - 1e-3, np.pi - 1e-6, np.pi]
_CASES = [pytest.param(a, D, id=f"f64-{a:.10f}") for a in _ANGLES]
_CASES += [pytest.param(a, torch.float32, id=f"f32-{a:.10f}")
           for a in _ANGLES + [np.pi - 0.05, np.pi - 1e-2]]


@pytest.mark.parametrize("angle,dtype", _CASES)
def test_axis_angle_round_trip_near_zero_and_pi(angle, dtype):
    tol = 1e-6 if dtype == D else 1e-4
    rv = _unit(64, 1) * angle
    M = Rotation.from_rotvec(rv).as_matrix()
    torch.testing.assert_close(axis_angle_to_matrix(torch.tensor(rv, dtype=dtype)),
                               torch.tensor(M, dtype=dtype), rtol=0, atol=tol / 10)
    aa = matrix_to_axis_angle(torch.tensor(M, dtype=dtype)).double().numpy()
    assert np.isfinite(aa).all()
    # compare rotations (at pi, +axis and -axis are the same rotation)
    np.testing.assert_allclose(Rotation.from_rotvec(aa).as_matrix(), M, atol=tol)
    np.testing.assert_allclose(np.linalg.norm(aa, axis=1), angle, atol=tol)
    if 1e-7 < angle < np.pi - 1e-5 and dtype == D:  # unique: same vector as scipy
        np.testing.assert_allclose(aa, Rotation.from_matrix(M).as_rotvec(), atol=1e-7)


@pytest.mark.parametrize("dtype,atol", [(torch.float16, 2e-3), (torch.bfloat16, 2e-2)])
def test_axis_angle_to_matrix_half_precision_near_zero(dtype, atol):
    """float16 / bfloat16: zero and tiny rotations give the identity-like matrix (not
    0/0 = NaN from a small-angle threshold that underflows), scipy within the dtype's
    resolution."""
    rv = np.concatenate([np.zeros((1, 3)), _unit(8, 3) * 1e-5, _unit(8, 4) * 1e-2,
                         _unit(8, 5) * 0.7])
    R = axis_angle_to_matrix(torch.tensor(rv, dtype=dtype))
    assert R.dtype == dtype and torch.isfinite(R).all()
    np.testing.assert_allclose(R.double().numpy(), Rotation.from_rotvec(rv).as_matrix(),
                               atol=atol)


def test_axis_angle_gradient_finite_at_zero():
    x = torch.zeros(3, 3, dtype=D, requires_grad=True)
    axis_angle_to_matrix(x).sum().backward()
    assert torch.isfinite(x.grad).all()
    y = (torch.randn(5, 3, dtype=D) * 0.7).requires_grad_(True)
    assert torch.autograd.gradcheck(axis_angle_to_matrix, (y,))


@pytest.mark.parametrize("order", TAIT_BRYAN)
def test_euler_to_matrix_matches_scipy_intrinsic(order):
    e = np.random.default_rng(2).uniform(-np.pi, np.pi, size=(200, 3))
    R = euler_to_matrix(torch.tensor(e), order).numpy()
    np.testing.assert_allclose(R, Rotation.from_euler(order, e).as_matrix(), atol=1e-12)
    # lower-case order strings mean the same here (documented as intrinsic)
    np.testing.assert_allclose(euler_to_matrix(torch.tensor(e), order.lower()).numpy(), R)


@pytest.mark.parametrize("order", TAIT_BRYAN)
def test_matrix_to_euler_matches_scipy(order):
    rng = np.random.default_rng(3)
    e = rng.uniform(-np.pi, np.pi, size=(300, 3))
    e[:, 1] = rng.uniform(-np.pi / 2 + 1e-3, np.pi / 2 - 1e-3, size=300)  # unique branch
    M = Rotation.from_euler(order, e).as_matrix()
    out = matrix_to_euler(torch.tensor(M), order).numpy()
    np.testing.assert_allclose(out, e, atol=1e-9)
    np.testing.assert_allclose(out, Rotation.from_matrix(M).as_euler(order), atol=1e-9)
    out32 = matrix_to_euler(torch.tensor(M, dtype=torch.float32), order).double().numpy()
    np.testing.assert_allclose(out32, e, atol=2e-3)  # asin near +-1 loses ~sqrt(eps)


@pytest.mark.parametrize("order", ["ZXY", "XYZ"])
def test_matrix_to_euler_gimbal_lock_round_trip(order):
    e = np.random.default_rng(4).uniform(-1, 1, size=(20, 3))
    e[:10, 1], e[10:, 1] = np.pi / 2, -np.pi / 2
    M = Rotation.from_euler(order, e).as_matrix()
    back = euler_to_matrix(matrix_to_euler(torch.tensor(M), order), order).numpy()
    np.testing.assert_allclose(back, M, atol=1e-6)


def test_bad_order():
    with pytest.raises(ValueError, match="`order`"):
        euler_to_matrix(torch.zeros(3), "XY")
    with pytest.raises(ValueError, match="`order`"):
        matrix_to_euler(torch.eye(3), "XYX")


def test_unwrap_axis_angle_keeps_rotations_and_removes_jumps():
    # a joint spinning steadily about a fixed axis past pi: the wrapped axis-angle jumps
    # (angle pi - e -> axis flipped), the unwrapped one grows linearly, same rotations
    axis = _unit(1, 3)[0]
    angles = np.linspace(0.0, 3 * np.pi, 41)  # steps of 3 pi / 40: never exactly 2 pi
    R = Rotation.from_rotvec(angles[:, None] * axis)
    wrapped = R.as_rotvec()[:, None, :]  # [T, 1, 3], angle in [0, pi]
    assert np.abs(np.diff(wrapped, axis=0)).max() > 1.0
    out = unwrap_axis_angle(wrapped)
    np.testing.assert_allclose(out[:, 0], angles[:, None] * axis, atol=1e-9)
    np.testing.assert_allclose(Rotation.from_rotvec(out[:, 0]).as_matrix(), R.as_matrix(),
                               atol=1e-9)
    assert out is not wrapped and np.abs(np.diff(wrapped, axis=0)).max() > 1.0  # input kept
