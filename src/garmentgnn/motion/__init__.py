"""Pose sequences (30 fps): procedural generators, BVH import/export, retargeting."""
from garmentgnn.motion.bvh import BVHHierarchy, load_bvh, save_bvh
from garmentgnn.motion.generators import (GRAVITY, MOTIONS, arm_swing, blend, concat, jump,
                                          kick, make_motion, run, sit_stand, slerp_rotations,
                                          twirl, walk)
from garmentgnn.motion.limits import (JOINT_LIMITS, JointLimit, clamp_to_limits, joint_limits,
                                      limit_violation, within_limits)
from garmentgnn.motion.retarget import ROLE_ALIASES, guess_roles, joint_mapping, retarget
from garmentgnn.motion.sequence import Motion

__all__ = [
    "BVHHierarchy", "GRAVITY", "JOINT_LIMITS", "JointLimit", "MOTIONS", "Motion",
    "ROLE_ALIASES", "arm_swing", "blend", "clamp_to_limits", "concat", "guess_roles",
    "joint_limits",
    "joint_mapping", "jump", "kick", "limit_violation", "load_bvh", "make_motion", "retarget",
    "run", "save_bvh", "sit_stand", "slerp_rotations", "twirl", "walk", "within_limits",
]
