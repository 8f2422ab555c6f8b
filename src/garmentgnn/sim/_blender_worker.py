"""Blender cloth worker: simulates one sequence with ``bpy`` and exits.

Run as ``<python with bpy> _blender_worker.py IN.npz OUT.npz`` by
:mod:`garmentgnn.sim.blender`; never imported by garmentgnn.  It imports only the
standard library, numpy and ``bpy`` (Blender as a Python module, GPL-3), so Blender's
code runs in this separate process and garmentgnn itself stays MIT.

``IN.npz`` holds ``garment_frames [N, V, 3]`` (the garment's rest shape carried by the
body: frame 0 is the initial state, pinned vertices follow it), ``faces [F, 3]``,
``pinned [V]``, ``body_frames [N, Vb, 3]``, ``body_faces [Fb, 3]`` and ``config_json``
(the Blender properties to set, made by :func:`garmentgnn.sim.blender.blender_config`).
Scene frame ``k + 1`` shows sample ``k``.  ``OUT.npz`` holds ``positions [N, V, 3]``
(world coordinates, the input's vertex order), ``seconds_per_frame [N]`` and
``info_json`` (Blender's version, timings).
"""
import json
import os
import sys
import tempfile
import time

import numpy as np


def _pc2(path, frames):
    """Write ``frames [N, V, 3]`` as a PC2 point cache (start frame 0, one sample a frame)."""
    frames = np.ascontiguousarray(frames, dtype="<f4")
    head = (b"POINTCACHE2\0" + np.array([1, frames.shape[1]], "<i4").tobytes()
            + np.array([0.0, 1.0], "<f4").tobytes() + np.array([frames.shape[0]], "<i4").tobytes())
    with open(path, "wb") as f:
        f.write(head)
        f.write(frames.tobytes())


def _mesh_object(bpy, name, verts, faces):
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(verts.tolist(), [], faces.tolist())
    mesh.update()
    if len(mesh.vertices) != len(verts) or len(mesh.polygons) != len(faces):
        raise RuntimeError(f"{name}: Blender built {len(mesh.vertices)} vertices / "
                           f"{len(mesh.polygons)} faces from {len(verts)} / {len(faces)}")
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def _cache(obj, path):
    """A Mesh Cache modifier reading ``path``: scene frame k + 1 shows sample k."""
    mod = obj.modifiers.new("cache", "MESH_CACHE")
    mod.cache_format = "PC2"
    mod.filepath = path
    mod.frame_start = 1.0
    return mod


def _set(target, props, where):
    for key, value in props.items():
        if not hasattr(target, key):
            raise RuntimeError(f"Blender {where} has no property {key!r}")
        setattr(target, key, value)


def run(inp, out):
    t_start = time.perf_counter()
    import bpy  # noqa: E402, PLC0415  (imported here: only this process loads Blender)
    t_import = time.perf_counter() - t_start
    data = np.load(inp, allow_pickle=False)
    cfg = json.loads(data["config_json"].tobytes().decode())
    G, B = data["garment_frames"], data["body_frames"]
    faces, body_faces, pinned = data["faces"], data["body_faces"], data["pinned"]
    N, V = G.shape[0], G.shape[1]

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, N
    scene.gravity = tuple(cfg["gravity"])
    tmp = tempfile.mkdtemp(prefix="garmentgnn-blender-")

    if len(body_faces):  # no body: the cloth hangs from its pins with no collider
        body = _mesh_object(bpy, "body", B[0], body_faces)
        _pc2(os.path.join(tmp, "body.pc2"), B)
        _cache(body, os.path.join(tmp, "body.pc2"))
        body.modifiers.new("collision", "COLLISION")  # after the cache: collides as animated
        _set(body.collision, cfg["collider"], "collision settings")

    cloth_obj = _mesh_object(bpy, "garment", G[0], faces)
    _pc2(os.path.join(tmp, "garment.pc2"), G)
    _cache(cloth_obj, os.path.join(tmp, "garment.pc2"))  # before the cloth: pins follow it
    cloth = cloth_obj.modifiers.new("cloth", "CLOTH")
    _set(cloth.settings, cfg["cloth"], "cloth settings")
    _set(cloth.collision_settings, cfg["cloth_collision"], "cloth collision settings")
    if pinned.any():
        group = cloth_obj.vertex_groups.new(name="pin")
        group.add(np.flatnonzero(pinned).tolist(), 1.0, "REPLACE")
        cloth.settings.vertex_group_mass = "pin"
    cloth.point_cache.frame_start, cloth.point_cache.frame_end = 1, N

    positions = np.empty((N, V, 3), np.float32)
    seconds = np.zeros(N, np.float64)
    co = np.empty(V * 3, np.float32)
    for k in range(N):
        t0 = time.perf_counter()
        scene.frame_set(k + 1)  # every frame in order: a jump is one coarse step
        ev = cloth_obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
        mesh = ev.data
        if len(mesh.vertices) != V:
            raise RuntimeError(f"frame {k + 1}: the evaluated garment has "
                               f"{len(mesh.vertices)} vertices, expected {V}")
        mesh.vertices.foreach_get("co", co)
        X = co.reshape(V, 3).astype(np.float64)
        M = np.array(ev.matrix_world, dtype=np.float64)
        positions[k] = X @ M[:3, :3].T + M[:3, 3]
        seconds[k] = time.perf_counter() - t0
        if not np.isfinite(positions[k]).all():
            raise RuntimeError(f"frame {k + 1}: Blender's cloth produced NaN/inf positions")
    info = {"blender_version": bpy.app.version_string, "import_seconds": t_import,
            "total_seconds": time.perf_counter() - t_start}
    np.savez(out, positions=positions, seconds_per_frame=seconds,
             info_json=np.frombuffer(json.dumps(info).encode(), np.uint8))


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: _blender_worker.py IN.npz OUT.npz")
    run(sys.argv[1], sys.argv[2])
