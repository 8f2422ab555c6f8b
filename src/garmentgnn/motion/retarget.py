"""Transfer a motion from one skeleton to another.

Joints are matched by a name map (source name -> target name); by default by
identical names, then by matching semantic roles when both skeletons define
them.  Unmapped target joints stay at rest (identity local rotation).

With the source skeleton known (``source_skeleton``), each mapped target joint
takes the source joint's *global* orientation, so extra or missing intermediate
joints (a clavicle, three spine joints instead of two) do not distort the pose;
with both rest poses given (``source_rest``/``target_rest``) bone directions are
matched too (a T-pose source drives an A-pose target).  Without the source
skeleton, local rotations of mapped joints are copied as they are.
"""
from __future__ import annotations

import math
import re
from typing import Dict, List, Mapping, Optional, Sequence

import torch
from torch import Tensor

from garmentgnn.body.skeleton import ROLES, Skeleton
from garmentgnn.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from garmentgnn.motion.sequence import Motion

#: Role -> joint names used by common rigs, in order of preference (compared
#: case-insensitively, ignoring ``_``, ``-``, spaces and a ``namespace:`` prefix).
#: CMU/Mixamo ``LeftArm`` is the shoulder joint (``LeftShoulder`` is the clavicle);
#: SMPL's ``left_shoulder`` is the shoulder joint (``left_collar`` the clavicle).
ROLE_ALIASES: Dict[str, List[str]] = {
    "pelvis": ["Hips", "Pelvis", "Hip", "Root"],
    "spine": ["LowerBack", "Spine", "Spine1", "Abdomen", "Waist"],
    "chest": ["Spine1", "Chest", "Spine2", "Spine3", "UpperChest"],
    "neck": ["Neck", "Neck1"],
    "head": ["Head"],
    "l_hip": ["LeftUpLeg", "LeftHip", "LeftThigh", "LThigh", "LHip", "LeftUpperLeg"],
    "l_knee": ["LeftLeg", "LeftKnee", "LeftShin", "LShin", "LKnee", "LeftLowerLeg"],
    "l_ankle": ["LeftFoot", "LeftAnkle", "LFoot", "LAnkle"],
    "r_hip": ["RightUpLeg", "RightHip", "RightThigh", "RThigh", "RHip", "RightUpperLeg"],
    "r_knee": ["RightLeg", "RightKnee", "RightShin", "RShin", "RKnee", "RightLowerLeg"],
    "r_ankle": ["RightFoot", "RightAnkle", "RFoot", "RAnkle"],
    "l_shoulder": ["LeftArm", "LeftUpArm", "LeftUpperArm", "LUpArm", "LShoulder",
                   "LeftShoulder"],
    "l_elbow": ["LeftForeArm", "LeftElbow", "LeftLowerArm", "LForeArm", "LElbow"],
    "l_wrist": ["LeftHand", "LeftWrist", "LHand", "LWrist"],
    "r_shoulder": ["RightArm", "RightUpArm", "RightUpperArm", "RUpArm", "RShoulder",
                   "RightShoulder"],
    "r_elbow": ["RightForeArm", "RightElbow", "RightLowerArm", "RForeArm", "RElbow"],
    "r_wrist": ["RightHand", "RightWrist", "RHand", "RWrist"],
}


def _norm(name: str) -> str:
    """``mixamorig:Left_Up-Leg`` -> ``leftupleg``."""
    return re.sub(r"[\s_\-.]", "", name.rsplit(":", 1)[-1]).lower()


_SMPL = {"pelvis": "pelvis", "spine": "spine1", "chest": "spine3", "neck": "neck",
         "head": "head", "l_hip": "lefthip", "l_knee": "leftknee", "l_ankle": "leftankle",
         "r_hip": "righthip", "r_knee": "rightknee", "r_ankle": "rightankle",
         "l_shoulder": "leftshoulder", "l_elbow": "leftelbow", "l_wrist": "leftwrist",
         "r_shoulder": "rightshoulder", "r_elbow": "rightelbow", "r_wrist": "rightwrist"}


def guess_roles(joint_names: Sequence[str]) -> Dict[str, str]:
    """Role -> joint name for joints named after a common rig (CMU, Mixamo, SMPL).

    Each role takes its first alias (:data:`ROLE_ALIASES`) that is present and
    not yet taken by an earlier role; SMPL names (``left_collar``,
    ``spine3``...) use SMPL's own table.  Roles without a match are left out.
    """
    by_norm: Dict[str, str] = {}
    for n in joint_names:
        by_norm.setdefault(_norm(n), n)
    is_smpl = "leftcollar" in by_norm or ("spine3" in by_norm and "lefthip" in by_norm)
    used = set()
    roles: Dict[str, str] = {}
    for role in ROLES:
        candidates = [_SMPL[role]] if is_smpl else [_norm(a) for a in ROLE_ALIASES[role]]
        for c in candidates:
            if c in by_norm and by_norm[c] not in used:
                roles[role] = by_norm[c]
                used.add(by_norm[c])
                break
    return roles


