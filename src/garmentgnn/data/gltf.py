"""glTF 2.0 export of mesh sequences: one base mesh per object, one morph target per
frame and one animation that steps through them.

Every object is a node with one mesh whose base ``POSITION`` is frame 0 and whose
morph target ``k`` holds ``positions[k] - positions[0]`` (so target 0 is zero).  The
animation ``"sequence"`` drives each node's ``weights`` with ``STEP`` keys at
``k / fps``: one-hot on target ``k``, so the displayed mesh at time ``k / fps`` is
exactly frame ``k``.  Vertices stay in our order and our coordinates (no welding, no
reordering); a node may carry a translation (``offset``) so several objects can stand
side by side without touching their vertex data.  glTF is +Y up and ours is +Z up
(the body's front faces -Y), so all object nodes hang under one root node
``"garmentgnn (Z up)"`` rotated -90 degrees about X: a viewer shows ``(x, y, z)`` at
``(x, z, -y)``, upright and facing +Z.  Written as a binary ``.glb`` (opens in Blender,
three.js / any browser viewer, VTK); needs ``pygltflib`` (the ``viz`` extra).

An object with per-vertex ``colors`` (e.g. an error colour map) gets ``COLOR_0`` (glTF's
linear RGB of the given sRGB colours) with one ``COLOR_0`` morph target per frame beside
the positions, so the colours step with the frames, and an unlit material
(``KHR_materials_unlit``): a viewer shows exactly those colours.  ``label`` goes into the
node's ``extras`` and ``extras`` of :func:`write_gltf` into the scene's (three.js: the
objects' ``userData``), for a viewer to show.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from garmentgnn.body.factory import build_body
from garmentgnn._files import atomic_write_bytes

PathLike = Union[str, os.PathLike]
#: quaternion (x, y, z, w) of the root node: -90 degrees about X, our +Z up -> glTF +Y up
Z_UP_TO_Y_UP = (-float(np.sqrt(0.5)), 0.0, 0.0, float(np.sqrt(0.5)))


@dataclass
class GltfMesh:
    """One object: ``positions [T, V, 3]`` (metres), ``faces [F, 3]``, an RGB colour, a
    node translation ``offset``, optional per-vertex sRGB ``colors`` in 0..1 (``[T, V,
    3]``, or ``[V, 3]`` for every frame; drawn unlit) and a ``label`` for viewers."""

    name: str
    positions: np.ndarray
    faces: np.ndarray
    color: Tuple[float, float, float] = (0.7, 0.7, 0.7)
    offset: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    colors: Optional[np.ndarray] = None
    label: str = ""

    def __post_init__(self) -> None:
        p = self.positions
        p = p.detach().cpu().numpy() if hasattr(p, "detach") else np.asarray(p)
        f = self.faces
        f = f.detach().cpu().numpy() if hasattr(f, "detach") else np.asarray(f)
        if p.ndim == 2:
            p = p[None]
        if p.ndim != 3 or p.shape[2] != 3 or p.shape[0] < 1:
            raise ValueError(f"GltfMesh {self.name!r}: `positions` must be [T, V, 3], got "
                             f"{p.shape}")
        if not np.isfinite(p).all():
            raise ValueError(f"GltfMesh {self.name!r}: `positions` contain NaN/inf")
        if f.ndim != 2 or f.shape[1] != 3 or f.min() < 0 or f.max() >= p.shape[1]:
            raise ValueError(f"GltfMesh {self.name!r}: `faces` must be [F, 3] indices into "
                             f"{p.shape[1]} vertices")
        self.positions, self.faces = p.astype(np.float32), f.astype(np.uint32)
        if self.colors is not None:
            c = np.asarray(self.colors, np.float64)
            c = np.broadcast_to(c, p.shape) if c.shape == p.shape[1:] else c
            if c.shape != p.shape or not np.isfinite(c).all() or c.min() < 0 or c.max() > 1:
                raise ValueError(f"GltfMesh {self.name!r}: `colors` must be [T, V, 3] or "
                                 f"[V, 3] = {p.shape[1:]} values in 0..1, got {c.shape}")
            self.colors = c.astype(np.float32)

    def __repr__(self) -> str:
        T, V, _ = self.positions.shape
        return f"GltfMesh({self.name!r}, frames={T}, vertices={V}, faces={len(self.faces)})"


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB colour components (0..1) to linear RGB (glTF's ``COLOR_0``), the sRGB
    standard's transfer function."""
    c = np.asarray(c, np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def write_gltf(path: PathLike, meshes: Sequence[GltfMesh], fps: float = 30.0,
               extras: Optional[Dict[str, Any]] = None) -> Path:
    """Write ``meshes`` (same frame count ``T`` each) as a ``.glb`` with one morph target
    per frame and one ``STEP`` animation (see the module doc); ``extras`` (JSON) go into
    the scene; returns the path."""
    import pygltflib as g  # noqa: PLC0415 (optional: the viz extra)

    if not meshes:
        raise ValueError("`meshes`: need at least one mesh")
    if not fps > 0:
        raise ValueError(f"`fps`: expected > 0, got {fps}")
    T = meshes[0].positions.shape[0]
    for m in meshes:
        if m.positions.shape[0] != T:
            raise ValueError(f"`meshes`: {m!r} has {m.positions.shape[0]} frames, the first "
                             f"has {T}; every mesh must have the same frames")
    blob = bytearray()
    doc = g.GLTF2(asset=g.Asset(generator="garmentgnn", version="2.0"), scene=0)

    def add(array: np.ndarray, kind: str, target: Optional[int], minmax: bool = False) -> int:
        a = np.ascontiguousarray(array)
        ctype = g.UNSIGNED_INT if a.dtype == np.uint32 else g.FLOAT
        doc.bufferViews.append(g.BufferView(buffer=0, byteOffset=len(blob),
                                            byteLength=a.nbytes, target=target))
        blob.extend(a.tobytes())
        while len(blob) % 4:
            blob.append(0)
        flat = a.reshape(len(a), -1) if kind != g.SCALAR else a.reshape(-1, 1)
        acc = g.Accessor(bufferView=len(doc.bufferViews) - 1, componentType=ctype,
                         count=len(flat), type=kind)
        if minmax:
            acc.min, acc.max = flat.min(0).tolist(), flat.max(0).tolist()
        doc.accessors.append(acc)
        return len(doc.accessors) - 1

    anim = None
    if T > 1:
        times = add(np.arange(T, dtype=np.float32) / np.float32(fps), g.SCALAR, None, True)
        weights = add(np.eye(T, dtype=np.float32).ravel(), g.SCALAR, None)
        anim = g.Animation(name="sequence")
    for m in meshes:
        base = m.positions[0]
        pos = add(base, g.VEC3, g.ARRAY_BUFFER, True)
        idx = add(m.faces.ravel(), g.SCALAR, g.ELEMENT_ARRAY_BUFFER, True)
        targets = [{"POSITION": add(m.positions[k] - base, g.VEC3, g.ARRAY_BUFFER, True)}
                   for k in range(T)] if T > 1 else None
        attributes = g.Attributes(POSITION=pos)
        material = g.Material(
            name=m.name, doubleSided=True,
            pbrMetallicRoughness=g.PbrMetallicRoughness(
                baseColorFactor=[*map(float, m.color), 1.0], metallicFactor=0.0,
                roughnessFactor=0.8))
        if m.colors is not None:
            lin = srgb_to_linear(m.colors).astype(np.float32)
            attributes.COLOR_0 = add(lin[0], g.VEC3, g.ARRAY_BUFFER)
            for k, t in enumerate(targets or []):
                t["COLOR_0"] = add(lin[k] - lin[0], g.VEC3, g.ARRAY_BUFFER)
            material.pbrMetallicRoughness.baseColorFactor = [1.0, 1.0, 1.0, 1.0]
            material.extensions = {"KHR_materials_unlit": {}}
            if "KHR_materials_unlit" not in doc.extensionsUsed:
                doc.extensionsUsed.append("KHR_materials_unlit")
        doc.materials.append(material)
        prim = g.Primitive(attributes=attributes, indices=idx,
                           material=len(doc.materials) - 1, targets=targets)
        doc.meshes.append(g.Mesh(name=m.name, primitives=[prim],
                                 weights=[1.0] + [0.0] * (T - 1) if T > 1 else None,
                                 extras={"targetNames": [f"frame_{k}" for k in range(T)]}
                                 if T > 1 else {}))
        node = g.Node(name=m.name, mesh=len(doc.meshes) - 1,
                      extras={"label": m.label} if m.label else {})
        if any(m.offset):
            node.translation = [float(x) for x in m.offset]
        doc.nodes.append(node)
        if anim is not None:
            anim.samplers.append(g.AnimationSampler(input=times, output=weights,
                                                    interpolation="STEP"))
            anim.channels.append(g.AnimationChannel(
                sampler=len(anim.samplers) - 1,
                target=g.AnimationChannelTarget(node=len(doc.nodes) - 1, path="weights")))
    doc.nodes.append(g.Node(name="garmentgnn (Z up)", rotation=list(Z_UP_TO_Y_UP),
                            children=list(range(len(doc.nodes)))))
    doc.scenes.append(g.Scene(nodes=[len(doc.nodes) - 1], extras=dict(extras or {})))
    if anim is not None:
        doc.animations.append(anim)
    doc.buffers.append(g.Buffer(byteLength=len(blob)))
    doc.set_binary_blob(bytes(blob))
    return atomic_write_bytes(path, b"".join(doc.save_to_bytes()))


def sequence_meshes(seq: dict, body: bool = True) -> Tuple[List[GltfMesh], float]:
    """The garment (simulated positions) and, with ``body``, the posed body of a loaded
    sequence file (:func:`garmentgnn.data.store.load_sequence`), and its fps."""
    meta = seq["meta"]
    name = meta.get("garment", {}).get("kind", "garment") if isinstance(
        meta.get("garment"), dict) else "garment"
    meshes = [GltfMesh(name, seq["positions"], seq["garment_faces"], (0.30, 0.50, 0.78))]
    if body:
        b = build_body(meta["body"])
        dt = b.vertices.dtype
        with torch.no_grad():
            pos, _ = b.pose(torch.from_numpy(np.asarray(seq["motion_rotations"])).to(dt),
                            torch.from_numpy(np.asarray(seq["motion_translation"])).to(dt))
        meshes.append(GltfMesh("body", pos, b.faces, (0.8, 0.8, 0.8)))
    return meshes, float((meta.get("settings") or {}).get("fps", 30.0))
