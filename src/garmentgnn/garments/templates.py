"""Procedural garments sized from the body they are made for.

Every template builds one connected, consistently oriented, manifold triangle mesh
around the rest body (Z up, facing -Y, metres) out of structured quad strips:

* tubes are stacks of rings of vertices; a ring can *split* (trousers: the ring at the
  crotch is cut by a crotch seam into the two leg openings) and the front/back panels of
  a top rise from the armpit ring to the shoulder seams, leaving a neck hole and two
  armholes; a sleeve's first ring *is* its armhole loop -- parts always share the seam
  vertices, so there are no T-junctions;
* sizes come from the body: horizontal cross-sections (convex hull of the torso surface
  in a height band, grown by ``ease``), limb radii around the bones, the armpit height
  (highest ring that clears the arms), the crotch height (highest level where the legs
  are far enough apart), the neck (narrowest level between the neck and head joints) --
  so one template fits thin, regular and fat bodies;
* placement: after building, every vertex closer than ``margin`` to the body (or inside)
  is moved out along the direction away from its closest body point (repeated), using an
  exact point-to-mesh distance (:mod:`garmentgnn.garments._distance`).  The design
  itself keeps about ``ease`` of room, so pushes are rare;
* material coordinates: see :mod:`garmentgnn.garments._flatten` and
  :class:`~garmentgnn.garments.Garment`.  Each panel (pattern piece) is flattened with
  ARAP into a sewing pattern; ``face_uv`` is every rest triangle laid flat and rigidly
  fitted to that pattern, so the rest stretch/shear of Eq. 12-14 is exactly zero and,
  wherever the panel is developable, ``face_uv`` *is* the pattern (continuous across
  edges).  Skirts are stacks of cones over the waist section with one panel per cone
  (yoke above the hips, skirt below), i.e. exactly developable: their pattern is the
  unrolled annular sectors.  Doubly curved transitions (sleeve caps, the crotch, the
  shoulders) cannot be flattened exactly; there ``face_uv`` stays exact per face and is
  discontinuous across edges by up to a few millimetres.
* panels: skirt -- cones, cut at the centre back; trousers -- waist tube and one panel
  per leg (cut along the inseam); tops -- front, back (side seams, shoulder seams) and
  one per sleeve (cut along the underarm); dress with straps -- skirt cones, bodice,
  one per strap.  ``Garment.panel`` holds the panel id of every face.

``resolution``: ``"low"`` (~1,000 vertices), ``"medium"`` (~4,000), ``"high"``
(~16,000, i.e. at least the 14K of the paper's largest garments) or an int target
vertex count.  The mesh spacing ``h`` is chosen as ``h = h0 * sqrt(V0 / target)`` from a
coarse trial build (vertex count ~ area / h^2), so the count lands within ~10% of the
target.

Modules: body measurements live in :mod:`garmentgnn.garments._measure`, the parts
(pattern construction) in :mod:`garmentgnn.garments._parts`; this module sizes the
mesh, assembles, places and flattens it, and holds the public builders.
"""
from __future__ import annotations

import logging
from typing import Callable, Dict, Optional, Union

import numpy as np
import torch

from garmentgnn.garments._fit import L_LEG, R_LEG, TORSO, BodyFit, MeshBuilder
from garmentgnn.garments._flatten import build_pattern
from garmentgnn.garments._measure import (SKIRT_LENGTHS, TROUSER_LENGTHS, Length, armpit_height,
                                          crotch_height, hem_height, ring_perimeter, section_ring,
                                          torso_section, waist_height)
from garmentgnn.garments._parts import (add_legs, skirt_rings, add_sleeve, add_straps, torso_rings,
                                        tube_grid, add_upper_body)
from garmentgnn.garments.garment import Garment

log = logging.getLogger(__name__)

RESOLUTIONS: Dict[str, int] = {"low": 1000, "medium": 4000, "high": 16000}
#: skirt flare presets: horizontal growth of the radius per metre of length
FLARES: Dict[str, float] = {"pencil": 0.0, "straight": 0.0, "a-line": 0.25, "flared": 0.5,
                            "full": 0.9}
SLEEVES = ("none", "short", "elbow", "long")


def _target(resolution: Union[str, int]) -> int:
    if isinstance(resolution, str):
        if resolution not in RESOLUTIONS:
            raise ValueError(f"`resolution`: unknown preset {resolution!r}; use one of "
                             f"{list(RESOLUTIONS)} or a target vertex count")
        return RESOLUTIONS[resolution]
    n = int(resolution)
    if n < 200 or n > 200_000:
        raise ValueError(f"`resolution`: target vertex count must lie in [200, 200000], got {n}")
    return n