def _check_rest(rest, skeleton: Skeleton, what: str) -> Tensor:
    r = torch.as_tensor(rest).detach().to(torch.float64)
    if r.shape != (skeleton.num_joints, 3) or not torch.isfinite(r).all():
        raise ValueError(f"`{what}`: expected finite [{skeleton.num_joints}, 3] rest joint "
                         f"positions, got {tuple(r.shape)}")
    return r


def _resolve(name: str, names: List[str], roles: Mapping[str, str], what: str) -> int:
    if name in names:
        return names.index(name)
    if name in roles:
        return names.index(roles[name])
    raise ValueError(f"`name_map`: unknown {what} joint {name!r}; {what} joints are {names}"
                     + (f" (roles: {sorted(roles)})" if roles else ""))


def joint_mapping(source_names: Sequence[str], target: Skeleton,
                  name_map: Optional[Mapping[str, str]] = None,
                  source_skeleton: Optional[Skeleton] = None) -> Dict[int, int]:
    """Target joint index -> source joint index (see :func:`retarget`)."""
    src = list(source_names)
    tgt = list(target.joint_names)
    src_roles = dict(source_skeleton.roles) if source_skeleton is not None else {}
    mapping: Dict[int, int] = {}
    if name_map is not None:
        if not isinstance(name_map, Mapping):
            raise ValueError(f"`name_map`: expected a dict source name -> target name, got "
                             f"{type(name_map).__name__}")
        for s, t in name_map.items():
            si = _resolve(s, src, src_roles, "source")
            ti = _resolve(t, tgt, target.roles, "target")
            if ti in mapping:
                raise ValueError(f"`name_map`: target joint {tgt[ti]!r} is mapped twice")
            mapping[ti] = si
        return mapping
    for ti, t in enumerate(tgt):
        if t in src:
            mapping[ti] = src.index(t)
    if source_skeleton is not None:
        taken = set(mapping.values())
        for role, tname in target.roles.items():
            ti = tgt.index(tname)
            if ti in mapping or role not in src_roles:
                continue
            si = src.index(src_roles[role])
            if si not in taken:
                mapping[ti] = si
                taken.add(si)
    return mapping


def _min_rotation(a: Tensor, b: Tensor) -> Tensor:
    """The smallest rotation taking direction ``a`` to direction ``b`` (``[3, 3]``)."""
    a = a / a.norm()
    b = b / b.norm()
    axis = torch.linalg.cross(a, b)
    s, c = axis.norm(), float(a @ b)
    if s < 1e-12:
        if c > 0:
            return torch.eye(3, dtype=a.dtype)
        perp = torch.tensor([1.0, 0.0, 0.0], dtype=a.dtype)
        if abs(float(a[0])) > 0.9:
            perp = torch.tensor([0.0, 1.0, 0.0], dtype=a.dtype)
        axis = torch.linalg.cross(a, perp)
        return axis_angle_to_matrix(axis / axis.norm() * math.pi)
    return axis_angle_to_matrix(axis / s * math.atan2(float(s), c))


