"""Kinematic inputs of a simulation: the skinned garment and the posed body for every
frame an engine steps through, including the pre-roll from the rest pose."""
from __future__ import annotations

from typing import Optional, Tuple

import torch
from torch import Tensor

from garmentgnn.body.body import Body
from garmentgnn.body.lbs import forward_kinematics, linear_blend_skinning
from garmentgnn.garments.placement import check_placement
from garmentgnn.garments.skinning import transfer_skinning_weights
from garmentgnn.motion.sequence import match_joints
from garmentgnn.sim.settings import DTYPE


def check_finite(t: Tensor, name: str) -> None:
    if not torch.isfinite(t).all():
        raise ValueError(f"`{name}`: contains NaN/inf")


def _smoothstep(P: int) -> Tensor:
    """``[P]`` weights ``3u^2 - 2u^3`` at ``u = k / P``, ``k = 0 .. P-1``."""
    u = torch.arange(P, dtype=DTYPE) / P
    return u * u * (3 - 2 * u)


def trajectories(garment, body: Optional[Body], motion, preroll_frames: int = 0,
                 body_frames: Optional[Tensor] = None) -> Tuple[Tensor, Optional[Tensor]]:
    """The garment's rest shape carried by the body, and the posed body, for every frame
    an engine steps through: ``preroll_frames`` frames that blend from the rest pose into
    the motion's first pose (joint rotations and root translation scaled by a smoothstep
    from 0 to 1, so the first is the rest pose itself), then the motion's frames.

    Returns ``(skinned [P + T, V, 3] float64, body_frames [P + T, Vb, 3] float64 or None)``.
    The skinned garment is the initial state and the pinned vertices' targets; its weights
    come from :func:`garmentgnn.garments.skinning.transfer_skinning_weights`.  Without a
    ``body`` the garment stays at rest (``preroll_frames`` must then be 0).
    ``body_frames [T, Vb, 3]`` may replace the posed body vertices."""
    verts = garment.vertices
    T, V, P = int(motion.num_frames), verts.shape[0], int(preroll_frames)
    if body is None and P:
        raise ValueError("`preroll_frames`: needs a `body` (nothing to blend into)")
    check_placement(verts, None if body is None else body.vertices)
    if body is not None:
        rot = match_joints(motion, body.skeleton.joint_names)
        trans = motion.translation
        if P:  # pre-roll: rest pose -> first pose (axis-angle scaling = slerp from identity)
            w = _smoothstep(P).to(rot.dtype)
            rot = torch.cat([w.view(P, 1, 1) * rot[:1], rot])
            trans = torch.cat([w.view(P, 1) * trans[:1].to(w.dtype), trans.to(w.dtype)])
        A, _ = forward_kinematics(rot.to(body.vertices.dtype), body.joints, body.skeleton.parents,
                                  trans.to(body.vertices.dtype))
        if body_frames is None:
            body_frames = linear_blend_skinning(body.vertices, body.weights, A)
        elif P:
            check_finite(body_frames, "body_frames")
            w = _smoothstep(P).to(body_frames.dtype).view(P, 1, 1)
            rest = body.vertices.to(body_frames.dtype)
            body_frames = torch.cat([(1 - w) * rest + w * body_frames[:1], body_frames])
        W = transfer_skinning_weights(verts.float(), garment.faces, body.vertices.float(),
                                      body.weights.float())
        skinned = linear_blend_skinning(verts.to(A.dtype), W.to(A.dtype), A).to(DTYPE)
    else:
        skinned = verts.to(DTYPE).unsqueeze(0).expand(T, V, 3)
        if body_frames is not None:
            raise ValueError("`body_frames`: given without a `body`")
    if body_frames is not None:
        if body_frames.dim() != 3 or body_frames.shape[0] != T + P:
            raise ValueError(f"`body_frames`: expected [{T}, Vb, 3] (one per motion frame), got "
                             f"{(body_frames.shape[0] - P,) + tuple(body_frames.shape[1:])}")
        check_finite(body_frames, "body_frames")
        body_frames = body_frames.detach().to(DTYPE)
    return skinned, body_frames


