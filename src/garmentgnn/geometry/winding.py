"""Inside test for closed triangle meshes by the winding number (ray crossings on an xy
grid): exact for a closed, outward-oriented body, and right where closed pieces overlap."""
from __future__ import annotations

from typing import Any, Optional, Union

import numpy as np
import torch
from torch import Tensor

from ._validate import check_points, numpy_mesh

__all__ = ["WindingNumber"]


class WindingNumber:
    """Inside test for closed triangle meshes: the winding number counted along a ray.

    From each query point ``p`` a ray goes up (+z); every face whose xy projection
    contains ``p``'s xy and which the ray meets above ``p`` counts ``+1`` if its normal
    points up and ``-1`` if down.  For a closed (every edge in exactly two faces),
    outward-oriented mesh this is the exact, integer winding number: 1 inside, 0
    outside; for several closed pieces that overlap (e.g. a body made of capsules) it
    is the number of pieces holding ``p``, so :meth:`inside` (``w != 0``) is right in
    the overlaps too, where the sign of the nearest face (or of
    :func:`signed_distance`) is relative to one piece.  Open meshes give meaningless
    counts.

    The faces are bucketed once on an xy grid of square cells of side ``cell``; a query
    tests only the faces of its cell.  Rays are shifted by a fixed ``(1.2e-9, 2.3e-9)``
    in xy so they miss the edges and vertices of grid-aligned meshes; points within
    about that distance of the surface may fall on either side.  numpy float64, not
    differentiable.

    Args:
        pos: ``[V, 3]`` vertex positions (tensor or array, one mesh).
        faces: ``[F, 3]`` faces, counter-clockwise seen from outside.
        cell: grid spacing in the units of ``pos``; defaults to the median xy extent
            of the faces.
    """

    def __init__(self, pos: Union[Tensor, np.ndarray], faces: Union[Tensor, np.ndarray],
                 cell: Optional[float] = None) -> None:
        v, f = numpy_mesh(pos, faces, "winding numbers are computed")
        tri = v[f]
        a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
        #: sign of the z component of each face normal (the crossing's direction)
        self._nz_sign = np.sign(np.cross(b - a, c - a)[:, 2])
        self._tri = tri
        lo = tri[:, :, :2].min(1)
        hi = tri[:, :, :2].max(1)
        if cell is None:
            cell = float(np.median((hi - lo).max(1)))
            if not np.isfinite(cell) or cell <= 0:
                cell = 1.0
        elif not (isinstance(cell, (int, float)) and np.isfinite(cell) and cell > 0):
            raise ValueError(f"`cell`: expected a positive grid spacing, got {cell!r}")
        cell = float(cell)
        self.cell = cell
        self._origin = lo.min(0) - cell
        i0 = np.floor((lo - self._origin) / cell).astype(np.int64)
        i1 = np.floor((hi - self._origin) / cell).astype(np.int64)
        self._ny = int(i1[:, 1].max()) + 2
        cells, fids = [], []
        span = i1 - i0 + 1
        for sx in np.unique(span[:, 0]):
            for sy in np.unique(span[span[:, 0] == sx, 1]):
                sel = np.nonzero((span[:, 0] == sx) & (span[:, 1] == sy))[0]
                gx, gy = np.meshgrid(np.arange(sx), np.arange(sy), indexing="ij")
                cx = i0[sel, 0][:, None] + gx.ravel()[None]
                cy = i0[sel, 1][:, None] + gy.ravel()[None]
                cells.append((cx * self._ny + cy).ravel())
                fids.append(np.repeat(sel, sx * sy))
        cells, fids = np.concatenate(cells), np.concatenate(fids)
        order = np.argsort(cells, kind="stable")
        self._grid_cells, self._grid_faces = cells[order], fids[order]

    @staticmethod
    def _points(points: Any) -> np.ndarray:
        x = torch.from_numpy(points) if isinstance(points, np.ndarray) else points
        return check_points(x, "points", allow_empty=True).detach().cpu().double().numpy(
        ).reshape(-1, 3)

    def _count(self, p: np.ndarray) -> np.ndarray:
        """Winding numbers (float64, integral values) of points ``p [n, 3]``."""
        q = p[:, :2] + np.array([1.234567e-9, 2.345678e-9])
        c = np.floor((q - self._origin) / self.cell).astype(np.int64)
        key = c[:, 0] * self._ny + c[:, 1]
        lo = np.searchsorted(self._grid_cells, key, side="left")
        hi = np.searchsorted(self._grid_cells, key, side="right")
        cnt = hi - lo
        pi = np.repeat(np.arange(len(p)), cnt)
        wind = np.zeros(len(p))
        if len(pi) == 0:
            return wind
        start = np.repeat(lo - np.concatenate([[0], np.cumsum(cnt)[:-1]]), cnt)
        fi = self._grid_faces[start + np.arange(len(pi))]
        tri = self._tri[fi]
        a, b, cc = tri[:, 0], tri[:, 1], tri[:, 2]
        x, y = q[pi, 0], q[pi, 1]

        def edge(u, v):
            return (v[:, 0] - u[:, 0]) * (y - u[:, 1]) - (v[:, 1] - u[:, 1]) * (x - u[:, 0])

        w0, w1, w2 = edge(b, cc), edge(cc, a), edge(a, b)
        area = w0 + w1 + w2
        hit = ((w0 > 0) & (w1 > 0) & (w2 > 0)) | ((w0 < 0) & (w1 < 0) & (w2 < 0))
        safe = np.where(area != 0, area, 1.0)
        z = (w0 * a[:, 2] + w1 * b[:, 2] + w2 * cc[:, 2]) / safe
        hit &= z > p[pi, 2]
        sign = self._nz_sign[fi]
        np.add.at(wind, pi[hit], sign[hit])
        return wind

    def __call__(self, points: Union[Tensor, np.ndarray]) -> Union[Tensor, np.ndarray]:
        """Integer winding numbers ``[...]`` of ``points [..., 3]`` (an int64 array, or
        a long tensor on ``points``' device)."""
        p = self._points(points)
        w = np.rint(self._count(p)).astype(np.int64).reshape(tuple(points.shape[:-1]))
        return torch.from_numpy(w).to(points.device) if isinstance(points, Tensor) else w

    def inside(self, points: Union[Tensor, np.ndarray]) -> Union[Tensor, np.ndarray]:
        """``[...]`` bool, True where the winding number is non-zero (inside at least
        one closed piece); same kind (array / tensor) as ``points``."""
        p = self._points(points)
        m = (np.abs(self._count(p)) > 0.5).reshape(tuple(points.shape[:-1]))
        return torch.from_numpy(m).to(points.device) if isinstance(points, Tensor) else m
