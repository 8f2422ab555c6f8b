"""Argument checks shared by the geometry functions (private).

Every check raises ``TypeError`` (wrong kind of object / dtype) or ``ValueError``
(wrong shape, empty, non-finite, out-of-range index) with a message that names the
argument and says how to fix it.
"""
from __future__ import annotations

from typing import Any, Tuple

import numpy as np
import torch
from torch import Tensor


def check_points(x: Any, name: str, dim: int = 3, allow_empty: bool = False) -> Tensor:
    """``x`` must be a floating tensor ``[..., N, dim]`` with finite entries."""
    if not isinstance(x, Tensor):
        raise TypeError(f"`{name}`: expected a torch.Tensor of shape [..., N, {dim}], got "
                        f"{type(x).__name__}; wrap it with "
                        f"torch.as_tensor(..., dtype=torch.float32)")
    if not x.is_floating_point():
        raise TypeError(f"`{name}`: expected a floating-point tensor, got dtype {x.dtype}; "
                        f"convert it with `.float()` or `.double()`")
    if x.dim() < 2 or x.size(-1) != dim:
        raise ValueError(f"`{name}`: expected shape [..., N, {dim}], got {tuple(x.shape)}")
    if not allow_empty and x.size(-2) == 0:
        raise ValueError(f"`{name}`: the point set is empty (shape {tuple(x.shape)}); "
                         f"pass at least one point")
    if x.numel() and not bool(torch.isfinite(x).all()):
        raise ValueError(f"`{name}`: contains NaN or inf entries; clean or mask the input first")
    return x


def check_faces(faces: Any, num_vertices: int, name: str = "faces",
                allow_empty: bool = False) -> Tensor:
    """``faces`` must be an integer tensor ``[F, 3]`` with indices in ``[0, num_vertices)``."""
    if not isinstance(faces, Tensor):
        raise TypeError(f"`{name}`: expected a torch.Tensor of shape [F, 3], got "
                        f"{type(faces).__name__}; wrap it with "
                        f"torch.as_tensor(..., dtype=torch.long)")
    if faces.is_floating_point() or faces.is_complex() or faces.dtype == torch.bool:
        raise TypeError(f"`{name}`: expected an integer tensor, got dtype {faces.dtype}; "
                        f"convert it with `.long()`")
    if faces.dim() != 2 or faces.size(1) != 3:
        raise ValueError(f"`{name}`: expected shape [F, 3] (one shared topology for the "
                         f"whole batch), got {tuple(faces.shape)}")
    if faces.size(0) == 0:
        if allow_empty:
            return faces.long()
        raise ValueError(f"`{name}`: the mesh has no faces; pass at least one triangle")
    lo, hi = int(faces.min()), int(faces.max())
    if lo < 0 or hi >= num_vertices:
        raise ValueError(f"`{name}`: indices must lie in [0, {num_vertices}) (the vertex "
                         f"count), got [{lo}, {hi}]; check that faces and positions belong "
                         f"to the same mesh and that indices are 0-based")
    return faces.long()


def check_mesh(pos: Any, faces: Any, pos_name: str = "pos", faces_name: str = "faces"):
    """Validate a (possibly batched) triangle mesh; returns ``(pos, faces.long())``."""
    pos = check_points(pos, pos_name)
    faces = check_faces(faces, pos.size(-2), faces_name)
    return pos, faces


def check_indices(idx: Any, num: int, name: str) -> Tensor:
    """A 1-D integer index tensor (or sequence) with entries in ``[0, num)``."""
    t = torch.as_tensor(idx)
    if t.is_floating_point() or t.dtype == torch.bool:
        raise TypeError(f"`{name}`: expected integer vertex indices, got dtype {t.dtype}")
    t = t.reshape(-1).long()
    if t.numel() == 0:
        raise ValueError(f"`{name}`: no indices given; pass at least one vertex index")
    if int(t.min()) < 0 or int(t.max()) >= num:
        raise ValueError(f"`{name}`: indices must lie in [0, {num}), got "
                         f"[{int(t.min())}, {int(t.max())}]")
    return t


def safe_norm(x: Tensor, dim: int = -1, keepdim: bool = False) -> Tensor:
    """Euclidean norm whose gradient is finite (zero) at the zero vector."""
    sq = (x * x).sum(dim, keepdim=keepdim)
    tiny = torch.finfo(x.dtype).tiny if x.is_floating_point() else 1e-30
    return torch.sqrt(sq.clamp_min(tiny ** 0.5))


def numpy_mesh(pos: Any, faces: Any, what: str = "geodesics are computed"
               ) -> Tuple[np.ndarray, np.ndarray]:
    """Validate a single mesh and return float64 / int64 numpy copies (``what`` names
    the computation in the error for a batched ``pos``)."""
    if isinstance(pos, np.ndarray):
        if not np.issubdtype(pos.dtype, np.floating):
            raise TypeError(f"`pos`: expected floating-point positions, got dtype {pos.dtype}")
        pos = torch.from_numpy(pos)
    if isinstance(faces, np.ndarray):
        faces = torch.from_numpy(faces)
    pos = check_points(pos, "pos")
    if pos.dim() != 2:
        raise ValueError(f"`pos`: {what} on one rest mesh, expected shape "
                         f"[V, 3], got {tuple(pos.shape)}; loop over the batch")
    faces = check_faces(faces, pos.size(0), "faces")
    return (pos.detach().cpu().double().numpy(), faces.detach().cpu().numpy().astype(np.int64))
