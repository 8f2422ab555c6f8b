"""Blender export worker: writes mesh sequences as Alembic (``.abc``) and/or ``.blend``.

Run as ``<python with bpy> _blender_export_worker.py IN.npz OUT.npz`` by
:mod:`garmentgnn.data.blender_export` (through
:func:`garmentgnn.sim.blender.run_blender_script`); never imported by garmentgnn.  It
imports only the standard library, numpy, ``bpy`` (Blender as a Python module, GPL-3)
and the cloth worker beside it (``_blender_worker.py``, for its mesh builder), so
Blender's code runs in this separate process.

``IN.npz`` holds, for each object ``i``, ``positions_<i> [T, V, 3]`` and ``faces_<i>
[F, 3]``, and ``config_json``: ``{"objects": [{"name", "color", "offset"}], "fps",
"abc": path or null, "blend": path or null}``.  Each object is one mesh built from its
frame 0 in our vertex order, with one shape key per frame (``f0000`` is the basis) whose
value is keyed 1 on its own frame and 0 elsewhere, with constant interpolation: scene
frame ``k + 1`` shows sample ``k`` exactly.  The ``.blend`` is self-contained (the shape
keys are in it, no external cache file).  ``OUT.npz`` holds ``info_json`` (Blender's
version, the files written, timings).
"""
import json
import sys
import time

import numpy as np

from _blender_worker import _mesh_object  # the cloth worker beside this file


def _colored_object(bpy, name, verts, faces, color):
    obj = _mesh_object(bpy, name, verts, faces)  # checks Blender kept every vertex and face
    mat = bpy.data.materials.new(name)
    mat.diffuse_color = (*color, 1.0)
    obj.data.materials.append(mat)
    return obj


def _animate(obj, frames):
    """One shape key per frame, keyed one-hot with constant interpolation."""
    T = frames.shape[0]
    obj.shape_key_add(name="f0000", from_mix=False)  # the basis: frame 0
    keys = [None]
    for k in range(1, T):
        key = obj.shape_key_add(name=f"f{k:04d}", from_mix=False)
        key.data.foreach_set("co", np.ascontiguousarray(frames[k], np.float32).ravel())
        keys.append(key)
    for k in range(1, T):
        key = keys[k]
        for frame, value in ((k, 0.0), (k + 1, 1.0), (k + 2, 0.0)):
            if 1 <= frame <= T:
                key.value = value
                key.keyframe_insert("value", frame=frame)
        key.value = 0.0


def run(inp, out):
    t_start = time.perf_counter()
    import bpy  # noqa: E402, PLC0415  (imported here: only this process loads Blender)
    data = np.load(inp, allow_pickle=False)
    cfg = json.loads(data["config_json"].tobytes().decode())
    bpy.ops.wm.read_factory_settings(use_empty=True)
    # new keyframes step: a frame shows its own sample, never a blend of two
    bpy.context.preferences.edit.keyframe_new_interpolation_type = "CONSTANT"
    scene = bpy.context.scene
    fps = float(cfg["fps"])
    scene.render.fps = max(1, round(fps))
    scene.render.fps_base = scene.render.fps / fps
    T = None
    for i, spec in enumerate(cfg["objects"]):
        P, F = data[f"positions_{i}"], data[f"faces_{i}"]
        if T is not None and P.shape[0] != T:
            raise RuntimeError(f"{spec['name']}: {P.shape[0]} frames, expected {T}")
        T = P.shape[0]
        obj = _colored_object(bpy, spec["name"], P[0], F, spec["color"])
        obj.location = tuple(spec["offset"])
        if T > 1:
            _animate(obj, P)
    scene.frame_start, scene.frame_end = 1, max(T, 1)
    scene.frame_set(1)
    written = []
    if cfg.get("abc"):
        res = bpy.ops.wm.alembic_export(filepath=cfg["abc"], start=1, end=max(T, 1),
                                        selected=False, export_hair=False,
                                        export_particles=False, evaluation_mode="RENDER")
        if "FINISHED" not in res:
            raise RuntimeError(f"Alembic export of {cfg['abc']} returned {res}")
        written.append(cfg["abc"])
    if cfg.get("blend"):
        res = bpy.ops.wm.save_as_mainfile(filepath=cfg["blend"], compress=True, copy=True)
        if "FINISHED" not in res:
            raise RuntimeError(f"saving {cfg['blend']} returned {res}")
        written.append(cfg["blend"])
    info = {"blender_version": bpy.app.version_string, "written": written,
            "total_seconds": time.perf_counter() - t_start}
    np.savez(out, info_json=np.frombuffer(json.dumps(info).encode(), np.uint8))


if __name__ == "__main__":
    run(sys.argv[1], sys.argv[2])