def _check_common(ease: float, margin: float) -> None:
    if not np.isfinite(ease) or ease < 0:
        raise ValueError(f"`ease`: must be a non-negative number of metres, got {ease}")
    if not np.isfinite(margin) or margin < 0:
        raise ValueError(f"`margin`: must be a non-negative number of metres, got {margin}")


# ---------------------------------------------------------------------------------------
# assembly
# ---------------------------------------------------------------------------------------
def _finish(fit: BodyFit, B: MeshBuilder, margin: float, kind: str, name: str,
            pinned: Optional[np.ndarray] = None, info: Optional[dict] = None) -> Garment:
    V, F, panel, init_uv, part = B.arrays()
    _orient(V, F, init_uv, part, fit)
    used = np.zeros(len(V), bool)
    used[F.reshape(-1)] = True
    if not used.all():  # should not happen; keep the mesh clean anyway
        remap = np.cumsum(used) - 1
        V, F = V[used], remap[F]
        if pinned is not None:
            pinned = pinned[used]
    V, moved = _place(fit, V, F, margin)
    uv, face_uv, _ = build_pattern(V, F, panel, init_uv)
    inf = dict(info or {})
    inf["pushed_vertices"] = moved
    return Garment(vertices=torch.tensor(V, dtype=torch.float32),
                   faces=torch.tensor(F, dtype=torch.long),
                   uv=torch.tensor(uv, dtype=torch.float32),
                   face_uv=torch.tensor(face_uv, dtype=torch.float32),
                   name=name, kind=kind,
                   pinned=None if pinned is None else torch.tensor(pinned),
                   panel=torch.tensor(panel, dtype=torch.long), info=inf)


def _orient(V, F, init_uv, part, fit: BodyFit) -> None:
    """Make the winding consistent across parts (a part sharing an edge with an earlier
    part in the same direction is flipped), then make the normals point away from the
    body overall.  In place."""
    done: Dict[tuple, int] = {}
    for p in np.unique(part):
        m = np.nonzero(part == p)[0]
        E = np.concatenate([F[m][:, [0, 1]], F[m][:, [1, 2]], F[m][:, [2, 0]]])
        same = sum(1 for e in map(tuple, E) if e in done)
        opp = sum(1 for e in E[:, ::-1] if tuple(e) in done)
        if same > opp:
            F[m] = F[m][:, ::-1]
            init_uv[m] = init_uv[m][:, ::-1]
            E = E[:, ::-1]
        for e in map(tuple, E):
            done[e] = p
    cen = V[F].mean(1)
    nrm = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    _, near = fit.tree(range(6)).query(cen)
    if np.einsum("ij,ij->i", nrm, cen - fit.samples[near]).sum() < 0:
        F[:] = F[:, ::-1]
        init_uv[:] = init_uv[:, ::-1]


def _place(fit: BodyFit, V: np.ndarray, F: np.ndarray, margin: float, rounds: int = 3):
    """Push vertices out to ``margin`` from the body; pushed vertices are then relaxed
    towards their neighbours (removes kinks and vertices pushed onto one spot) and the
    push repeated."""
    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    E = np.concatenate([E, E[:, ::-1]])
    deg = np.bincount(E[:, 0], minlength=len(V)).astype(np.float64)
    ever = np.zeros(len(V), bool)
    for r in range(rounds):
        V2, _ = fit.dist.push_out(V, margin)
        moved = np.linalg.norm(V2 - V, axis=1) > 0
        V = V2
        ever |= moved
        if not moved.any() or r == rounds - 1:
            break
        # relax the pushed vertices and their neighbours a little
        zone = moved.copy()
        zone[E[np.isin(E[:, 0], np.nonzero(moved)[0]), 1]] = True
        avg = np.zeros_like(V)
        np.add.at(avg, E[:, 0], V[E[:, 1]])
        avg /= np.maximum(deg, 1)[:, None]
        V[zone] = 0.5 * V[zone] + 0.5 * avg[zone]
    return V, int(ever.sum())


def _at_resolution(build: Callable[[float], MeshBuilder], target: int):
    h0 = 0.05
    b = build(h0)
    h = h0 * np.sqrt(b.n / target)
    for _ in range(2):
        b = build(h)
        ratio = b.n / target
        if abs(ratio - 1) < 0.08:
            break
        h *= np.sqrt(ratio)
    return b, h


