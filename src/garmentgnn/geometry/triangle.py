"""The exact closest point on a triangle (Ericson 2005, §5.1.5), in the batched form
and in the per-coordinate form of the candidate face search."""
from __future__ import annotations

from typing import List, Sequence, Tuple

import torch
from torch import Tensor

__all__ = ["closest_point_on_triangle", "squared_distances_per_coordinate", "REGION_FACE",
           "REGION_VERTEX", "REGION_EDGE"]

# region codes returned by closest_point_on_triangle
REGION_FACE = 0
REGION_VERTEX = (1, 2, 3)  # closest point is corner a, b, c
REGION_EDGE = (4, 5, 6)  # closest point on edge ab, bc, ca


def _safe_div(num: Tensor, den: Tensor) -> Tensor:
    ok = den.abs() > torch.finfo(den.dtype).tiny
    return num / torch.where(ok, den, torch.ones_like(den))


def closest_point_on_triangle(p: Tensor, a: Tensor, b: Tensor, c: Tensor
                              ) -> Tuple[Tensor, Tensor, Tensor]:
    """Exact closest point on triangle ``(a, b, c)`` to ``p`` (Ericson 2005, §5.1.5).

    All inputs broadcast to ``[..., 3]``.  The Voronoi region of ``p`` is found from
    the dot products ``d1..d6`` of Ericson's algorithm (vertex regions first, then
    edge regions, else the face interior) and the closest point is written in
    barycentric form ``q = u a + v b + w c``.  Differentiable (the division by
    degenerate denominators is guarded, so gradients never become NaN).

    Returns:
        ``(q [..., 3], bary [..., 3] = (u, v, w), region [...] long)`` with region
        ``0`` = face interior, ``1/2/3`` = vertex a/b/c, ``4/5/6`` = edge ab/bc/ca.
    """
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = p - b
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = p - c
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    u, v, w, region = _voronoi_regions(d1, d2, d3, d4, d5, d6)
    q = u.unsqueeze(-1) * a + v.unsqueeze(-1) * b + w.unsqueeze(-1) * c
    return q, torch.stack([u, v, w], -1), region


def _voronoi_regions(d1: Tensor, d2: Tensor, d3: Tensor, d4: Tensor, d5: Tensor, d6: Tensor
                     ) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """Ericson's cascade on the dot products ``d1 = ab.ap, d2 = ac.ap, d3 = ab.bp, d4 =
    ac.bp, d5 = ab.cp, d6 = ac.cp``: the closest point's barycentric ``(u, v, w)`` and
    region code (:func:`closest_point_on_triangle`), each shaped like ``d1``."""
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4

    zero, one = torch.zeros_like(d1), torch.ones_like(d1)
    # face interior (default)
    denom = va + vb + vc
    v, w = _safe_div(vb, denom), _safe_div(vc, denom)
    u = 1 - v - w
    region = torch.zeros(d1.shape, dtype=torch.long, device=d1.device)

    def put(cond: Tensor, new_u: Tensor, new_v: Tensor, new_w: Tensor, code: int):
        nonlocal u, v, w, region
        u, v, w = (torch.where(cond, new, old) for new, old in ((new_u, u), (new_v, v),
                                                                (new_w, w)))
        region = torch.where(cond, torch.full_like(region, code), region)

    # apply in reverse priority so that Ericson's earlier tests win
    t_bc = _safe_div(d4 - d3, (d4 - d3) + (d5 - d6))
    put((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), zero, 1 - t_bc, t_bc, 5)
    t_ac = _safe_div(d2, d2 - d6)
    put((vb <= 0) & (d2 >= 0) & (d6 <= 0), 1 - t_ac, zero, t_ac, 6)
    put((d6 >= 0) & (d5 <= d6), zero, zero, one, 3)
    t_ab = _safe_div(d1, d1 - d3)
    put((vc <= 0) & (d1 >= 0) & (d3 <= 0), 1 - t_ab, t_ab, zero, 4)
    put((d3 >= 0) & (d4 <= d3), zero, one, zero, 2)
    put((d1 <= 0) & (d2 <= 0), one, zero, zero, 1)
    return u, v, w, region


def squared_distances_per_coordinate(p: Sequence[Tensor], a: Sequence[Tensor],
                                     b: Sequence[Tensor], c: Sequence[Tensor]) -> Tensor:
    """Squared distance from ``p`` to triangle ``(a, b, c)``, each point given as its
    three coordinate tensors (broadcasting): the arithmetic of
    :func:`closest_point_on_triangle` written per coordinate, so that a compiled kernel
    runs along the candidates (the last dimension) instead of the 3 coordinates."""
    def sub(x: Sequence[Tensor], y: Sequence[Tensor]) -> List[Tensor]:
        return [xi - yi for xi, yi in zip(x, y)]

    def dot(x: Sequence[Tensor], y: Sequence[Tensor]) -> Tensor:
        return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]

    ab, ac = sub(b, a), sub(c, a)
    ap, bp, cp = sub(p, a), sub(p, b), sub(p, c)
    u, v, w, _ = _voronoi_regions(dot(ab, ap), dot(ac, ap), dot(ab, bp), dot(ac, bp),
                                  dot(ab, cp), dot(ac, cp))
    return sum((p[i] - (u * a[i] + v * b[i] + w * c[i])) ** 2 for i in range(3))
