"""GarTrans's unified objective (paper §3.4).

Supervised terms, per batch element, mean over frames:

* Eq. 7  ``L_vert = k_v / N sum_i |p_i - p_i^GT|``
* Eq. 8  ``L_edge = k_e |E - E^GT|^2`` (squared L2 norm over the unique edges; with
  ``edge_reduction="mean"`` divided by the edge count, which keeps the weight
  meaningful across mesh resolutions -- the paper does not say which it used)
* Eq. 9  ``L_norm = k_n / N sum_i (1 - n_i . n_i^GT)`` (vertex normals)

Physics terms reuse :mod:`garmentgnn.physics` (one definition shared with the
simulator) with the paper's weights as stiffnesses:

* Eq. 10 collision ``k_c sum_i |min(s(p_i) - eps, 0)|``
* Eq. 11 gravity ``-k_g sum_i m_i p_i . g``
* Eq. 12 stretch, Eq. 13 shear (``k_s``, ``k_h``)
* extra, off by default: bending and inertia;
* extra supervised term, off by default (not in the paper):
  ``L_curv = k_curv / N_int sum_i |K_i - K_i^GT|``, the angle defect (discrete Gaussian
  curvature) at interior vertices -- the E_curv metric itself
  (:func:`garmentgnn.geometry.angle_defect_difference`), the way Eqs. 8 and 9
  train toward E_len and the normal errors.

Paper weights: k_v 100, k_e 15, k_n 50; k_c 1.5, k_g 0.1, k_s 5, k_h 2.

``LossInputs.frame_mask`` leaves frames whose ground truth is not valid (the dataset's
``valid``: not converged, or the body through the cloth) out of the terms that compare
with it (the supervised ones and ``curv``): their mean runs over the kept frames only.
The physics terms, which never read the ground truth, keep every frame.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Dict, Iterable, Optional, Tuple

import torch
from torch import Tensor, nn

from garmentgnn.geometry import (NearestFaceCache, angle_defect_difference, edge_lengths,
                                 full_precision, signed_distance, unique_edges,
                                 vertex_normals)
from garmentgnn.physics import (
    COLLISION_MARGIN,
    ClothRest,
    bending_energy,
    collision_energy,
    gravity_energy,
    inertia_energy,
    shear_energy,
    stretch_energy,
)

PAPER_WEIGHTS: Dict[str, float] = {
    "vert": 100.0, "edge": 15.0, "norm": 50.0,
    "collision": 1.5, "gravity": 0.1, "stretch": 5.0, "shear": 2.0,
    "bending": 0.0, "inertia": 0.0, "curv": 0.0,
}
SUPERVISED = ("vert", "edge", "norm")
#: the terms that compare with the ground truth: the paper's supervised ones and ``curv``
NEEDS_GT = SUPERVISED + ("curv",)
PHYSICS = ("collision", "gravity", "stretch", "shear", "bending", "inertia")


class NonFiniteLossError(FloatingPointError):
    """A loss term became NaN/inf; the message names the term."""


def vertex_loss(pred: Tensor, gt: Tensor) -> Tensor:
    """Eq. 7 without its weight: mean vertex distance, ``[...]``."""
    return (pred - gt).norm(dim=-1).mean(-1)


def edge_loss(pred: Tensor, gt: Tensor, edges: Tensor, reduction: str = "sum") -> Tensor:
    """Eq. 8 without its weight: squared L2 norm of the edge-length differences."""
    d2 = (edge_lengths(pred, edges) - edge_lengths(gt, edges)) ** 2
    if reduction == "sum":
        return d2.sum(-1)
    if reduction == "mean":
        return d2.mean(-1)
    raise ValueError(f"`edge_reduction`: expected 'sum' or 'mean', got {reduction!r}")


def normal_loss(pred: Tensor, gt: Tensor, faces: Tensor) -> Tensor:
    """Eq. 9 without its weight: mean ``1 - cos`` between vertex normals."""
    return (1.0 - (vertex_normals(pred, faces) * vertex_normals(gt, faces)).sum(-1)).mean(-1)


@dataclass
class LossInputs:
    """What one batch of frames of one garment provides.

    ``pred``/``gt`` ``[T, V, 3]``; ``body_pos`` ``[T, Vb, 3]`` with ``body_faces``
    (``None`` for scenes without a body: collision is skipped); ``mass`` ``[V]``;
    ``rest`` from :meth:`ClothRest.from_mesh` (``None`` when the garment has no
    material coordinates: stretch/shear/bending are skipped); ``predicted`` the
    inertial prediction ``p_prev + dt v_prev`` for the inertia term; ``face_cache`` a
    :class:`~garmentgnn.geometry.NearestFaceCache` kept for this garment-body pair (the
    one the model's collision projection used on the same frames): the collision term's
    nearest-face search then runs through it, exact, instead of ``distance_candidates``.
    ``frame_mask`` ``[T]`` bool: the frames whose ``gt`` the supervised terms compare with
    (``None``: every frame); with none kept those terms are 0.
    """

    pred: Tensor
    faces: Tensor
    gt: Optional[Tensor] = None
    body_pos: Optional[Tensor] = None
    body_faces: Optional[Tensor] = None
    mass: Optional[Tensor] = None
    rest: Optional[ClothRest] = None
    predicted: Optional[Tensor] = None
    dt: float = 1.0 / 30.0
    face_cache: Optional[NearestFaceCache] = None
    frame_mask: Optional[Tensor] = None


def supervised_frames(inp: LossInputs) -> Tuple[Tensor, Optional[Tensor]]:
    """``(pred, gt)`` restricted to ``inp.frame_mask``'s frames (both whole without a
    mask); a mask that is not a ``[T]`` bool tensor is a ``ValueError``/``TypeError``."""
    m = inp.frame_mask
    if m is None:
        return inp.pred, inp.gt
    if not isinstance(m, Tensor):
        raise TypeError(f"`frame_mask`: expected a [T] bool tensor, got {type(m).__name__}")
    T = inp.pred.shape[0] if inp.pred.dim() == 3 else None
    if m.dtype != torch.bool or T is None or tuple(m.shape) != (T,):
        raise ValueError(f"`frame_mask`: expected a [{T}] bool mask of the frames of `pred` "
                         f"{tuple(inp.pred.shape)}, got {m.dtype} {tuple(m.shape)}; pass one "
                         f"flag per frame (the dataset's `valid`)")
    m = m.to(inp.pred.device)
    return inp.pred[m], None if inp.gt is None else inp.gt[m]


class GarTransLoss(nn.Module):
    """Weighted sum of the enabled terms; returns ``(total, {term: value})``.

    Args:
        weights: per-term weights (defaults: :data:`PAPER_WEIGHTS`).
        enabled: the active terms (the training schedule switches these).
        supervised_scale: multiplies the supervised terms (0.05 in the paper's
            second phase).
        collision_margin: ``epsilon`` of Eq. 10 in metres.
        edge_reduction: ``"sum"`` (the paper's Eq. 8 literally) or ``"mean"``.
        distance_candidates: body faces searched per garment vertex for the collision
            term (faces around the nearest body vertices, as in the simulator);
            ``None`` is the exact brute force -- measured 2.4 s of a 3.6 s training step
            at 280 garment x 2.5K body vertices x 8 frames.
        compile_search: run that search through ``torch.compile``
            (:func:`garmentgnn.geometry.signed_distance`'s ``compiled``).
    """

    def __init__(self, weights: Optional[Dict[str, float]] = None,
                 enabled: Iterable[str] = SUPERVISED, supervised_scale: float = 1.0,
                 collision_margin: float = COLLISION_MARGIN, edge_reduction: str = "sum",
                 distance_candidates: Optional[int] = 8, compile_search: bool = False) -> None:
        super().__init__()
        self.weights = dict(PAPER_WEIGHTS)
        if weights:
            unknown = set(weights) - set(PAPER_WEIGHTS)
            if unknown:
                raise ValueError(f"`weights`: unknown term(s) {sorted(unknown)}; known: "
                                 f"{sorted(PAPER_WEIGHTS)}")
            self.weights.update(weights)
        self.enabled = set()
        self.set_enabled(enabled)
        self.supervised_scale = supervised_scale
        self.collision_margin = collision_margin
        self.edge_reduction = edge_reduction
        self.distance_candidates = distance_candidates
        self.compile_search = compile_search
        self._edges: Optional[tuple] = None  # (faces tensor, its unique edges)

    def set_enabled(self, terms: Iterable[str]) -> None:
        terms = set(terms)
        unknown = terms - set(PAPER_WEIGHTS)
        if unknown:
            raise ValueError(f"`enabled`: unknown term(s) {sorted(unknown)}; known: "
                             f"{sorted(PAPER_WEIGHTS)}")
        self.enabled = terms

    def _unique_edges(self, faces: Tensor, num_vertices: int) -> Tensor:
        # keyed by the faces object itself (holding it, so its id cannot be reused)
        if self._edges is None or self._edges[0] is not faces:
            self._edges = (faces, unique_edges(faces, num_vertices).edges)
        return self._edges[1]

    def _cached_distance(self, inp: LossInputs) -> Optional[Tensor]:
        """``s(pred)`` through ``inp.face_cache`` (``None`` without one)."""
        if inp.face_cache is None:
            return None
        return signed_distance(inp.pred, inp.body_pos, inp.body_faces, cache=inp.face_cache,
                               compiled=self.compile_search).distance

    def forward(self, inp: LossInputs):
        """``(total, terms)``, in float32 also under autocast (a low-precision ``pred`` or
        ``predicted`` is cast up; the energies' products stay float32)."""
        with full_precision(inp.pred) as up:
            return self._forward(replace(inp, pred=up(inp.pred), predicted=None if
                                         inp.predicted is None else up(inp.predicted)))

    def _forward(self, inp: LossInputs):
        w = self.weights
        pred = inp.pred
        need_gt = self.enabled & set(NEEDS_GT)
        if need_gt and inp.gt is None:
            raise ValueError(f"`gt`: supervised term(s) {sorted(need_gt)} need ground truth")
        if "gravity" in self.enabled and inp.mass is None:
            raise ValueError("`mass`: the gravity term (Eq. 11) needs vertex masses")
        s = self.supervised_scale
        sp, sg = supervised_frames(inp)
        fns = {
            "vert": lambda: s * w["vert"] * vertex_loss(sp, sg).mean(),
            "edge": lambda: s * w["edge"] * edge_loss(
                sp, sg, self._unique_edges(inp.faces, pred.shape[-2]),
                self.edge_reduction).mean(),
            "norm": lambda: s * w["norm"] * normal_loss(sp, sg, inp.faces).mean(),
            "curv": lambda: s * w["curv"] * angle_defect_difference(sp, sg, inp.faces).mean(),
            "collision": lambda: collision_energy(pred, inp.body_pos, inp.body_faces,
                                                  self.collision_margin, w["collision"],
                                                  power=1, distance=self._cached_distance(inp),
                                                  candidates=self.distance_candidates,
                                                  compiled=self.compile_search).mean(),
            "gravity": lambda: w["gravity"] * gravity_energy(pred, inp.mass).mean(),
            "stretch": lambda: stretch_energy(pred, inp.rest, w["stretch"]).mean(),
            "shear": lambda: shear_energy(pred, inp.rest, w["shear"]).mean(),
            "bending": lambda: bending_energy(pred, inp.rest, w["bending"]).mean(),
            "inertia": lambda: w["inertia"] * inertia_energy(pred, inp.predicted, inp.mass,
                                                             inp.dt).mean(),
        }
        if sp.shape[0] == 0:  # no frame with valid ground truth: those terms are 0
            for name in NEEDS_GT:
                fns[name] = lambda: pred.sum() * 0.0
        skip = set()
        if inp.body_pos is None:
            skip.add("collision")  # no body in the scene
        if inp.rest is None:
            skip |= {"stretch", "shear", "bending"}  # no material coordinates
        if inp.predicted is None or inp.mass is None:
            skip.add("inertia")
        terms: Dict[str, Tensor] = {}
        for name in PAPER_WEIGHTS:  # fixed order: the first bad term is the one named
            if name in self.enabled and name not in skip:
                terms[name] = self._term(name, fns[name])
        total = sum(terms.values()) if terms else pred.sum() * 0.0
        return total, terms

    @staticmethod
    def _term(name: str, fn) -> Tensor:
        """Evaluate one term; NaN/inf (or geometry refusing NaN input) names the term."""
        try:
            value = fn()
        except ValueError as err:
            if "nan" in str(err).lower() or "inf" in str(err).lower():
                raise NonFiniteLossError(f"loss term {name!r} is non-finite ({err}); check "
                                         "the prediction and inputs of this term") from err
            raise
        if not math.isfinite(float(value.detach())):
            raise NonFiniteLossError(f"loss term {name!r} is {float(value.detach())}; "
                                     "check the prediction and inputs of this term")
        return value
