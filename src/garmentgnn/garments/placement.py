"""Unit and placement sanity checks of a garment against a body (metres, Z up).

A garment modelled in millimetres (a T-shirt 700 units tall) or exported with an
offset (10 m from the body) simulates without complaint -- it just falls, or never
touches the body -- and gives a meaningless sequence.  :func:`check_placement`
turns both into a ``ValueError`` that says what to change.
"""
from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

#: the largest garment extent (metres) accepted; a long dress is ~1.6 m
MAX_EXTENT = 4.0
#: the smallest garment extent (metres) accepted
MIN_EXTENT = 0.02
#: largest gap (metres) between the garment's and the body's bounding boxes
MAX_GAP = 0.25


#: (name, metres per unit) of the units a garment file is likely in
UNITS = (("centimetres", 0.01), ("inches", 0.0254), ("millimetres", 0.001))
#: the extents (metres) a garment has once its unit is right: a bib to a long dress
PLAUSIBLE = (0.1, 2.5)


def _unit_hint(extent: float) -> str:
    """One factor: the unit that brings ``extent`` units to a plausible garment size
    (the first of centimetres, inches, millimetres that does), else no guess."""
    for name, factor in UNITS:
        if PLAUSIBLE[0] <= extent * factor <= PLAUSIBLE[1]:
            return (f"it looks like {name}: scale the vertices by {factor} "
                    f"(e.g. garment.vertices * {factor})")
    return ("the unit cannot be told from the size (no common unit gives a garment "
            f"{PLAUSIBLE[0]}-{PLAUSIBLE[1]} m across); scale the vertices to metres")


def check_placement(vertices: Tensor, body_vertices: Optional[Tensor] = None,
                    name: str = "garment.vertices") -> None:
    """Raise ``ValueError`` when ``vertices [V, 3]`` are not a garment in metres, or
    (with ``body_vertices [Vb, 3]``, the body in the pose the garment was made for)
    lie away from the body: bounding-box extent outside ``[MIN_EXTENT, MAX_EXTENT]``
    metres, or a gap over ``MAX_GAP`` metres between the two bounding boxes."""
    if vertices.numel() == 0:
        return
    lo, hi = vertices.detach().amin(0).double(), vertices.detach().amax(0).double()
    extent = float((hi - lo).max())
    if extent > MAX_EXTENT:
        raise ValueError(f"`{name}`: the garment is {extent:.4g} units across; garmentgnn "
                         f"works in metres and {_unit_hint(extent)}")
    if extent < MIN_EXTENT:
        raise ValueError(f"`{name}`: the garment is {extent:.3g} m across, smaller than "
                         f"{MIN_EXTENT} m; give the vertices in metres")
    if body_vertices is None or body_vertices.numel() == 0:
        return
    blo, bhi = body_vertices.detach().amin(0).double(), body_vertices.detach().amax(0).double()
    gap = torch.maximum(blo - hi, lo - bhi).clamp_min(0).norm()
    if float(gap) > MAX_GAP:
        # modelled Y-up (garmentgnn is Z-up)? Turned +90 degrees about X, (x, y, z) ->
        # (x, -z, y), a garment modelled around the Y-up body lies where it belongs
        v = vertices.detach().double()
        turned = torch.stack([v[:, 0], -v[:, 2], v[:, 1]], 1)
        tlo, thi = turned.amin(0), turned.amax(0)
        if float(torch.maximum(blo - thi, tlo - bhi).clamp_min(0).norm()) <= MAX_GAP:
            raise ValueError(
                f"`{name}`: the garment lies {float(gap):.3g} m away from the body, and "
                f"turned +90 degrees about X it lies on it: it looks modelled Y-up, and "
                f"garmentgnn is Z-up; rotate it +90 degrees about X ((x, y, z) -> "
                f"(x, -z, y); Blender's OBJ export: Forward -Y, Up Z)")
        shift = ((blo + bhi) / 2 - (lo + hi) / 2).tolist()
        raise ValueError(f"`{name}`: the garment lies {float(gap):.3g} m away from the body "
                         f"(bounding boxes); it must be modelled around the body in its rest "
                         f"pose: translate it by about ({shift[0]:.3g}, {shift[1]:.3g}, "
                         f"{shift[2]:.3g}) m")
