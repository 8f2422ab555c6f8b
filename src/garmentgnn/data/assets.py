"""A dataset's own files: garment meshes (OBJ, PLY, glTF ...) and mocap (BVH) as spec
entries, and the garment, motion they build on a body.

A spec entry that names a file (:mod:`garmentgnn.data.spec_file`) keeps the file as it
was written in the spec (``file``), its resolved absolute ``path`` and its content's
``sha256``; the item id hashes the name and the content, not the path, so a changed mesh
is a changed dataset and a moved folder is the same one.  Workers rebuild the garment
and the motion from the entry and refuse a file whose content changed since.

Garment files are refused (``ValueError`` naming the file and the fix) when they have
more than :data:`MAX_VERTICES` vertices, a non-manifold edge (:func:`load_garment`), lie
away from the body (:func:`~garmentgnn.garments.placement.check_placement`) or partly
inside it at rest (deeper than :data:`MAX_INSIDE`).  BVH files are refused without
frames, with NaN channels, with joints that match none of the body's roles and no
``mapping``, a frame rate other than the entry's ``fps``, or fewer frames (at the
dataset's frame rate) than the spec asks for.
"""
from __future__ import annotations

import hashlib
import re
from pathlib import Path
from typing import Any, Dict, Optional

import torch

from garmentgnn.body.body import Body
from garmentgnn.body.skeleton import ROLES
from garmentgnn.garments.garment import Garment
from garmentgnn.garments.io import load_garment
from garmentgnn.garments.placement import check_placement
from garmentgnn.geometry.distance import signed_distance
from garmentgnn.motion.bvh import load_bvh
from garmentgnn.motion.retarget import joint_mapping, retarget
from garmentgnn.motion.sequence import Motion

#: the most vertices a garment file may have (the simulators and models are sized for
#: garments of hundreds to a few thousand vertices)
MAX_VERTICES = 50_000
#: the deepest a garment vertex may lie inside the body at rest (metres)
MAX_INSIDE = 0.01
#: the body's roles a BVH file must drive (the rest stay at rest when unmapped)
REQUIRED_ROLES = ("pelvis", "l_hip", "l_knee", "r_hip", "r_knee", "l_shoulder", "r_shoulder")