def retarget(motion: Motion, target_skeleton: Skeleton,
             name_map: Optional[Mapping[str, str]] = None, *,
             source_skeleton: Optional[Skeleton] = None, source_rest: Optional[Tensor] = None,
             target_rest: Optional[Tensor] = None,
             translation_scale: Optional[float] = None) -> Motion:
    """``motion`` on ``target_skeleton``.

    Args:
        motion: the source motion (its ``joint_names`` are the source joints).
        target_skeleton: the skeleton to drive.
        name_map: ``{source name: target name}`` (role names are accepted on either
            side when the skeleton defines them).  Only these pairs are mapped.
            Default: identical names, then joints whose roles match (roles need
            ``source_skeleton``).
        source_skeleton: the source's tree (``joint_names`` must equal the
            motion's); enables role matching and global-orientation transfer.
        source_rest, target_rest: ``[S, 3]`` rest joint positions; with both (and
            ``source_skeleton``) bone directions of single-child joints are
            matched and the translation scale defaults to the ratio of the
            skeletons' heights (z-extent of their rest joints).
        translation_scale: multiplies root positions (default as above, else 1).

    Returns:
        A :class:`Motion` over ``target_skeleton.joint_names``; unmapped target
        joints have zero rotation.  With both rests the root's absolute position
        (rest + translation) is scaled, so the floor stays at ``z = 0``;
        otherwise the translation itself is scaled.
    """
    if not isinstance(motion, Motion):
        raise ValueError(f"`motion`: expected a Motion, got {type(motion).__name__}")
    if not isinstance(target_skeleton, Skeleton):
        raise ValueError(f"`target_skeleton`: expected a Skeleton, got "
                         f"{type(target_skeleton).__name__}")
    if source_skeleton is not None:
        if not isinstance(source_skeleton, Skeleton):
            raise ValueError(f"`source_skeleton`: expected a Skeleton, got "
                             f"{type(source_skeleton).__name__}")
        if list(source_skeleton.joint_names) != list(motion.joint_names):
            raise ValueError("`source_skeleton`: its joint_names must equal the motion's "
                             "joint_names (same joints, same order)")
    if (source_rest is None) != (target_rest is None):
        raise ValueError("`source_rest`/`target_rest`: give both or neither")
    if source_rest is not None and source_skeleton is None:
        raise ValueError("`source_rest`: needs `source_skeleton` (the source's parents)")
    if not torch.isfinite(motion.rotations).all() or not torch.isfinite(motion.translation).all():
        raise ValueError("`motion`: rotations/translation contain NaN/inf")
    if translation_scale is not None and (
            isinstance(translation_scale, bool) or not isinstance(translation_scale, (int, float))
            or not math.isfinite(translation_scale) or translation_scale <= 0):
        raise ValueError(f"`translation_scale`: expected a positive number, got "
                         f"{translation_scale!r}")
    mapping = joint_mapping(motion.joint_names, target_skeleton, name_map, source_skeleton)
    if not mapping:
        raise ValueError("`name_map`: no target joint matches a source joint (by name or "
                         "role); pass name_map={source name: target name}")
    src_rest = tgt_rest = None
    if source_rest is not None:
        src_rest = _check_rest(source_rest, source_skeleton, "source_rest")
        tgt_rest = _check_rest(target_rest, target_skeleton, "target_rest")

    dtype = motion.rotations.dtype
    T, St = motion.num_frames, target_skeleton.num_joints
    Rs = axis_angle_to_matrix(motion.rotations.detach().to(torch.float64))  # [T, Ss, 3, 3]
    tpar = target_skeleton.parents.tolist()
    eye = torch.eye(3, dtype=torch.float64).expand(T, 3, 3)
    if source_skeleton is None:
        Rt = eye.unsqueeze(1).expand(T, St, 3, 3).clone()
        for ti, si in mapping.items():
            Rt[:, ti] = Rs[:, si]
    else:
        spar = source_skeleton.parents.tolist()
        Gs = [Rs[:, 0]]
        for k in range(1, len(spar)):
            Gs.append(Gs[spar[k]] @ Rs[:, k])
        Q = [torch.eye(3, dtype=torch.float64) for _ in range(St)]
        if src_rest is not None:
            children: List[List[int]] = [[] for _ in range(St)]
            for k in range(1, St):
                children[tpar[k]].append(k)
            for ti, si in mapping.items():
                kids = [c for c in children[ti] if c in mapping]
                if len(kids) != 1:
                    continue
                c = kids[0]
                rt = tgt_rest[c] - tgt_rest[ti]
                rs = src_rest[mapping[c]] - src_rest[si]
                if rt.norm() > 1e-9 and rs.norm() > 1e-9:
                    Q[ti] = _min_rotation(rt, rs)
        Gt: List[Tensor] = []
        Rt_list: List[Tensor] = []
        for k in range(St):
            parent_G = Gt[tpar[k]] if k > 0 else eye
            if k in mapping:
                G = Gs[mapping[k]] @ Q[k]
                Rt_list.append(parent_G.transpose(-1, -2) @ G)
            else:
                G = parent_G
                Rt_list.append(eye)
            Gt.append(G)
        Rt = torch.stack(Rt_list, 1)
    rot = matrix_to_axis_angle(Rt)

    tr = motion.translation.detach().to(torch.float64)
    if src_rest is not None:
        scale = translation_scale
        if scale is None:
            hs = float(src_rest[:, 2].max() - src_rest[:, 2].min())
            ht = float(tgt_rest[:, 2].max() - tgt_rest[:, 2].min())
            scale = ht / hs if hs > 1e-9 and ht > 1e-9 else 1.0
        tr = scale * (src_rest[0] + tr) - tgt_rest[0]
    elif translation_scale is not None:
        tr = tr * translation_scale
    return Motion(rot.to(dtype), tr.to(motion.translation.dtype),
                  list(target_skeleton.joint_names), motion.fps)


__all__ = ["ROLE_ALIASES", "guess_roles", "joint_mapping", "retarget"]