def _flare_value(flare) -> float:
    if isinstance(flare, str):
        if flare not in FLARES:
            raise ValueError(f"`flare`: unknown preset {flare!r}; use one of {list(FLARES)} "
                             "or a non-negative number (radius growth per metre of length)")
        return FLARES[flare]
    f = float(flare)
    if not np.isfinite(f) or f < 0:
        raise ValueError(f"`flare`: must be >= 0, got {flare}")
    return f


def skirt(body, length: Length = "knee", flare: Union[str, float] = "a-line",
          resolution: Union[str, int] = "medium", ease: float = 0.02, margin: float = 0.01,
          name: str = "skirt") -> Garment:
    """A skirt hanging from the natural waist.

    Args:
        body: a rest :class:`~garmentgnn.body.Body` with the standard roles.
        length: ``"mini" | "knee" | "midi" | "long"`` (hem height from the leg joints) or
            metres from the waist down.
        flare: ``"pencil"/"straight" (0) | "a-line" (0.25) | "flared" (0.5) | "full" (0.9)``
            or a number: growth of the radius per metre of length; the skirt is always at
            least as wide as the hips/legs need (plus ``ease``).
        resolution: see the module doc.
        ease: room between body and garment by design (metres).
        margin: minimum clearance enforced after building (metres).

    The waistband ring is ``pinned``.
    """
    _check_common(ease, margin)
    fit = BodyFit.of(body)
    f = _flare_value(flare)
    z_w = waist_height(fit)
    z_hem = hem_height(fit, length, z_w, "skirt", SKIRT_LENGTHS)
    if z_hem >= z_w - 0.05:
        raise ValueError(f"`length`: hem at {z_hem:.3f} m is not below the waist ({z_w:.3f} m)")
    top_n = {}

    def build(h):
        B = MeshBuilder()
        rings, Q, _, corners = skirt_rings(fit, z_w, z_hem, f, ease, h)
        idx = B.add(rings)
        # one panel per cone of the profile (a yoke above the hips, the skirt below),
        # each cut at the centre back
        cuts = [0] + corners + [len(rings) - 1]
        for p, (a, b) in enumerate(zip(cuts[:-1], cuts[1:])):
            tube_grid(B, idx[a:b + 1], rings[a:b + 1], p, seam=Q)
        top_n["top"] = idx[-1]
        return B

    B, h = _at_resolution(build, _target(resolution))
    pinned = np.zeros(B.n, bool)
    pinned[top_n["top"]] = True
    return _finish(fit, B, margin, "skirt", name, pinned,
                   {"spacing": h, "waist_z": z_w, "hem_z": z_hem, "flare": f})


def trousers(body, length: Length = "long", resolution: Union[str, int] = "medium",
             ease: float = 0.02, margin: float = 0.01, name: str = "trousers") -> Garment:
    """Trousers: a waist tube down to the crotch, where its last ring splits (the crotch
    seam) into the two leg openings, then one tube per leg.

    ``length``: ``"shorts" | "knee" | "capri" | "long"`` or metres from the waist.  The
    crotch is placed at the highest level where a seam fits between the legs with
    ``margin`` (on bodies whose thighs touch, that is low: the garment stays
    collision-free rather than pretending).  The waistband ring is ``pinned``.
    """
    _check_common(ease, margin)
    fit = BodyFit.of(body)
    z_w = waist_height(fit)
    z_hem = hem_height(fit, length, z_w, "trouser", TROUSER_LENGTHS)
    cx = float(fit.J["pelvis"][0])
    z_c = crotch_height(fit, ease, margin, cx)
    if z_hem >= z_c - 0.05:
        raise ValueError(f"`length`: hem at {z_hem:.3f} m is not below the crotch "
                         f"({z_c:.3f} m) on this body")
    top_n = {}

    def build(h):
        B = MeshBuilder()
        poly, c = torso_section(fit, z_w - 0.03, z_w + 0.03, [TORSO], ease)
        Q = max(3, int(round(ring_perimeter(section_ring(poly, c, 8, z_w)) / 4 / h)))
        rings = torso_rings(fit, z_c, z_w, Q, h, ease, [TORSO, L_LEG, R_LEG], loose=False)
        # a waist tube must not narrow downwards (it would cut under the buttocks)
        rings = _monotone_down(rings)
        idx = B.add(rings)
        tube_grid(B, idx, rings, 0, seam=Q)
        add_legs(fit, B, idx[0], Q, z_c, z_hem, h, ease, (1, 2), cx)
        top_n["top"] = idx[-1]
        return B

    B, h = _at_resolution(build, _target(resolution))
    pinned = np.zeros(B.n, bool)
    pinned[top_n["top"]] = True
    return _finish(fit, B, margin, "trousers", name, pinned,
                   {"spacing": h, "waist_z": z_w, "crotch_z": z_c, "hem_z": z_hem})


