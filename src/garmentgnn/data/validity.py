"""Which frames of a sequence are valid ground truth: the one per-frame mask that training
targets and every score read.

A frame is **valid** when the engine converged on it (the sequence file's ``converged``)
and the garment is at most :data:`VALID_PENETRATION` inside the body at its end (the file's
``penetration``, the exact depth of the deepest vertex, metres).  A frame that fails either
is kept in the file (its positions are what the engine produced) but left out of the
supervised loss and of every metric, and counted.  Files written before ``penetration`` was
recorded have only ``converged``: their frames are valid where they converged.

The mask is computed when a file is read, not stored, so it follows this module's line;
the manifest's ``invalid_frames`` counts it as it was when the file was generated.
"""
from __future__ import annotations

from typing import Any, Mapping, Optional

import numpy as np

__all__ = ["VALID_PENETRATION", "invalid_frame_count", "sequence_valid", "valid_frames"]

#: deepest a garment vertex may be inside the body (m) for a frame to count as ground truth:
#: 1 cm, well beyond Blender's contact jitter (1-3 mm) and its collision shell
#: (``collision_distance`` + ``body_thickness``, 5 mm each in the presets); a frame deeper
#: than that has the body through the cloth
VALID_PENETRATION = 0.01


def valid_frames(converged: Optional[Any], penetration: Optional[Any] = None,
                 num_frames: Optional[int] = None,
                 line: float = VALID_PENETRATION) -> np.ndarray:
    """``[T]`` bool: converged and at most ``line`` (m) inside the body.

    ``converged`` / ``penetration``: ``[T]`` arrays (either may be ``None``: every frame
    converged / nothing measured); ``num_frames`` gives ``T`` when both are ``None``."""
    if not (isinstance(line, (int, float)) and np.isfinite(line) and line >= 0):
        raise ValueError(f"`line`: expected a finite depth >= 0 in metres, got {line!r}")
    arrays = [np.asarray(a) for a in (converged, penetration) if a is not None]
    lengths = {a.shape for a in arrays}
    if len(lengths) > 1 or any(a.ndim != 1 for a in arrays):
        raise ValueError(f"`converged` / `penetration`: expected [T] arrays of one length, got "
                         f"shapes {sorted(lengths)}")
    if arrays:
        T = arrays[0].shape[0]
        if num_frames is not None and num_frames != T:
            raise ValueError(f"`num_frames`: {num_frames} differs from the arrays' {T} frames")
    elif num_frames is None:
        raise ValueError("`num_frames`: needed when neither `converged` nor `penetration` is "
                         "given")
    else:
        T = int(num_frames)
    ok = np.ones(T, bool) if converged is None else np.asarray(converged).astype(bool)
    if penetration is not None:
        depth = np.asarray(penetration, dtype=np.float64)
        ok = ok & (depth <= line)  # NaN depth: not valid
    return ok


def sequence_valid(seq: Mapping[str, Any]) -> np.ndarray:
    """:func:`valid_frames` of a loaded sequence file (``converged`` and, when the file has
    it, ``penetration``; ``positions`` gives ``T`` for a file with neither)."""
    T = None
    if seq.get("converged") is None and seq.get("penetration") is None:
        T = int(np.asarray(seq["positions"]).shape[0])
    return valid_frames(seq.get("converged"), seq.get("penetration"), T)


def invalid_frame_count(converged: Optional[Any], penetration: Optional[Any] = None,
                        num_frames: Optional[int] = None) -> int:
    """How many frames :func:`valid_frames` leaves out."""
    return int((~valid_frames(converged, penetration, num_frames)).sum())

