"""Alembic (``.abc``) and ``.blend`` export of mesh sequences through Blender.

:func:`write_blender` takes the same objects as the glTF export
(:class:`~garmentgnn.data.gltf.GltfMesh`: ``positions [T, V, 3]``, faces, colour, offset)
and has Blender write them, in a worker process started with the Blender engine's
interpreter (:func:`garmentgnn.sim.blender.run_blender_script`; the script is
``garmentgnn/sim/_blender_export_worker.py``).  garmentgnn never imports ``bpy``.

In the files each object is one mesh in our vertex order and our coordinates (Blender is
+Z up like us; its Alembic exporter converts to Alembic's +Y up and its importer back),
animated by one shape key per frame keyed one-hot with constant interpolation: scene
frame ``k + 1`` is sample ``k``, at ``fps`` frames per second.  The ``.blend`` carries
the shape keys itself (no external cache file); the ``.abc`` stores every frame's
evaluated vertex positions.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Union

import numpy as np

from garmentgnn.sim.blender import require_blender, run_blender_script

PathLike = Union[str, os.PathLike]
WORKER = Path(__file__).parents[1] / "sim" / "_blender_export_worker.py"
#: the file suffix of each format
SUFFIX = {"abc": ".abc", "blend": ".blend"}


def write_blender(meshes: Sequence, fps: float = 30.0, abc: Optional[PathLike] = None,
                  blend: Optional[PathLike] = None, timeout: float = 900.0) -> List[Path]:
    """Write ``meshes`` (:class:`~garmentgnn.data.gltf.GltfMesh`, all with the same
    number of frames) as an Alembic file ``abc`` and/or a ``.blend`` file ``blend``;
    returns the paths written.  Needs the ``bpy`` package in the Blender engine's
    interpreter: ``RuntimeError`` saying how to install it otherwise."""
    if abc is None and blend is None:
        raise ValueError("`abc`/`blend`: give at least one output path")
    if not (isinstance(fps, (int, float)) and np.isfinite(fps) and fps > 0):
        raise ValueError(f"`fps`: must be a positive finite number, got {fps!r}")
    if not meshes:
        raise ValueError("`meshes`: give at least one object")
    frames = {m.positions.shape[0] for m in meshes}
    if len(frames) != 1:
        raise ValueError(f"`meshes`: every object needs the same number of frames, got "
                         f"{sorted(frames)} ({meshes})")
    names = [m.name for m in meshes]
    if len(set(names)) != len(names):
        raise ValueError(f"`meshes`: object names must differ, got {names}")
    outputs: Dict[str, Optional[str]] = {}
    for fmt, path in (("abc", abc), ("blend", blend)):
        if path is not None and Path(path).suffix.lower() != SUFFIX[fmt]:
            raise ValueError(f"`{fmt}`: the file name must end in {SUFFIX[fmt]}, got {path}")
        outputs[fmt] = None if path is None else str(Path(path).resolve())
        if path is not None:
            Path(path).parent.mkdir(parents=True, exist_ok=True)
    require_blender()  # the clear error before any work
    arrays: Dict[str, np.ndarray] = {}
    for i, m in enumerate(meshes):
        arrays[f"positions_{i}"] = m.positions.astype(np.float32)
        arrays[f"faces_{i}"] = m.faces.astype(np.int64)
    config = {"objects": [{"name": m.name, "color": [float(c) for c in m.color],
                           "offset": [float(o) for o in m.offset]} for m in meshes],
              "fps": float(fps), **outputs}
    json.dumps(config)
    run_blender_script(WORKER, arrays, config, timeout=timeout)
    written = [Path(p) for p in (outputs["abc"], outputs["blend"]) if p is not None]
    for p in written:
        if not p.is_file() or p.stat().st_size == 0:
            raise RuntimeError(f"Blender reported success but wrote no {p}")
    return written
