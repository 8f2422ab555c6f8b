"""The one check of a loaded sequence file (:func:`check_sequence`): its arrays, shapes,
finiteness and vertex order, used by ``manifest``, ``generate`` (resume), ``export`` and
every loader of a manifest's records (through :mod:`garmentgnn.data.store`)."""
from __future__ import annotations

from typing import Any, Dict, Optional

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["ORDER_TOLERANCE", "REST_ORDER_TOLERANCE", "SEQUENCE_KEYS", "check_sequence",
           "nonfinite_arrays"]

#: arrays every sequence file holds (besides ``meta_json``; files of the real simulator
#: also hold ``penetration [T]``, the exact end-of-frame depth inside the body, metres)
SEQUENCE_KEYS = ("garment_vertices", "garment_faces", "garment_uv", "garment_face_uv",
                 "garment_pinned", "body_shape", "motion_rotations", "motion_translation",
                 "positions", "converged", "newton_iterations", "residual")


#: median relative edge-length change (over a frame's edges) beyond which a frame's vertex
#: order cannot match the rest garment's: cloth stretches a few percent, a reordered
#: vertex list changes a typical edge by several hundred percent
ORDER_TOLERANCE = 0.5
#: median rest edge over the median distance of a rest vertex to its nearest neighbour
#: beyond which the rest vertices cannot be in the faces' order: about 1 to 1.5 on a mesh
#: (an edge joins near neighbours), tens on a reordered vertex list (an "edge" joins two
#: vertices anywhere on the garment); independent of the UVs and of the unit
REST_ORDER_TOLERANCE = 4.0


def nonfinite_arrays(arrays: Dict[str, Any]) -> Optional[str]:
    """``None`` if every floating-point array of ``arrays`` (a sequence file's; ``meta``
    is skipped) is finite, otherwise which array holds NaN/inf and how many values."""
    for key in sorted(arrays):
        if key == "meta":
            continue
        a = np.asarray(arrays[key])
        if np.issubdtype(a.dtype, np.inexact) and not np.isfinite(a).all():
            bad = np.flatnonzero(~np.isfinite(a).reshape(-1))
            return (f"{key} contain NaN/inf in {len(bad)} of {a.size} values (first at index "
                    f"{tuple(int(i) for i in np.unravel_index(bad[0], a.shape))})")
    return None


def check_sequence(seq: Dict[str, Any], item_id: Optional[str] = None) -> Optional[str]:
    """``None`` if the arrays of a loaded sequence file (:func:`load_sequence`) fit
    together, otherwise what is wrong: missing arrays, another item's id, shapes
    (``positions [T, V, 3]`` with ``V`` the rest garment's vertices and ``T`` the
    metadata's frames; faces in range), NaN/inf frames (named) and NaN/inf in any other
    array (:func:`nonfinite_arrays`, the array named), and the vertex order:
    the edge lengths of the first, middle and last frame against the rest garment's
    (``garment_vertices`` on ``garment_faces``: a median relative difference over
    :data:`ORDER_TOLERANCE`), and the rest edges against the distances between nearest
    rest vertices (:data:`REST_ORDER_TOLERANCE`).  The one check of sequence files, used by
    ``manifest``, ``generate`` (resume), ``export`` and every loader of a manifest's
    records."""
    missing = [k for k in SEQUENCE_KEYS if k not in seq]
    if missing:
        return f"missing arrays {missing}"
    meta = seq["meta"]
    if item_id is not None and meta.get("id") != item_id:
        return f"holds item {meta.get('id')!r}, expected {item_id!r}"
    P, V, F = seq["positions"], seq["garment_vertices"], seq["garment_faces"]
    if V.ndim != 2 or V.shape[1:] != (3,) or F.ndim != 2 or F.shape[1:] != (3,):
        return (f"garment_vertices {V.shape} / garment_faces {F.shape}: expected [V, 3] "
                f"and [F, 3]")
    if P.ndim != 3 or P.shape[1:] != V.shape or P.shape[0] != meta.get("num_frames"):
        return f"positions have shape {P.shape}, expected [{meta.get('num_frames')}, {V.shape}]"
    if not np.issubdtype(F.dtype, np.integer) or (F.size and (F.min() < 0 or F.max() >= len(V))):
        return f"garment_faces reference vertices outside [0, {len(V)})"
    bad = ~np.isfinite(P).reshape(len(P), -1).all(1)
    if bad.any():
        frames = np.flatnonzero(bad)
        return (f"positions contain NaN/inf in {len(frames)} of {len(P)} frames (first: "
                f"frame {int(frames[0])})")
    msg = nonfinite_arrays(seq)
    if msg is not None:
        return msg
    if not F.size or not len(P):
        return None
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]).astype(np.int64)
    rest = np.linalg.norm(V[e[:, 0]] - V[e[:, 1]], axis=1).astype(np.float64)
    keep = rest > 0
    if not keep.any():
        return None
    e, rest = e[keep], rest[keep]
    for t in sorted({0, len(P) // 2, len(P) - 1}):
        cur = np.linalg.norm(P[t, e[:, 0]] - P[t, e[:, 1]], axis=1)
        off = float(np.median(np.abs(cur / rest - 1.0)))
        if off > ORDER_TOLERANCE:
            return (f"vertex order of positions does not match the rest garment: frame {t}'s "
                    f"edges differ from the rest edges by {100 * off:.0f}% (median)")
    nn = cKDTree(V).query(V, k=2)[0][:, 1]
    nn = nn[nn > 0]
    ratio = float(np.median(rest) / np.median(nn)) if nn.size else 1.0
    if ratio > REST_ORDER_TOLERANCE:
        return (f"vertex order of garment_vertices does not match garment_faces: the median "
                f"rest edge is {ratio:.0f}x the median distance between nearest vertices "
                f"(a mesh's edges join near neighbours)")
    return None