def _monotone_down(rings: np.ndarray) -> np.ndarray:
    """Make each ring (bottom first) at least as wide, per column and about its centre,
    as the ring above it."""
    out = rings.copy()
    for j in range(len(out) - 2, -1, -1):
        c = out[j, :, :2].mean(0)
        ca = out[j + 1, :, :2].mean(0)
        r = np.linalg.norm(out[j, :, :2] - c, axis=1)
        ra = np.linalg.norm(out[j + 1, :, :2] - ca, axis=1)
        s = np.maximum(r, ra) / np.maximum(r, 1e-9)
        out[j, :, :2] = c + (out[j, :, :2] - c) * s[:, None]
    return out


def tshirt(body, sleeves: str = "short", length: Length = "hip", neckline: str = "crew",
           resolution: Union[str, int] = "medium", ease: float = 0.02, margin: float = 0.01,
           name: str = "tshirt") -> Garment:
    """A T-shirt: a torso tube from the hem up to the armpits, front and back panels up to
    the shoulder seams (neck hole between them), sleeves sewn into the armholes.

    Args:
        sleeves: ``"short" | "elbow" | "long" | "none"`` (``"none"``: a tank top).
        length: ``"hip"`` (just below the hip joints), ``"waist"`` or metres below the
            armpit.
        neckline: ``"crew" | "scoop"``.
    """
    return _top(body, "tshirt", sleeves, length, neckline, resolution, ease, margin, name)


def _top(body, kind, sleeves, length, neckline, resolution, ease, margin, name,
         bottom: str = "hem", legs_length: Length = "long", skirt_args=None):
    _check_common(ease, margin)
    if sleeves not in SLEEVES:
        raise ValueError(f"`sleeves`: use one of {SLEEVES}, got {sleeves!r}")
    if neckline not in ("crew", "scoop"):
        raise ValueError(f"`neckline`: use 'crew' or 'scoop', got {neckline!r}")
    fit = BodyFit.of(body)
    z_a = armpit_height(fit, ease, margin)
    z_w = waist_height(fit)
    cx = float(fit.J["pelvis"][0])
    info = {"armpit_z": z_a}
    if bottom == "hem":
        presets = {"hip": lambda f: min(f.J["l_hip"][2], f.J["r_hip"][2]) - 0.03,
                   "waist": lambda f: waist_height(f)}
        z_lo = hem_height(fit, length, z_a, "top", presets)
        if z_lo >= z_a - 0.05:
            raise ValueError(f"`length`: hem at {z_lo:.3f} m is not below the armpits")
    elif bottom == "legs":
        z_lo = crotch_height(fit, ease, margin, cx)
        z_hem = hem_height(fit, legs_length, z_w, "trouser", TROUSER_LENGTHS)
        if z_hem >= z_lo - 0.05:
            raise ValueError(f"`length`: hem at {z_hem:.3f} m is not below the crotch")
        info.update(crotch_z=z_lo, hem_z=z_hem)
    else:  # skirt below the waist (dress)
        z_lo = z_w
    info["bottom_z"] = z_lo

    def build(h):
        B = MeshBuilder()
        poly, c = torso_section(fit, z_a - 0.03, z_a + 0.02, [TORSO], ease)
        Q = max(4, int(round(ring_perimeter(section_ring(poly, c, 8, z_a)) / 4 / h)))
        if bottom == "skirt":
            z_hem, f = skirt_args
            srings, _, _, _ = skirt_rings(fit, z_w, z_hem, f, ease, h, Q=Q)
            upper = torso_rings(fit, z_w, z_a, Q, h, ease, [TORSO], loose=False)
            rings = np.concatenate([srings[:-1], upper], 0)
        else:
            labels = [TORSO, L_LEG, R_LEG] if bottom == "legs" else [TORSO]
            rings = torso_rings(fit, z_lo, z_a, Q, h, ease, labels, loose=(bottom == "hem"))
            if bottom == "legs":
                rings = _monotone_down(rings)
        idx = B.add(rings)
        loops = add_upper_body(fit, B, idx[-1], Q, h, ease, (0, 1), (idx, rings), (idx, rings),
                            neckline)
        if sleeves != "none":
            add_sleeve(fit, B, loops[0], "l", sleeves, h, ease, 2)
            add_sleeve(fit, B, loops[1], "r", sleeves, h, ease, 3)
        if bottom == "legs":
            add_legs(fit, B, idx[0], Q, z_lo, info["hem_z"], h, ease, (4, 5), cx)
        return B

    B, h = _at_resolution(build, _target(resolution))
    info["spacing"] = h
    return _finish(fit, B, margin, kind, name, None, info)


