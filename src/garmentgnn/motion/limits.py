"""Anatomical joint limits per skeleton role, as per-axis Euler ranges.

Axes are the body's world-aligned rest axes (Z up, body faces -Y, metres):
X is lateral (+X is the body's *left*), Y is front-back (-Y is forward), Z is up.
A joint's local rotation (axis-angle, relative to its parent in those axes, the
convention of :func:`garmentgnn.body.forward_kinematics`) is decomposed into
intrinsic Euler angles in the joint's fixed ``order`` and each axis' angle is
kept within ``[lower, upper]`` degrees.  Limits are indexed by axis (X, Y, Z),
not by position in ``order``.

Signs follow the right-hand rule about +X, +Y, +Z; for the *left* side and the
midline they mean:

* legs (bones point down): hip ``X < 0`` is flexion (thigh forward, -Y),
  ``Y < 0`` abduction (thigh out, +X), ``Z > 0`` external rotation; knee ``X > 0``
  is flexion (shank and foot go backwards, +Y); ankle ``X > 0`` is plantar
  flexion (toes down), ``X < 0`` dorsiflexion.
* arms (bones point down-out, the rest pose is an A-pose ~25 deg from vertical):
  shoulder ``X < 0`` is flexion (arm forward), ``Y < 0`` abduction (arm up
  sideways); elbow ``X < 0`` is flexion (hand forward/up), ``Z`` forearm
  pronation/supination; wrist ``Y > 0`` flexion toward the palm (palms face the
  thighs), ``X < 0`` radial deviation.
* spine, chest, neck, head (bones point up): ``X > 0`` bends forward, ``Y > 0``
  bends to the left, ``Z > 0`` turns to the left.

Right-side limits are the mirror image (reflection x -> -x): the X range is the
same, the Y and Z ranges are negated.  The root role ``pelvis`` carries the
global orientation and is not limited.

Ranges follow the normal active ranges of motion of the American Academy of
Orthopaedic Surgeons (AAOS, *Joint Motion: Method of Measuring and Recording*,
1965; as tabulated e.g. in Norkin & White, *Measurement of Joint Motion*):
hip flexion 120 / extension 30 / abduction 45 / adduction 30 / internal 40 /
external rotation 45; knee 0-150 (hinge only); ankle plantar flexion 50,
dorsiflexion 20 (widened to 30, the weight-bearing range needed to squat);
shoulder flexion 180 / extension 60 / abduction 180; elbow 0-150 with 80 deg of
pronation/supination; wrist flexion 80 / extension 70 / radial 20 / ulnar 30
deviation; cervical flexion 45-50 / extension 60 / lateral 45 / rotation 80 and
thoraco-lumbar flexion 80 / extension 25 / lateral 35 / rotation 45, split
between the neck/head and spine/chest joints.  Shoulder ranges are trimmed to
what one Euler decomposition can express without gimbal lock (its middle axis
stays inside +-90 deg), so very high forward flexion is reached by abduction.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Mapping, Optional, Tuple

import torch
from torch import Tensor

from garmentgnn.body.skeleton import ROLES, Skeleton
from garmentgnn.geometry.rotations import (axis_angle_to_matrix, euler_to_matrix,
                                           matrix_to_axis_angle, matrix_to_euler)

_AXIS = {"X": 0, "Y": 1, "Z": 2}


@dataclass(frozen=True)
class JointLimit:
    """Euler ``order`` (intrinsic, e.g. ``"XYZ"``: ``R = R_X R_Y R_Z``) and the
    per-axis ``lower``/``upper`` bounds in degrees, indexed X, Y, Z."""

    order: str
    lower: Tuple[float, float, float]
    upper: Tuple[float, float, float]

    def __post_init__(self) -> None:
        if sorted(self.order) != ["X", "Y", "Z"]:
            raise ValueError(f"`order`: expected a permutation of 'XYZ', got {self.order!r}")
        if len(self.lower) != 3 or len(self.upper) != 3:
            raise ValueError("`lower`/`upper`: expected three angles (X, Y, Z) in degrees")
        if any(lo > hi for lo, hi in zip(self.lower, self.upper)):
            raise ValueError(f"`lower` must not exceed `upper`: {self.lower} > {self.upper}")
        middle = _AXIS[self.order[1]]
        if self.lower[middle] <= -90.0 or self.upper[middle] >= 90.0:
            raise ValueError(f"the middle axis {self.order[1]} of order {self.order!r} must stay "
                             "inside (-90, 90) degrees (gimbal lock); choose another order")

    def mirrored(self) -> "JointLimit":
        """The limit of the mirror-image joint (reflection x -> -x): Y, Z ranges negated."""
        lo, hi = self.lower, self.upper
        return JointLimit(self.order, (lo[0], -hi[1], -hi[2]), (hi[0], -lo[1], -lo[2]))

    def in_order(self) -> Tuple[List[float], List[float]]:
        """Bounds rearranged into Euler-order positions."""
        idx = [_AXIS[a] for a in self.order]
        return [self.lower[i] for i in idx], [self.upper[i] for i in idx]


_LEFT_AND_MID: Dict[str, JointLimit] = {
    "spine": JointLimit("XYZ", (-25.0, -25.0, -30.0), (45.0, 25.0, 30.0)),
    "chest": JointLimit("XYZ", (-20.0, -25.0, -35.0), (40.0, 25.0, 35.0)),
    "neck": JointLimit("XYZ", (-40.0, -35.0, -60.0), (50.0, 35.0, 60.0)),
    "head": JointLimit("XYZ", (-30.0, -20.0, -25.0), (30.0, 20.0, 25.0)),
    "l_hip": JointLimit("XYZ", (-120.0, -45.0, -40.0), (30.0, 30.0, 45.0)),
    "l_knee": JointLimit("XYZ", (0.0, 0.0, 0.0), (150.0, 0.0, 0.0)),
    "l_ankle": JointLimit("XYZ", (-30.0, -20.0, -25.0), (50.0, 20.0, 25.0)),
    "l_shoulder": JointLimit("YXZ", (-85.0, -150.0, -90.0), (60.0, 40.0, 90.0)),
    "l_elbow": JointLimit("XYZ", (-150.0, 0.0, -80.0), (0.0, 0.0, 80.0)),
    "l_wrist": JointLimit("XYZ", (-20.0, -70.0, -10.0), (30.0, 80.0, 10.0)),
}

#: Role -> limit for every role in :data:`garmentgnn.body.ROLES` except the
#: unconstrained root ``pelvis``.
JOINT_LIMITS: Dict[str, JointLimit] = dict(_LEFT_AND_MID)
for _role, _lim in _LEFT_AND_MID.items():
    if _role.startswith("l_"):
        JOINT_LIMITS["r_" + _role[2:]] = _lim.mirrored()
assert set(JOINT_LIMITS) == set(ROLES) - {"pelvis"}


def joint_limits(skeleton: Skeleton, limits: Optional[Mapping[str, JointLimit]] = None
                 ) -> List[Optional[JointLimit]]:
    """Per joint of ``skeleton``, the limit of its role (``None``: no role / unlimited)."""
    if not isinstance(skeleton, Skeleton):
        raise ValueError(f"`skeleton`: expected a garmentgnn.body.Skeleton, got "
                         f"{type(skeleton).__name__}")
    table = JOINT_LIMITS if limits is None else limits
    unknown = set(table) - set(ROLES)
    if unknown:
        raise ValueError(f"`limits`: unknown role(s) {sorted(unknown)}; known roles: {ROLES}")
    out: List[Optional[JointLimit]] = [None] * skeleton.num_joints
    for role, name in skeleton.roles.items():
        if role in table:
            out[skeleton.joint_names.index(name)] = table[role]
    return out


def _check_rotations(rotations: Tensor, skeleton: Skeleton) -> Tensor:
    if not isinstance(rotations, Tensor):
        raise ValueError(f"`rotations`: expected a torch.Tensor [..., S, 3] of axis-angle, got "
                         f"{type(rotations).__name__}")
    if rotations.dim() < 2 or rotations.shape[-1] != 3:
        raise ValueError(f"`rotations`: expected [..., S, 3] axis-angle, got "
                         f"{tuple(rotations.shape)}")
    if rotations.shape[-2] != skeleton.num_joints:
        raise ValueError(f"`rotations`: has {rotations.shape[-2]} joints, the skeleton has "
                         f"{skeleton.num_joints}; retarget the motion first")
    if not torch.isfinite(rotations).all():
        raise ValueError("`rotations`: contain NaN/inf")
    return rotations


def _groups(lims: List[Optional[JointLimit]]) -> Dict[str, List[int]]:
    groups: Dict[str, List[int]] = {}
    for k, lim in enumerate(lims):
        if lim is not None:
            groups.setdefault(lim.order, []).append(k)
    return groups


def _bounds(lims: List[Optional[JointLimit]], idx: List[int]) -> Tuple[Tensor, Tensor]:
    lo = torch.tensor([lims[k].in_order()[0] for k in idx], dtype=torch.float64)
    hi = torch.tensor([lims[k].in_order()[1] for k in idx], dtype=torch.float64)
    return torch.deg2rad(lo), torch.deg2rad(hi)


def clamp_to_limits(rotations: Tensor, skeleton: Skeleton,
                    limits: Optional[Mapping[str, JointLimit]] = None) -> Tensor:
    """Clamp ``[..., S, 3]`` axis-angle rotations to the joint limits of their roles.

    Each limited joint is decomposed into Euler angles in its order, each angle
    clamped to its range, and converted back; joints already within their limits
    (and joints without a limited role) are returned unchanged, bit for bit.
    """
    _check_rotations(rotations, skeleton)
    lims = joint_limits(skeleton, limits)
    out = rotations.clone()
    for order, idx in _groups(lims).items():
        aa = rotations[..., idx, :].double()
        euler = matrix_to_euler(axis_angle_to_matrix(aa), order)
        lo, hi = _bounds(lims, idx)
        clamped = torch.maximum(torch.minimum(euler, hi), lo)
        changed = (clamped != euler).any(-1, keepdim=True)
        new = matrix_to_axis_angle(euler_to_matrix(clamped, order))
        out[..., idx, :] = torch.where(changed, new, aa).to(rotations.dtype)
    return out


def limit_violation(rotations: Tensor, skeleton: Skeleton,
                    limits: Optional[Mapping[str, JointLimit]] = None) -> Tensor:
    """``[..., S]`` largest excess over the joint's limits in degrees (0 when within)."""
    _check_rotations(rotations, skeleton)
    lims = joint_limits(skeleton, limits)
    out = torch.zeros(rotations.shape[:-1], dtype=torch.float64)
    for order, idx in _groups(lims).items():
        euler = matrix_to_euler(axis_angle_to_matrix(rotations[..., idx, :].double()), order)
        lo, hi = _bounds(lims, idx)
        excess = torch.maximum(lo - euler, euler - hi).clamp_min(0.0)
        out[..., idx] = torch.rad2deg(excess.amax(-1))
    return out


def within_limits(rotations: Tensor, skeleton: Skeleton, tol_deg: float = 1e-3,
                  limits: Optional[Mapping[str, JointLimit]] = None) -> bool:
    """Whether every joint of every frame is within its limits (up to ``tol_deg``)."""
    return bool((limit_violation(rotations, skeleton, limits) <= tol_deg).all())
