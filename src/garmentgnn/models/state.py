"""The recurrent vertex latent of :class:`~garmentgnn.models.GarTrans` (``vertex_state``).

The paper's model is frame-parallel: frame ``t`` sees the body's pose history, never where
the garment was.  With ``vertex_state=L`` (not in the paper; off by default) a latent
``h_v`` of ``L`` channels per vertex is carried frame to frame: it enters the dynamic
stack with the frame's features, and the stack's ``2L`` extra outputs update it by a gate
(a GRU-style convex step that keeps it in ``[-1, 1]``),
``h^t = (1 - z) h^{t-1} + z tanh(c)``, ``z = sigmoid(u)``.  The frames of a chunk run in
order, trained by truncated backpropagation through each chunk (the latent starts at zero
at a chunk's first frame).  A motion is predicted in frame order from a zero latent, and
the latent after the last frame is returned, which a next call continues from
(:meth:`~garmentgnn.models.sequence.SequencePrediction.predict_sequence`).

Measured on ``learn`` against the frame-parallel model, with a motion code in the dynamic
stack and autoregressive offsets (docs/experiments.md, "Which model can hold the state").
"""
from __future__ import annotations

from typing import Optional, Tuple

import torch
from torch import Tensor, nn

from garmentgnn.models.inputs import GarmentInputs
from garmentgnn.models.sequence import StaticFeatures

__all__ = ["recurrent_steps"]


def recurrent_steps(model: nn.Module, inputs: GarmentInputs, static: StaticFeatures,
                    prev: Tensor, cur: Tensor, joints: Tensor, R: Tensor,
                    state: Optional[Tensor] = None) -> Tuple[Tensor, Tensor, Tensor]:
    """The frames of ``inputs`` in order with a latent per vertex (module doc), for
    ``model``, a :class:`~garmentgnn.models.GarTrans`, from its coarse step; ``state``
    ``[V, L]``: the latent after the frame before (``None``: zeros).  Returns the garment
    ``[B, V, 3]``, the stack's ``a`` ``[B, V, 3]`` and the last latent."""
    L, (B, V) = model.vertex_state, cur.shape[:2]
    if state is None:
        h = cur.new_zeros(V, L)
    elif tuple(state.shape) != (V, L):
        raise ValueError(f"`state`: expected {(V, L)} (the `state` output of the call on the "
                         f"frames before), got {tuple(state.shape)}")
    else:
        h = state
    accel = []
    for b in range(B):
        sl = slice(b, b + 1)
        o = model.deform(inputs, prev[sl], cur[sl], joints[:, sl], R[sl], h[None])[0]
        z, c = torch.sigmoid(o[:, 3:3 + L]), torch.tanh(o[:, 3 + L:])
        h = (1 - z) * h + z * c
        accel.append(o[:, :3])
    a = torch.stack(accel)
    final = model.post_steps(inputs, static, cur + model._gate(2, a * model.unit))
    return final, a, h
