"""Bodies: skeleton, shape, skinning (Eq. 1).  Z up, facing -Y, metres."""
from garmentgnn.body.anny_body import AnnyBodyModel
from garmentgnn.body.body import Body, BodyModel
from garmentgnn.body.capsule import CapsuleBodyModel
from garmentgnn.body.factory import body_model, build_body
from garmentgnn.body.lbs import blend_transforms, forward_kinematics, linear_blend_skinning
from garmentgnn.body.skeleton import ROLES, Skeleton
from garmentgnn.body.smpl_body import SMPLBodyModel

__all__ = ["AnnyBodyModel", "Body", "BodyModel", "CapsuleBodyModel", "SMPLBodyModel", "ROLES",
           "Skeleton", "blend_transforms", "body_model", "build_body", "forward_kinematics",
           "linear_blend_skinning"]
