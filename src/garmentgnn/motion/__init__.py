"""Pose sequences (30 fps): procedural generators, BVH import/export, retargeting."""
from garmentgnn.motion.sequence import Motion

__all__ = ["Motion"]
