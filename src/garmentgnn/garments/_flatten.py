"""Flattening of garment panels into a sewing pattern and per-face-corner material UVs.

Pipeline (used by the procedural templates):

1. every face carries a panel id and an *initial* pattern coordinate for each of its
   corners (arc length around / length along the part, from the template);
2. corners of the same vertex, in the same panel, with the same initial UV are one
   *pattern vertex*; anything else is a seam (panel borders, and the cut that opens a
   closed tube);
3. each panel is flattened with ARAP (as-rigid-as-possible, Liu et al. 2008,
   local/global iterations with cotangent weights), which is exact (zero distortion)
   for developable panels (cylinders, cones, generalised cylinders) and spreads the
   small unavoidable distortion elsewhere; the result is rigidly re-aligned to the
   initial layout, so ``u`` runs around and ``v`` along the part, and panels are laid
   side by side;
4. ``face_uv`` is, per face, the rest 3D triangle laid flat and rigidly aligned
   (rotation + translation, best fit) to its pattern triangle.  So the rest deformation
   gradient of Eq. 14 is a rotation for every face (zero rest stretch and shear), and
   wherever the pattern is developable ``face_uv`` *equals* the pattern coordinates.
"""
from __future__ import annotations

from typing import Tuple

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.linalg import splu

from garmentgnn.geometry import face_cotangents
from garmentgnn.geometry import flat_triangles as _geometry_flat_triangles


def flat_triangles(tri: np.ndarray) -> np.ndarray:
    """:func:`garmentgnn.geometry.flat_triangles` on numpy float64 ``[F, 3, 3]``."""
    return _geometry_flat_triangles(torch.as_tensor(np.asarray(tri, np.float64))).numpy()


def rigid_align(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Per-triangle best rotation + translation of ``src [F, 3, 2]`` onto ``dst``
    (no reflection); returns the moved ``src``."""
    cs, cd = src.mean(1, keepdims=True), dst.mean(1, keepdims=True)
    a, b = src - cs, dst - cd
    dot = (a * b).sum((1, 2))
    cross = (a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]).sum(1)
    ang = np.arctan2(cross, dot)
    c, s = np.cos(ang)[:, None], np.sin(ang)[:, None]
    rx = c * a[..., 0] - s * a[..., 1]
    ry = s * a[..., 0] + c * a[..., 1]
    return np.stack([rx, ry], -1) + cd


def pattern_vertices(faces: np.ndarray, panel: np.ndarray, init_uv: np.ndarray,
                     decimals: int = 9) -> Tuple[np.ndarray, int]:
    """Group face corners into pattern vertices.  Returns ``(corner_to_pattern [F, 3],
    number of pattern vertices)``."""
    F = len(faces)
    key = np.concatenate([faces.reshape(-1, 1).astype(np.float64),
                          np.repeat(panel, 3).reshape(-1, 1).astype(np.float64),
                          np.round(init_uv.reshape(-1, 2), decimals)], 1)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.reshape(F, 3)
    return inv, int(inv.max()) + 1


def arap_flatten(tri3d: np.ndarray, corner: np.ndarray, n: int, init: np.ndarray,
                 panel_of_vertex: np.ndarray, iterations: int = 100, tol: float = 1e-7
                 ) -> np.ndarray:
    """ARAP parameterisation of a cut mesh (Liu et al. 2008, local/global).

    Args:
        tri3d: ``[F, 3, 3]`` rest triangles.
        corner: ``[F, 3]`` pattern-vertex index of every corner.
        n: number of pattern vertices.
        init: ``[n, 2]`` initial pattern coordinates.
        panel_of_vertex: ``[n]`` panel id (one vertex per panel is pinned).
        iterations: at most this many local/global steps; stops earlier when no vertex
            moves more than ``tol`` metres.
    """
    F = len(tri3d)
    flat = flat_triangles(tri3d)
    # corner cotangents of the rest triangles (= of their flat copies): weights of the
    # edge opposite each corner
    cot = face_cotangents(torch.from_numpy(np.ascontiguousarray(tri3d, dtype=np.float64)
                                           ).reshape(-1, 3), torch.arange(3 * F).view(F, 3))
    cot = np.clip(cot.numpy(), 1e-3, 1e3)
    # edge k = (k+1 -> k+2)
    I = np.stack([corner[:, 1], corner[:, 2], corner[:, 0]], 1)  # noqa: E741
    J = np.stack([corner[:, 2], corner[:, 0], corner[:, 1]], 1)
    W = 0.5 * cot
    rows = np.concatenate([I.ravel(), J.ravel(), I.ravel(), J.ravel()])
    cols = np.concatenate([I.ravel(), J.ravel(), J.ravel(), I.ravel()])
    vals = np.concatenate([W.ravel(), W.ravel(), -W.ravel(), -W.ravel()])
    L = sp.csr_matrix((vals, (rows, cols)), shape=(n, n))
    # rhs assembly b = K @ (rotated rest edges): +w at I, -w at J
    e_idx = np.arange(3 * F)
    K = sp.csr_matrix((np.concatenate([W.ravel(), -W.ravel()]),
                       (np.concatenate([I.ravel(), J.ravel()]), np.concatenate([e_idx, e_idx]))),
                      shape=(n, 3 * F))
    ex = np.stack([flat[:, 1] - flat[:, 2], flat[:, 2] - flat[:, 0], flat[:, 0] - flat[:, 1]], 1)
    _, pin = np.unique(panel_of_vertex, return_index=True)
    free = np.ones(n, bool)
    free[pin] = False
    fi = np.nonzero(free)[0]
    Lff = L[fi][:, fi].tocsc()
    Lfp = L[fi][:, pin]
    lu = splu(Lff)
    u = init.astype(np.float64).copy()
    for _ in range(iterations):
        eu = u[I] - u[J]  # [F, 3, 2] current edges
        dot = (cot * (ex * eu).sum(-1)).sum(1)
        crs = (cot * (ex[..., 0] * eu[..., 1] - ex[..., 1] * eu[..., 0])).sum(1)
        ang = np.arctan2(crs, dot)
        c, s = np.cos(ang)[:, None], np.sin(ang)[:, None]
        rx = np.stack([c * ex[..., 0] - s * ex[..., 1], s * ex[..., 0] + c * ex[..., 1]], -1)
        b = K @ rx.reshape(-1, 2)
        new = lu.solve(b[fi] - Lfp @ u[pin])
        step = np.abs(new - u[fi]).max() if len(fi) else 0.0
        u[fi] = new
        if step < tol:
            break
    return u


def _procrustes(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Rigidly move point set ``src`` onto ``dst`` (rotation + translation)."""
    cs, cd = src.mean(0), dst.mean(0)
    a, b = src - cs, dst - cd
    dot = (a * b).sum()
    crs = (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]).sum()
    ang = np.arctan2(crs, dot)
    R = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    return a @ R.T + cd


