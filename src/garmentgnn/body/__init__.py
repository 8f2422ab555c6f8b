"""Bodies: skeleton, shape, skinning (Eq. 1).  Z up, facing -Y, metres."""
from garmentgnn.body.body import Body, BodyModel
from garmentgnn.body.lbs import forward_kinematics, linear_blend_skinning
from garmentgnn.body.skeleton import ROLES, Skeleton

__all__ = ["Body", "BodyModel", "ROLES", "Skeleton", "forward_kinematics",
           "linear_blend_skinning"]