def sha256_of(path) -> str:
    """The SHA-256 of a file's content (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def file_name(entry: Dict[str, Any]) -> str:
    """A readable, id-safe name of a file entry (its stem)."""
    return re.sub(r"[^A-Za-z0-9_]+", "_", Path(entry["file"]).stem) or "file"


def checked_path(entry: Dict[str, Any]) -> Path:
    """The entry's file, refused (``ValueError``) when it is gone or its content is not
    the one the spec was read with."""
    path = Path(entry["path"])
    if not path.is_file():
        raise ValueError(f"{path}: no such file (named {entry['file']!r} in the spec); "
                         f"restore it, or read the spec again without it")
    sha = sha256_of(path)
    if sha != entry["sha256"]:
        raise ValueError(f"{path}: changed since the spec was read (SHA-256 {sha[:12]}, the "
                         f"spec's {entry['sha256'][:12]}); a changed file is another "
                         f"dataset: rerun `garmentgnn generate --spec` into another --out")
    return path


# --------------------------------------------------------------------------- garments
def _count_obj_vertices(path: Path) -> Optional[int]:
    if path.suffix.lower() != ".obj":
        return None
    data = path.read_bytes()
    return data.count(b"\nv ") + data.startswith(b"v ")


def _too_many(path: Path, n: int) -> ValueError:
    return ValueError(f"{path}: {n:,} vertices, more than {MAX_VERTICES:,}; decimate or "
                      f"remesh it (e.g. Blender's Decimate modifier) to at most "
                      f"{MAX_VERTICES:,}")


def read_garment_file(path, name: Optional[str] = None) -> Garment:
    """A garment mesh file, validated (:func:`load_garment`) and at most
    :data:`MAX_VERTICES` vertices; ``ValueError`` naming the file and the fix."""
    path = Path(path)
    n = _count_obj_vertices(path) if path.is_file() else None
    if n is not None and n > MAX_VERTICES:  # before parsing a huge file
        raise _too_many(path, n)
    try:
        garment = load_garment(path, name=name)
    except ValueError as exc:
        msg = str(exc)
        if "non-manifold" in msg:
            msg += ("; split those edges in a modelling tool (each edge of a garment "
                    "belongs to one or two faces)")
        raise ValueError(msg) from None
    if garment.num_vertices > MAX_VERTICES:
        raise _too_many(path, garment.num_vertices)
    return garment


def check_fit(garment: Garment, body: Body, where: str) -> None:
    """``ValueError`` naming ``where`` (the file) when the garment lies away from the
    body or deeper than :data:`MAX_INSIDE` inside it at rest."""
    try:
        check_placement(garment.vertices, body.vertices.float())
    except ValueError as exc:
        raise ValueError(f"{where}: {str(exc).split(': ', 1)[-1]}") from None
    with torch.no_grad():
        d = signed_distance(garment.vertices.double(), body.vertices.double(),
                            body.faces.long(), candidates=16).distance
    depth = float(-d.min())
    if depth > MAX_INSIDE:
        n = int((d < -MAX_INSIDE).sum())
        raise ValueError(f"{where}: {n} vertices lie inside the body at rest, up to "
                         f"{depth * 100:.1f} cm deep (at most {MAX_INSIDE * 100:.0f} cm); "
                         f"model the garment around this body in its rest pose (or on a "
                         f"larger body), or list only bodies it fits")


def garment_from_entry(entry: Dict[str, Any], body: Body) -> Garment:
    """The garment of a file entry on ``body`` (checked: :func:`checked_path`,
    :func:`read_garment_file`, :func:`check_fit`)."""
    path = checked_path(entry)
    garment = read_garment_file(path, name=file_name(entry))
    check_fit(garment, body, str(path))
    return garment


# --------------------------------------------------------------------------- motions
def read_bvh_file(path, scale: float = 1.0, up: str = "Y"):
    """``(hierarchy, motion)`` of a BVH file; ``ValueError`` naming the file for zero
    frames and NaN/inf channels."""
    path = Path(path)
    try:
        hierarchy, motion = load_bvh(path, scale=scale, up=up, dtype=torch.float64)
    except ValueError as exc:
        msg = str(exc)
        if "NaN" in msg or "nan" in msg:
            raise ValueError(f"{path}: its channels hold NaN/inf values ({msg}); export "
                             f"the take again, or cut the frames that hold them") from None
        raise ValueError(msg if msg.startswith(str(path)) else f"{path}: {msg}") from None
    if motion.num_frames == 0:
        raise ValueError(f"{path}: no frames (Frames: 0); export the take with its motion")
    return hierarchy, motion


def check_roles(path, source_names, body: Body, mapping: Optional[Dict[str, str]],
                skeleton) -> None:
    """``ValueError`` naming the file when the body's :data:`REQUIRED_ROLES` joints get
    no joint of the file (no ``mapping`` and names the role table does not know)."""
    if mapping:
        return
    got = joint_mapping(source_names, body.skeleton, None, skeleton)
    target = list(body.skeleton.joint_names)
    missing = [r for r in REQUIRED_ROLES if r in body.skeleton.roles
               and target.index(body.skeleton.roles[r]) not in got]
    if missing:
        raise ValueError(
            f"{path}: its joints ({', '.join(list(source_names)[:6])}, ...) match none of "
            f"the body's {', '.join(missing)}; map them: a `mapping:` of file joint -> body "
            f"joint or role ({', '.join(ROLES[:3])}, ...) on the spec's motion entry, e.g. "
            f"{{{list(source_names)[0]}: pelvis}} (predict: --mapping "
            f"{list(source_names)[0]}=pelvis,...)")


def motion_from_entry(entry: Dict[str, Any], body: Body, fps: float,
                      num_frames: Optional[int] = None) -> Motion:
    """The motion of a BVH entry on ``body``: read (``scale``, ``up``), retargeted by
    name, role or ``mapping`` (:func:`retarget` with both rests), resampled to ``fps``
    (rotations by slerp, :meth:`Motion.resample`), frames ``start ..
    start + num_frames`` (default the entry's ``num_frames``, else every frame)."""
    path = checked_path(entry)
    hierarchy, motion = read_bvh_file(path, entry.get("scale", 1.0), entry.get("up", "Y"))
    stated = entry.get("fps")
    if stated is not None and abs(float(stated) - motion.fps) > 1e-3 * motion.fps:
        raise ValueError(f"{path}: its Frame Time gives {motion.fps:g} fps, the spec says "
                         f"fps {stated:g}; correct the motion entry's `fps` (or drop it: "
                         f"the file's rate is read and resampled to the dataset's)")
    mapping = entry.get("mapping") or None
    skeleton = hierarchy.to_skeleton()
    check_roles(path, motion.joint_names, body, mapping, skeleton)
    try:
        moved = retarget(motion, body.skeleton, mapping, source_skeleton=skeleton,
                         source_rest=hierarchy.rest_joints,
                         target_rest=body.joints.to(torch.float64))
    except ValueError as exc:
        raise ValueError(f"{path}: {str(exc).replace('`name_map`', '`mapping`')}") from None
    moved = moved.resample(float(fps)) if abs(moved.fps - fps) > 1e-9 else moved
    start = entry.get("start", 0)
    if not isinstance(start, int) or isinstance(start, bool) or start < 0:
        raise ValueError(f"`start`: expected a first frame >= 0 of {path}, got {start!r}")
    if start >= moved.num_frames:
        raise ValueError(f"`start` {start} is beyond the take {path}: it has "
                         f"{moved.num_frames} frames at {fps:g} fps (from "
                         f"{motion.num_frames} at {motion.fps:g} fps); give a `start` "
                         f"below {moved.num_frames}")
    have = moved.num_frames - start
    n = num_frames or entry.get("num_frames") or max(have, 1)  # none given: every frame
    if have < n:
        raise ValueError(f"{path}: {have} frames at {fps:g} fps (from {motion.num_frames} at "
                         f"{motion.fps:g} fps{f', after start {start}' if start else ''}), "
                         f"the spec asks for {n}; lower `frames` to {max(have, 0)} or less, "
                         f"or use a longer take")
    sl = slice(start, start + n)
    return Motion(moved.rotations[sl].contiguous(), moved.translation[sl].contiguous(),
                  list(moved.joint_names), float(fps))


__all__ = ["MAX_INSIDE", "MAX_VERTICES", "REQUIRED_ROLES", "check_fit", "checked_path",
           "file_name", "garment_from_entry", "motion_from_entry", "read_bvh_file",
           "read_garment_file", "sha256_of"]