def build_pattern(vertices: np.ndarray, faces: np.ndarray, panel: np.ndarray,
                  init_uv: np.ndarray, iterations: int = 100, gap: float = 0.05
                  ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pattern and material coordinates of a garment.

    Args:
        vertices: ``[V, 3]`` rest positions.
        faces: ``[F, 3]``.
        panel: ``[F]`` panel id per face.
        init_uv: ``[F, 3, 2]`` initial pattern coordinates per face corner (metres).

    Returns:
        ``(uv [V, 2], face_uv [F, 3, 2], pattern_uv [F, 3, 2])``: per-vertex UV (the
        ``face_uv`` of the vertex's first face corner), the material coordinates for
        Eq. 14 (isometric per face, see module doc) and the continuous ARAP pattern per
        face corner.
    """
    tri = vertices[faces]
    corner, n = pattern_vertices(faces, panel, init_uv)
    init = np.zeros((n, 2))
    init[corner.reshape(-1)] = init_uv.reshape(-1, 2)
    pv_panel = np.zeros(n, dtype=np.int64)
    pv_panel[corner.reshape(-1)] = np.repeat(panel, 3)
    u = arap_flatten(tri, corner, n, init, pv_panel, iterations)
    # re-align each panel to its initial layout, then lay panels out side by side
    x0 = 0.0
    for p in np.unique(pv_panel):
        m = pv_panel == p
        u[m] = _procrustes(u[m], init[m])
        u[m] -= np.array([u[m, 0].min() - x0, u[m, 1].min()])
        x0 = u[m, 0].max() + gap
    pattern = u[corner]
    face_uv = rigid_align(flat_triangles(tri), pattern)
    return first_corner_uv(faces, face_uv, len(vertices)), face_uv, pattern


def first_corner_uv(faces: np.ndarray, corner_uv: np.ndarray, n: int) -> np.ndarray:
    """Per-vertex UV = the UV of the vertex's first face corner (row-major order)."""
    fl = faces.reshape(-1)
    first = np.full(n, -1)
    idx = np.arange(len(fl))[::-1]
    first[fl[idx]] = idx  # the smallest corner index is written last and wins
    uv = np.zeros((n, 2))
    has = first >= 0
    uv[has] = corner_uv.reshape(-1, 2)[first[has]]
    return uv
