"""A stand-in for the simulator: the garment skinned to the moving body plus a smooth
wobble, with no physics.  Deterministic and fast, it makes datasets without simulating
(:func:`skinned_wobble`, for ``generate(simulate_fn=...)``) and moving garment-body
scenes for checking and timing the garment-body searches (:func:`wobbling_frames`)."""
from __future__ import annotations

from types import SimpleNamespace
from typing import Optional, Tuple

import torch
from torch import Tensor

from garmentgnn.body.lbs import forward_kinematics, linear_blend_skinning
from garmentgnn.garments.skinning import transfer_skinning_weights

#: the wobble's amplitude (m)
WOBBLE = 0.003


def wobbling_frames(garment, body, motion, dtype: Optional[torch.dtype] = None
                    ) -> Tuple[Tensor, Tensor]:
    """``(garment [T, V, 3], body [T, Vb, 3])`` in ``dtype`` (default: the body's) over
    the motion's frames: the posed body, and the garment skinned to it (weights from
    :func:`garmentgnn.garments.skinning.transfer_skinning_weights`) plus a smooth wave,
    ``WOBBLE * sin(0.7 t + 8 x)`` on each coordinate (``t``: the frame, ``x``: the
    vertex's rest x)."""
    d = body.vertices.dtype if dtype is None else dtype
    A, _ = forward_kinematics(motion.rotations.to(d), body.joints.to(d), body.skeleton.parents,
                              motion.translation.to(d))
    X = linear_blend_skinning(body.vertices.to(d), body.weights.to(d), A)
    W = transfer_skinning_weights(garment.vertices, garment.faces, body.vertices, body.weights)
    P = linear_blend_skinning(garment.vertices.to(d), W.to(d), A)
    T = motion.num_frames
    t = torch.arange(T, dtype=d).view(T, 1, 1)
    P = P + WOBBLE * torch.sin(0.7 * t + 8.0 * garment.vertices[None, :, :1].to(d))
    return P, X


def skinned_wobble(garment, body, motion, material, settings=None, progress=None
                   ) -> SimpleNamespace:
    """:func:`garmentgnn.sim.simulate`'s signature and result fields, the garment of
    :func:`wobbling_frames` (float32) as the simulated one: every frame converged in one
    Newton iteration, no residual (``material``, ``settings``, ``progress``: unused)."""
    T = motion.num_frames
    P, _ = wobbling_frames(garment, body, motion)
    return SimpleNamespace(positions=P.float(), converged=torch.ones(T, dtype=torch.bool),
                           newton_iterations=torch.full((T,), 1), residual=torch.zeros(T),
                           ok=True, message="", seconds=0.0)
