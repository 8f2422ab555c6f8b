"""Rigid analytic colliders for :func:`garmentgnn.sim.simulate`: a (possibly moving)
sphere and an infinite plane.

A collider answers, at a fractional motion frame ``f`` (frame ``t`` of the motion is
``f = t``; substeps interpolate), the signed distance of points to its surface
(:mod:`garmentgnn.geometry.sdf`) and how far the surface point under a contact moved
between two frames (for friction, which acts on the cloth's motion relative to the
collider).  Pre-roll and settle frames see the collider at frame 0.
"""
from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from garmentgnn.geometry import SignedDistance, plane_distance, sphere_distance
from garmentgnn.geometry.sdf import check_vector
from garmentgnn.sim.settings import DTYPE

__all__ = ["Collider", "Sphere", "Plane"]


class Collider:
    """Base class of the rigid colliders (subclasses: :class:`Sphere`, :class:`Plane`)."""

    def distance(self, points: Tensor, frame: float) -> SignedDistance:
        """Signed distance of ``points [V, 3]`` at fractional frame ``frame``."""
        raise NotImplementedError

    def motion(self, closest: Tensor, frame0: float, frame1: float) -> Tensor:
        """``[C, 3]`` displacement, from ``frame0`` to ``frame1``, of the collider's
        material points now at ``closest [C, 3]``."""
        raise NotImplementedError


class Sphere(Collider):
    """A rigid sphere.

    Args:
        centre: ``[3]`` (fixed) or ``[T, 3]`` (one centre per motion frame, linearly
            interpolated between frames; the sphere translates, it does not spin).
        radius: positive radius (m).
    """

    def __init__(self, centre: Any, radius: float):
        if isinstance(radius, bool) or not isinstance(radius, (int, float)) \
                or not (math.isfinite(radius) and radius > 0):
            raise ValueError(f"`radius`: must be a positive finite number (m), got {radius!r}")
        c = check_vector(centre, "centre", torch.zeros(0, dtype=DTYPE))
        if c.dim() not in (1, 2) or (c.dim() == 2 and c.shape[0] == 0):
            raise ValueError(f"`centre`: expected [3] or [T, 3] (one per frame), got "
                             f"{tuple(c.shape)}")
        self.centres = c.detach().reshape(-1, 3).to(DTYPE)
        self.radius = float(radius)

    def centre(self, frame: float) -> Tensor:
        """The centre at fractional frame ``frame`` (clamped to the given frames)."""
        T = self.centres.shape[0]
        f = min(max(float(frame), 0.0), T - 1.0)
        i = min(int(math.floor(f)), T - 1)
        j = min(i + 1, T - 1)
        w = f - i
        return (1 - w) * self.centres[i] + w * self.centres[j]

    def distance(self, points: Tensor, frame: float) -> SignedDistance:
        return sphere_distance(points, self.centre(frame).to(points.dtype), self.radius)

    def motion(self, closest: Tensor, frame0: float, frame1: float) -> Tensor:
        return (self.centre(frame1) - self.centre(frame0)).to(closest.dtype).expand_as(closest)

    def __repr__(self) -> str:
        c = self.centres[0].tolist()
        moving = f", {self.centres.shape[0]} frames" if self.centres.shape[0] > 1 else ""
        return f"Sphere(centre={[round(v, 4) for v in c]}{moving}, radius={self.radius})"


class Plane(Collider):
    """A fixed infinite plane through ``point`` with outward ``normal`` (normalised here;
    must be non-zero); the half-space behind it is inside."""

    def __init__(self, point: Any = (0.0, 0.0, 0.0), normal: Any = (0.0, 0.0, 1.0)):
        like = torch.zeros(0, dtype=DTYPE)
        o, n = check_vector(point, "point", like), check_vector(normal, "normal", like)
        if o.shape != (3,) or n.shape != (3,):
            raise ValueError(f"`point`, `normal`: expected [3] each, got {tuple(o.shape)}, "
                             f"{tuple(n.shape)}")
        if not float(n.norm()) > 1e-12:
            raise ValueError(f"`normal`: must be non-zero, got {n.tolist()}")
        self.point, self.normal = o.detach(), (n / n.norm()).detach()

    def distance(self, points: Tensor, frame: float) -> SignedDistance:
        return plane_distance(points, self.point.to(points.dtype), self.normal.to(points.dtype))

    def motion(self, closest: Tensor, frame0: float, frame1: float) -> Tensor:
        return torch.zeros_like(closest)

    def __repr__(self) -> str:
        return (f"Plane(point={[round(v, 4) for v in self.point.tolist()]}, "
                f"normal={[round(v, 4) for v in self.normal.tolist()]})")
