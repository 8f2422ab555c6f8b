"""Rotation conversions (batched, differentiable): axis-angle, matrices, Euler angles."""
from __future__ import annotations

import torch
from torch import Tensor

_AXES = {"X": 0, "Y": 1, "Z": 2}


def axis_angle_to_matrix(aa: Tensor) -> Tensor:
    """Rodrigues' formula: ``[..., 3]`` axis-angle (angle = norm) to ``[..., 3, 3]``.

    Smooth at zero rotation (uses the Taylor series of sin(t)/t and (1-cos t)/t^2).
    """
    theta2 = (aa * aa).sum(-1, keepdim=True).unsqueeze(-1)  # [..., 1, 1]
    theta = theta2.clamp_min(1e-24).sqrt()
    small = theta2 < 1e-8
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / theta2.clamp_min(1e-24))
    x, y, z = aa.unbind(-1)
    zero = torch.zeros_like(x)
    K = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).view(*aa.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=aa.dtype, device=aa.device).expand_as(K)
    return eye + a * K + b * (K @ K)


def matrix_to_axis_angle(R: Tensor) -> Tensor:
    """Inverse of :func:`axis_angle_to_matrix` (angle in [0, pi])."""
    cos = ((R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0) / 2.0).clamp(-1.0, 1.0)
    angle = torch.acos(cos)
    w = torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                     R[..., 1, 0] - R[..., 0, 1]], -1)
    sin = torch.sin(angle)
    small = sin.abs() < 1e-6
    axis_generic = w / (2.0 * sin.clamp_min(1e-12)).unsqueeze(-1)
    # near pi: axis from the diagonal of (R + I) / 2 = a a^T
    B = (R + torch.eye(3, dtype=R.dtype, device=R.device)) / 2.0
    diag = torch.diagonal(B, dim1=-2, dim2=-1).clamp_min(0.0)
    k = diag.argmax(-1, keepdim=True)
    col = torch.gather(B, -1, k.unsqueeze(-2).expand(*B.shape[:-1], 1)).squeeze(-1)
    axis_pi = col / col.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    near_zero = small & (cos > 0)
    axis = torch.where((small & ~near_zero).unsqueeze(-1), axis_pi, axis_generic)
    out = axis * angle.unsqueeze(-1)
    return torch.where(near_zero.unsqueeze(-1), w / 2.0, out)


def _elementary(axis: str, angle: Tensor) -> Tensor:
    c, s = torch.cos(angle), torch.sin(angle)
    one, zero = torch.ones_like(angle), torch.zeros_like(angle)
    if axis == "X":
        m = [one, zero, zero, zero, c, -s, zero, s, c]
    elif axis == "Y":
        m = [c, zero, s, zero, one, zero, -s, zero, c]
    else:
        m = [c, -s, zero, s, c, zero, zero, zero, one]
    return torch.stack(m, -1).view(*angle.shape, 3, 3)


def euler_to_matrix(angles: Tensor, order: str) -> Tensor:
    """Intrinsic Euler angles (radians) ``[..., 3]`` in ``order`` (e.g. ``"ZXY"``,
    the BVH convention: ``R = R_Z @ R_X @ R_Y`` for channels listed Z, X, Y)."""
    order = order.upper()
    if len(order) != 3 or set(order) - set(_AXES):
        raise ValueError(f"`order`: expected three of X, Y, Z such as 'ZXY', got {order!r}")
    R = _elementary(order[0], angles[..., 0])
    for i in (1, 2):
        R = R @ _elementary(order[i], angles[..., i])
    return R


def matrix_to_euler(R: Tensor, order: str) -> Tensor:
    """Inverse of :func:`euler_to_matrix` for Tait-Bryan orders (all three axes differ)."""
    order = order.upper()
    if len(order) != 3 or len(set(order)) != 3 or set(order) - set(_AXES):
        raise ValueError(f"`order`: expected a permutation of 'XYZ' such as 'ZXY', got {order!r}")
    i, j, k = (_AXES[c] for c in order)
    # sign of the permutation (i, j, k): +1 for cyclic orders
    sign = 1.0 if (j - i) % 3 == 1 else -1.0
    middle = torch.asin((sign * R[..., i, k]).clamp(-1.0, 1.0))
    first = torch.atan2(-sign * R[..., j, k], R[..., k, k])
    last = torch.atan2(-sign * R[..., i, j], R[..., i, i])
    return torch.stack([first, middle, last], -1)
