"""Analytic signed distances of rigid shapes (sphere, infinite plane).

Both return a :class:`~garmentgnn.geometry.distance.SignedDistance` like the body-mesh
:func:`~garmentgnn.geometry.signed_distance`: ``distance`` positive outside, ``closest``
the closest surface point, ``normal`` the unit outward normal there (the gradient of the
distance), and ``face = -1`` (no faces).  Differentiable in ``points`` and in the shape
parameters.
"""
from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from ._validate import check_points, safe_norm
from .distance import SignedDistance

__all__ = ["sphere_distance", "plane_distance", "check_vector"]


def check_vector(v: Any, name: str, like: Tensor) -> Tensor:
    """``v``: three finite numbers (tensor, tuple or list), cast to ``like``'s dtype."""
    if isinstance(v, (tuple, list)):
        if not all(isinstance(c, (int, float)) and not isinstance(c, bool) for c in v):
            raise TypeError(f"`{name}`: expected three numbers, got {v!r}")
        v = torch.tensor(v, dtype=like.dtype)
    if not isinstance(v, Tensor):
        raise TypeError(f"`{name}`: expected a [3] tensor or three numbers, got "
                        f"{type(v).__name__}")
    if not v.is_floating_point():
        v = v.to(like.dtype)
    if v.shape[-1:] != (3,):
        raise ValueError(f"`{name}`: expected shape [..., 3], got {tuple(v.shape)}")
    if not bool(torch.isfinite(v).all()):
        raise ValueError(f"`{name}`: contains NaN or inf")
    return v.to(like.dtype)


def sphere_distance(points: Tensor, centre: Any, radius: float) -> SignedDistance:
    """Signed distance ``|p - c| - r`` to the sphere of centre ``c`` and radius ``r``.

    Args:
        points: ``[..., V, 3]``.
        centre: ``[3]`` (or ``[..., 1, 3]`` broadcasting with ``points``).
        radius: positive finite number (m).

    At the centre itself (no defined direction) the normal is ``+z``.
    """
    points = check_points(points, "points")
    if isinstance(radius, bool) or not isinstance(radius, (int, float)) \
            or not (math.isfinite(radius) and radius > 0):
        raise ValueError(f"`radius`: must be a positive finite number (m), got {radius!r}")
    c = check_vector(centre, "centre", points)
    diff = points - c
    dist = safe_norm(diff, keepdim=True)
    tiny = 1e3 * torch.finfo(points.dtype).eps
    up = torch.zeros_like(diff)
    up[..., 2] = 1.0
    normal = torch.where(dist > tiny, diff / dist.clamp_min(tiny), up)
    face = torch.full(points.shape[:-1], -1, dtype=torch.long, device=points.device)
    return SignedDistance(dist.squeeze(-1) - radius, c + radius * normal, normal, face)


def plane_distance(points: Tensor, point: Any, normal: Any) -> SignedDistance:
    """Signed distance ``(p - o) . n / |n|`` to the infinite plane through ``o`` with
    normal ``n`` (the half-space ``n . (p - o) < 0`` is inside).

    Args:
        points: ``[..., V, 3]``.
        point: ``[3]`` a point ``o`` of the plane.
        normal: ``[3]`` non-zero normal ``n`` (normalised here).
    """
    points = check_points(points, "points")
    o = check_vector(point, "point", points)
    n = check_vector(normal, "normal", points)
    length = float(n.norm())
    if not length > 1e-12:
        raise ValueError(f"`normal`: must be non-zero, got {n.tolist()}")
    n = n / length
    d = ((points - o) * n).sum(-1)
    face = torch.full(points.shape[:-1], -1, dtype=torch.long, device=points.device)
    return SignedDistance(d, points - d.unsqueeze(-1) * n, n.expand_as(points), face)