def dress(body, length: Length = "knee", flare: Union[str, float] = "a-line",
          top: str = "straps", sleeves: str = "none", neckline: str = "scoop",
          resolution: Union[str, int] = "medium", ease: float = 0.02, margin: float = 0.01,
          name: str = "dress") -> Garment:
    """A dress: a fitted bodice from the armpits to the waist, continued by a skirt (as in
    :func:`skirt`) below.

    Args:
        top: ``"straps"`` (two shoulder straps), ``"strapless"`` or ``"sleeveless"``
            (front/back panels up to the shoulders, like a T-shirt; then ``sleeves`` may
            add sleeves).
        length, flare: as for :func:`skirt`.
    """
    _check_common(ease, margin)
    if top not in ("straps", "strapless", "sleeveless"):
        raise ValueError(f"`top`: use 'straps', 'strapless' or 'sleeveless', got {top!r}")
    fit = BodyFit.of(body)
    f = _flare_value(flare)
    z_w = waist_height(fit)
    z_hem = hem_height(fit, length, z_w, "skirt", SKIRT_LENGTHS)
    if z_hem >= z_w - 0.05:
        raise ValueError(f"`length`: hem at {z_hem:.3f} m is not below the waist ({z_w:.3f} m)")
    if top == "sleeveless":
        return _top(body, "dress", sleeves, None, neckline, resolution, ease, margin, name,
                    bottom="skirt", skirt_args=(z_hem, f))
    if sleeves != "none":
        raise ValueError("`sleeves`: only a 'sleeveless' top can have sleeves")
    z_a = armpit_height(fit, ease, margin)

    def build(h):
        B = MeshBuilder()
        poly, c = torso_section(fit, z_a - 0.03, z_a + 0.02, [TORSO], ease)
        Q = max(4, int(round(ring_perimeter(section_ring(poly, c, 8, z_a)) / 4 / h)))
        Q += Q % 2
        srings, _, _, corners = skirt_rings(fit, z_w, z_hem, f, ease, h, Q=Q)
        upper = torso_rings(fit, z_w, z_a, Q, h, ease, [TORSO], loose=False)
        rings = np.concatenate([srings[:-1], upper], 0)
        idx = B.add(rings)
        # panels: the skirt's cones (as in `skirt`), the bodice; cut at the centre back
        cuts = [0] + corners + [len(srings) - 1, len(rings) - 1]
        for p, (a, b) in enumerate(zip(cuts[:-1], cuts[1:])):
            tube_grid(B, idx[a:b + 1], rings[a:b + 1], p, seam=Q)
        if top == "straps":
            add_straps(fit, B, idx[-1], Q, h, ease, (len(cuts) - 1, len(cuts)))
        return B

    B, h = _at_resolution(build, _target(resolution))
    return _finish(fit, B, margin, "dress", name, None,
                   {"spacing": h, "waist_z": z_w, "hem_z": z_hem, "armpit_z": z_a})



def jumpsuit(body, length: Length = "long", sleeves: str = "short",
             resolution: Union[str, int] = "medium", ease: float = 0.02, margin: float = 0.01,
             name: str = "jumpsuit") -> Garment:
    """A jumpsuit: the top of :func:`tshirt` (``sleeves`` may be ``"none"``) whose torso
    tube continues down to the crotch and splits into the legs of :func:`trousers`."""
    return _top(body, "jumpsuit", sleeves, None, "crew", resolution, ease, margin, name,
                bottom="legs", legs_length=length)


TEMPLATES = {"skirt": skirt, "dress": dress, "tshirt": tshirt, "trousers": trousers,
             "jumpsuit": jumpsuit}


def make_garment(kind: str, body, **kwargs) -> Garment:
    """Build a template by name (``TEMPLATES``)."""
    if kind not in TEMPLATES:
        raise ValueError(f"`kind`: unknown garment {kind!r}; use one of {list(TEMPLATES)}")
    if not (hasattr(body, "skeleton") and hasattr(body, "vertices")):
        raise TypeError(f"`body`: expected a Body (the garment is fitted to it), got "
                        f"{type(body).__name__}; e.g. garmentgnn.body.make_body('capsule')")
    return TEMPLATES[kind](body, **kwargs)
