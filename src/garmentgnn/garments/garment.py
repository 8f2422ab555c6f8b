"""The rest-state garment: mesh on the body plus its material (sewing-pattern) coordinates.

UV convention (read this before writing stretch/shear code, GarTrans Eqs. 12-14):

* ``face_uv [F, 3, 2]`` -- **per face corner**, in metres -- is what Eq. 14 must use:
  ``(W^u W^v) = (p_j - p_i, p_k - p_i) @ inv([[u_j - u_i, u_k - u_i], [v_j - v_i, v_k - v_i]])``
  with ``(u, v)`` of corner ``c`` of face ``f`` = ``face_uv[f, c]``.  For the procedural
  templates and for the loader's fallback, every rest triangle is congruent to its UV
  triangle, so the rest deformation gradient is a rotation (singular values 1: zero
  rest stretch and shear).  ``u`` runs around the body part and ``v`` along it
  (towards the top / the body), so ``W^u`` / ``W^v`` are the weft / warp directions.
  With :func:`garmentgnn.geometry.uv_deformation_gradient` pass
  ``uv=face_uv.reshape(-1, 2), uv_faces=arange(3F).view(F, 3)`` or use
  :meth:`Garment.uv_layout`.
* ``uv [V, 2]`` -- per vertex -- is ``face_uv`` at the vertex's first face corner (in
  face order).  A vertex on a seam (a panel border, or the cut that opens a closed tube)
  has one pattern position per side and ``uv`` keeps one of them, so per-vertex ``uv``
  is *wrong* for faces along seams: use it for features and pictures, not for Eq. 14.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Tuple

import numpy as np
import torch
from torch import Tensor

from garmentgnn.geometry.uv import deformation_gradient as geometry_deformation_gradient
from garmentgnn.geometry.uv import uv_rest_frame

KINDS = ("skirt", "dress", "tshirt", "trousers", "jumpsuit", "other")


def _as(t, dtype) -> Tensor:
    return torch.as_tensor(np.asarray(t) if not isinstance(t, Tensor) else t).to(dtype)


@dataclass
class Garment:
    """A garment mesh in its rest state, placed on (around) a body.

    Attributes:
        vertices: ``[V, 3]`` float32 rest positions (Z up, metres; same frame as the body).
        faces: ``[F, 3]`` long, counter-clockwise seen from outside (normals point away
            from the body for the templates).
        uv: ``[V, 2]`` float32 per-vertex pattern coordinates in metres (see module doc:
            ambiguous on seams).
        info: free-form build/load report (template measurements such as ``waist_z``,
            ``pushed_vertices``; loader ``repair`` counts, ``uv`` source, ``uv_scale``).
        face_uv: ``[F, 3, 2]`` float32 per-face-corner material coordinates in metres;
            the ones Eq. 14 uses.  Defaults to ``uv[faces]``.
        name: free-form name.
        kind: one of :data:`KINDS`.
        pinned: optional ``[V]`` bool mask of vertices fixed to the body (e.g. a waistband).
        panel: optional ``[F]`` long panel (pattern piece) id per face.
    """

    vertices: Tensor
    faces: Tensor
    uv: Tensor
    face_uv: Optional[Tensor] = None
    name: str = "garment"
    kind: str = "other"
    pinned: Optional[Tensor] = None
    panel: Optional[Tensor] = None
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.vertices = _as(self.vertices, torch.float32)
        self.faces = _as(self.faces, torch.long)
        self.uv = _as(self.uv, torch.float32)
        v, f = self.vertices, self.faces
        if v.dim() != 2 or v.shape[1] != 3 or v.shape[0] == 0:
            raise ValueError(f"Garment {self.name!r}: `vertices` must be a non-empty [V, 3], "
                             f"got {tuple(v.shape)}")
        if f.dim() != 2 or f.shape[1] != 3 or f.shape[0] == 0:
            raise ValueError(f"Garment {self.name!r}: `faces` must be a non-empty [F, 3], "
                             f"got {tuple(f.shape)}")
        V = v.shape[0]
        if not torch.isfinite(v).all():
            raise ValueError(f"Garment {self.name!r}: `vertices` contain NaN/inf")
        if int(f.min()) < 0 or int(f.max()) >= V:
            raise ValueError(f"Garment {self.name!r}: `faces` index outside [0, {V}) "
                             f"(min {int(f.min())}, max {int(f.max())})")
        if self.uv.shape != (V, 2):
            raise ValueError(f"Garment {self.name!r}: `uv` must be [{V}, 2], got "
                             f"{tuple(self.uv.shape)}")
        if not torch.isfinite(self.uv).all():
            raise ValueError(f"Garment {self.name!r}: `uv` contains NaN/inf")
        if self.face_uv is None:
            self.face_uv = self.uv[f]
        self.face_uv = _as(self.face_uv, torch.float32)
        if self.face_uv.shape != (f.shape[0], 3, 2):
            raise ValueError(f"Garment {self.name!r}: `face_uv` must be [{f.shape[0]}, 3, 2], "
                             f"got {tuple(self.face_uv.shape)}")
        if not torch.isfinite(self.face_uv).all():
            raise ValueError(f"Garment {self.name!r}: `face_uv` contains NaN/inf")
        if self.kind not in KINDS:
            raise ValueError(f"Garment {self.name!r}: unknown kind {self.kind!r}; use one of "
                             f"{KINDS}")
        if self.pinned is not None:
            self.pinned = _as(self.pinned, torch.bool)
            if self.pinned.shape != (V,):
                raise ValueError(f"Garment {self.name!r}: `pinned` must be [{V}] bool, got "
                                 f"{tuple(self.pinned.shape)}")
        if self.panel is not None:
            self.panel = _as(self.panel, torch.long)
            if self.panel.shape != (f.shape[0],):
                raise ValueError(f"Garment {self.name!r}: `panel` must be [{f.shape[0]}], got "
                                 f"{tuple(self.panel.shape)}")

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    def uv_layout(self, decimals: int = 6) -> Tuple[Tensor, Tensor]:
        """``face_uv`` as shared UV vertices and UV faces (as an OBJ's ``vt``/``f a/t``):
        ``(uv_coords [T, 2], uv_faces [F, 3])``; corners whose coordinates agree to
        ``10**-decimals`` m share a UV vertex."""
        flat = self.face_uv.reshape(-1, 2).double().numpy()
        key = np.round(flat, decimals)
        _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
        coords = torch.as_tensor(flat[first], dtype=torch.float32)
        return coords, torch.as_tensor(inv.reshape(-1, 3), dtype=torch.long)

    def rest_frame(self) -> Tuple[Tensor, Tensor]:
        """Eq. 14's rest quantities from ``face_uv``: ``(Dm_inv [F, 2, 2], uv_area [F])``
        with ``Dm = [[du1, du2], [dv1, dv2]]``, so ``(W^u W^v) = (dp1 dp2) @ Dm_inv``
        (:func:`garmentgnn.geometry.uv_rest_frame`; zero-area UV faces get 0, not inf)."""
        F = self.faces.shape[0]
        frame = uv_rest_frame(self.face_uv.reshape(-1, 2), torch.arange(3 * F).view(F, 3))
        return frame.inverse, frame.area

    def deformation_gradient(self, positions: Optional[Tensor] = None) -> Tensor:
        """``[..., F, 3, 2]`` = ``(W^u W^v)`` of Eq. 14 for ``positions [..., V, 3]``
        (default: the rest vertices, where it is a rotation for the templates)."""
        p = self.vertices if positions is None else positions
        inv, _ = self.rest_frame()
        return geometry_deformation_gradient(p, self.faces, inv.to(p.dtype))

    def __repr__(self) -> str:
        return (f"Garment(name={self.name!r}, kind={self.kind!r}, V={self.num_vertices}, "
                f"F={self.num_faces})")
