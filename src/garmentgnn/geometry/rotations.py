"""Rotation conversions (batched, differentiable): axis-angle, matrices, Euler angles;
and making an axis-angle sequence continuous in time (numpy)."""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

_AXES = {"X": 0, "Y": 1, "Z": 2}


def axis_angle_to_matrix(aa: Tensor) -> Tensor:
    """Rodrigues' formula: ``[..., 3]`` axis-angle (angle = norm) to ``[..., 3, 3]``.

    Smooth at zero rotation (uses the Taylor series of sin(t)/t and (1-cos t)/t^2 below
    t^2 = 1e-8, or below the dtype's machine epsilon where that is larger: float16 and
    bfloat16, where 1e-8 underflows to 0 and t = 0 would divide 0 by 0).
    """
    info = torch.finfo(aa.dtype)
    floor, threshold = max(1e-24, info.tiny), max(1e-8, info.eps)
    theta2 = (aa * aa).sum(-1, keepdim=True).unsqueeze(-1)  # [..., 1, 1]
    theta = theta2.clamp_min(floor).sqrt()
    small = theta2 < threshold
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / theta2.clamp_min(floor))
    x, y, z = aa.unbind(-1)
    zero = torch.zeros_like(x)
    K = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).view(*aa.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=aa.dtype, device=aa.device).expand_as(K)
    return eye + a * K + b * (K @ K)


def matrix_to_axis_angle(R: Tensor) -> Tensor:
    """Inverse of axis_angle_to_matrix (angle in [0, pi]), accurate near 0 and pi in float32.

    angle = atan2(|w| / 2, (tr R - 1) / 2) with w = vee(R - R^T) = 2 sin(angle) a;
    axis = w / |w| for angle <= pi/2; for angle > pi/2 it is read from the symmetric
    part (R + R^T)/2 - cos(angle) I = (1 - cos) a a^T (largest column), its sign taken
    from w.  Near 0, rotvec = w * angle / (2 sin angle) with the Taylor series.
    """
    w = torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                     R[..., 1, 0] - R[..., 0, 1]], -1)
    cos = (R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0) / 2.0
    s2 = (w * w).sum(-1)
    sin = 0.5 * s2.clamp_min(1e-30).sqrt()
    angle = torch.atan2(sin, cos)
    # small / moderate angles: w * angle / (2 sin)
    small = angle < 1e-3
    ratio = torch.where(small, 0.5 + angle * angle / 12.0,
                        angle / (2.0 * torch.where(small, torch.ones_like(sin), sin)))
    out_generic = w * ratio.unsqueeze(-1)
    # obtuse angles: axis from the symmetric part
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    S = 0.5 * (R + R.transpose(-1, -2)) - cos[..., None, None] * eye
    k = torch.diagonal(S, dim1=-2, dim2=-1).argmax(-1, keepdim=True)
    col = torch.gather(S, -1, k.unsqueeze(-2).expand(*S.shape[:-1], 1)).squeeze(-1)
    axis = col / col.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    flip = (axis * w).sum(-1, keepdim=True) < 0
    axis = torch.where(flip, -axis, axis)
    out_obtuse = axis * angle.unsqueeze(-1)
    return torch.where((cos < 0).unsqueeze(-1), out_obtuse, out_generic)


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
    """Inverse of euler_to_matrix for Tait-Bryan orders; at gimbal lock the last angle is 0."""
    order = order.upper()
    if len(order) != 3 or len(set(order)) != 3 or set(order) - set(_AXES):
        raise ValueError(f"`order`: expected a permutation of 'XYZ' such as 'ZXY', got {order!r}")
    i, j, k = (_AXES[c] for c in order)
    sign = 1.0 if (j - i) % 3 == 1 else -1.0
    cos_mid = torch.sqrt(R[..., i, i] ** 2 + R[..., i, j] ** 2)
    middle = torch.atan2(sign * R[..., i, k], cos_mid)  # accurate also near +-pi/2
    first = torch.atan2(-sign * R[..., j, k], R[..., k, k])
    last = torch.atan2(-sign * R[..., i, j], R[..., i, i])
    lock = cos_mid < (1e-6 if R.dtype == torch.float64 else 1e-4)
    first_lock = torch.atan2(sign * R[..., k, j], R[..., j, j])
    first = torch.where(lock, first_lock, first)
    last = torch.where(lock, torch.zeros_like(last), last)
    return torch.stack([first, middle, last], -1)


def unwrap_axis_angle(aa: np.ndarray) -> np.ndarray:
    """Make ``[T, S, 3]`` axis-angle (numpy) continuous in time: each rotation keeps its
    axis and gets the angle ``+ 2 pi k`` closest to the previous frame's (a copy)."""
    out = aa.copy()
    for t in range(1, aa.shape[0]):
        cur = out[t]
        ang = np.linalg.norm(cur, axis=-1, keepdims=True)
        ok = ang[:, 0] > 1e-8
        axis = np.where(ok[:, None], cur / np.maximum(ang, 1e-12), 0.0)
        p = (out[t - 1] * axis).sum(-1, keepdims=True)
        k = np.round((p - ang) / (2 * np.pi))
        out[t] = np.where(ok[:, None], cur + 2 * np.pi * k * axis, cur)
    return out
