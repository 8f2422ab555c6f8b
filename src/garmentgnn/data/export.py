"""Export of a generated sequence file: a Blender/3ds Max point cache (PC2), a folder of
per-frame OBJs, or glTF (:mod:`garmentgnn.data.gltf`)."""
from __future__ import annotations

import math
import os
import re
import struct
from pathlib import Path
from typing import List

import numpy as np

from garmentgnn.data.blender_export import write_blender
from garmentgnn.data.gltf import sequence_meshes, write_gltf
from garmentgnn.data.store import PathLike, atomic_write_bytes, checked_sequence, load_sequence
from garmentgnn.sim.blender import require_blender

PC2_HEADER = struct.Struct("<12siiffi")


def write_pc2(path: PathLike, positions: np.ndarray, start_frame: float = 0.0,
              sample_rate: float = 1.0) -> Path:
    """Blender/3ds Max point cache: header ``POINTCACHE2\\0``, version 1, number of
    points, start frame, sample rate (frames between samples), number of samples, then
    ``float32`` xyz for every point of every sample."""
    P = np.asarray(positions)
    if P.ndim != 3 or P.shape[2] != 3:
        raise ValueError(f"`positions`: expected [T, V, 3], got {P.shape}")
    if not np.issubdtype(P.dtype, np.number) or np.iscomplexobj(P):
        raise TypeError(f"`positions`: expected real numbers, got dtype {P.dtype}")
    P = P.astype("<f4")
    if not np.isfinite(P).all():
        raise ValueError("`positions`: contain NaN/inf (or values beyond float32)")
    if not math.isfinite(start_frame) or not math.isfinite(sample_rate) or sample_rate <= 0:
        raise ValueError(f"`start_frame`/`sample_rate`: expected finite numbers and a "
                         f"positive rate, got {start_frame!r}, {sample_rate!r}")
    head = PC2_HEADER.pack(b"POINTCACHE2\0", 1, P.shape[1], float(start_frame),
                           float(sample_rate), P.shape[0])
    return atomic_write_bytes(path, head + np.ascontiguousarray(P).tobytes())


def write_obj_sequence(folder: PathLike, positions: np.ndarray, faces: np.ndarray,
                       stem: str = "frame") -> List[Path]:
    """One OBJ per frame, ``folder/<stem>_<t:04d>.obj``, same vertex order in every file.
    Frame files of an earlier, longer write into ``folder`` (``<stem>_<digits>.obj``
    beyond these frames) are removed: a rerun with fewer frames would otherwise leave
    them beside the new ones as if they were its own."""
    X = np.asarray(positions, dtype=np.float64)
    if X.ndim != 3 or X.shape[2] != 3 or not np.isfinite(X).all():
        raise ValueError(f"`positions`: expected finite [T, V, 3], got shape {X.shape}")
    F = np.asarray(faces)
    if F.ndim != 2 or F.shape[1] != 3 or not np.issubdtype(F.dtype, np.integer):
        raise ValueError(f"`faces`: expected integer [F, 3], got {F.dtype} {F.shape}")
    if F.size and (F.min() < 0 or F.max() >= X.shape[1]):
        raise ValueError(f"`faces`: reference vertices {int(F.min())}..{int(F.max())} but "
                         f"`positions` have {X.shape[1]} per frame; pass the faces of "
                         f"these positions")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    F = F.astype(np.int64) + 1
    flines = "".join(f"f {a} {b} {c}\n" for a, b, c in F)
    paths = []
    for t, X in enumerate(np.asarray(positions, dtype=np.float64)):
        vlines = "".join(f"v {x:.7g} {y:.7g} {z:.7g}\n" for x, y, z in X)
        p = folder / f"{stem}_{t:04d}.obj"
        atomic_write_bytes(p, (f"# garmentgnn frame {t}\n" + vlines + flines).encode())
        paths.append(p)
    mine = re.compile(rf"{re.escape(stem)}_\d{{4,}}\.obj")
    written = {p.name for p in paths}
    for old in folder.iterdir():
        if mine.fullmatch(old.name) and old.name not in written and old.is_file():
            old.unlink()
    return paths


#: the formats of :func:`export_sequence` (``abc`` and ``blend`` need Blender's ``bpy``)
EXPORT_FORMATS = ("pc2", "obj", "gltf", "abc", "blend")
#: the file name ending each single-file format needs (obj writes a folder)
EXPORT_SUFFIX = {"pc2": ".pc2", "gltf": ".glb", "abc": ".abc", "blend": ".blend"}


def check_output(out: PathLike, fmt: str) -> Path:
    """``out`` as a path ``fmt`` can write to: a file (a folder of OBJs for ``obj``) that
    is not a folder (a file), below a writable folder or one that can be made (no file in
    the way).  Otherwise a ``ValueError`` naming ``out`` and the fix, before any work:
    Blender, handed a folder, ended in its own traceback."""
    path = Path(out)
    folder = fmt == "obj"
    if not str(out).strip():
        raise ValueError("`out`: empty path; name a file (a folder for obj)")
    if path.is_dir() and not folder:
        raise ValueError(f"`out` {out}: is a folder, and {fmt} writes one file; name a file "
                         f"in it, e.g. {path / ('sequence' + EXPORT_SUFFIX[fmt])}")
    if path.exists() and not path.is_dir() and folder:
        raise ValueError(f"`out` {out}: is a file, and obj writes a folder of OBJs; name a "
                         f"folder")
    parent = next(q for q in path.absolute().parents if q.exists())
    if not parent.is_dir():
        raise ValueError(f"`out` {out}: {parent} is a file, so nothing can be made below it; "
                         f"name another path")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ValueError(f"`out` {out}: {parent} is not writable by you; name another path")
    return path


def export_sequence(seq_path: PathLike, fmt: str, out: PathLike, start_frame: float = 0.0,
                    body: bool = True) -> List[Path]:
    """Export a sequence file's simulated positions as ``pc2`` (one file), ``obj``
    (a folder of per-frame OBJs), ``gltf`` (one ``.glb`` with the posed body unless
    ``body=False``, one morph target per frame and an animation; see
    :mod:`garmentgnn.data.gltf`), or, through Blender (the ``bpy`` package, see
    :mod:`garmentgnn.data.blender_export`), ``abc`` (Alembic) or ``blend`` (a ``.blend``
    file), garment and body animated likewise."""
    if fmt not in EXPORT_FORMATS:
        raise ValueError(f"`fmt`: expected one of {', '.join(map(repr, EXPORT_FORMATS))}, "
                         f"got {fmt!r}")
    if EXPORT_SUFFIX.get(fmt) and Path(out).suffix.lower() != EXPORT_SUFFIX[fmt]:
        raise ValueError(f"`out` {out}: {fmt} writes a file whose name must end in "
                         f"{EXPORT_SUFFIX[fmt]}")
    check_output(out, fmt)
    if fmt in ("abc", "blend"):  # the clear errors before loading anything
        require_blender()
    # the whole file, checked (shapes, faces in range, NaN frames, vertex order)
    seq = checked_sequence(seq_path, load_sequence(seq_path))
    if fmt in ("gltf", "abc", "blend"):
        meshes, fps = sequence_meshes(seq, body=body)
        if fmt == "gltf":
            return [write_gltf(out, meshes, fps=fps)]
        return write_blender(meshes, fps=fps, **{fmt: out})
    if fmt == "pc2":
        return [write_pc2(out, seq["positions"], start_frame=start_frame)]
    return write_obj_sequence(out, seq["positions"], seq["garment_faces"],
                              stem=Path(seq_path).stem)
