"""Joint hierarchy with semantic roles shared by every body model and motion generator."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Sequence

import torch
from torch import Tensor

#: Semantic joint roles that procedural motions drive.  A skeleton maps each
#: role it has to one of its joint names; roles it lacks are simply not animated.
ROLES = (
    "pelvis", "spine", "chest", "neck", "head",
    "l_hip", "l_knee", "l_ankle", "r_hip", "r_knee", "r_ankle",
    "l_shoulder", "l_elbow", "l_wrist", "r_shoulder", "r_elbow", "r_wrist",
)


@dataclass
class Skeleton:
    """A joint tree: names, parent indices (root has -1, parents precede children)
    and a role -> joint-name map used by motion generators and retargeting."""

    joint_names: List[str]
    parents: Tensor
    roles: Dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.parents = torch.as_tensor(self.parents, dtype=torch.long)
        S = len(self.joint_names)
        if self.parents.shape != (S,):
            raise ValueError(f"`parents`: expected shape [{S}] (one per joint name), "
                             f"got {tuple(self.parents.shape)}")
        if len(set(self.joint_names)) != S:
            raise ValueError("`joint_names`: names must be unique")
        if S == 0 or int(self.parents[0]) != -1:
            raise ValueError("`parents`: joint 0 must be the root (parent -1)")
        for i in range(1, S):
            p = int(self.parents[i])
            if not 0 <= p < i:
                raise ValueError(f"`parents`: joint {i} ({self.joint_names[i]!r}) has parent {p}; "
                                 "parents must precede their children (topological order)")
        unknown = set(self.roles) - set(ROLES)
        if unknown:
            raise ValueError(f"`roles`: unknown role(s) {sorted(unknown)}; known roles: {ROLES}")
        missing = [n for n in self.roles.values() if n not in self.joint_names]
        if missing:
            raise ValueError(f"`roles`: joint name(s) {missing} are not in joint_names")

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    def index(self, name: str) -> int:
        """Index of a joint by name or role (``ValueError`` naming the unknown one)."""
        if name in self.roles:
            name = self.roles[name]
        try:
            return self.joint_names.index(name)
        except ValueError:
            raise ValueError(f"unknown joint {name!r}; this skeleton has "
                             f"{self.num_joints} joints: {self.joint_names}") from None

    def indices(self, names: Sequence[str]) -> List[int]:
        return [self.index(n) for n in names]
