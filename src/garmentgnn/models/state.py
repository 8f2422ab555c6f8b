"""The garment's state carried frame to frame by :class:`~garmentgnn.models.GarTrans`.

The paper's model is frame-parallel: frame ``t`` sees the body's pose history, never where
the garment was.  Two ways to carry a state (not in the paper; options of GarTrans, one
at a time), each running the dynamic stack frame after frame:

* :func:`recurrent_steps` (``vertex_state=L``): a latent ``h_v`` of ``L`` channels per
  vertex enters the stack with the frame's features; the stack's ``2L`` extra outputs
  update it by a gate (a GRU-style convex step that keeps it in ``[-1, 1]``),
  ``h^t = (1 - z) h^{t-1} + z tanh(c)``, ``z = sigmoid(u)``.  Trained by truncated
  backpropagation through each chunk (the latent starts at zero at a chunk's first frame).
* :func:`autoregressive_steps` (``autoregressive=True``): the stack reads the garment's own
  offsets from the coarse mesh at ``t-1`` and ``t-2``, ``d = M^{d} - M^{c}`` (and their
  difference, the offset's velocity), and the output keeps the last one,
  ``M^{t,d} = M^{t,c} + d_{t-1} + g_a a u``: with ``a = 0`` the previous frame carried by
  the skinned motion.  Trained with MeshGraphNets' and HOOD's recipe
  (:class:`TeacherForcing`): rollouts of ``k`` frames from the simulated frames before
  them with Gaussian noise on those positions, gradients through the rollout.

Both predict a whole motion in frame order from no state (zero latent, zero offsets) and
return the state after their last frame, which a next call continues from
(:meth:`~garmentgnn.models.sequence.SequencePrediction.predict_sequence`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

import torch
from torch import Tensor, nn

from garmentgnn.models.inputs import GarmentInputs
from garmentgnn.models.sequence import StaticFeatures

__all__ = ["TeacherForcing", "autoregressive_steps", "recurrent_steps"]


@dataclass
class TeacherForcing:
    """How an ``autoregressive`` GarTrans trains on a chunk: rollouts of ``rollout``
    frames, each started from the simulated garment ``gt`` ``[B, V, 3]`` at the two
    frames before it with Gaussian noise of ``noise`` metres (a chunk's first two frames
    start from no state, as a test rollout does)."""

    gt: Tensor
    rollout: int = 1
    noise: float = 0.0

    def __post_init__(self) -> None:
        self.check(self.rollout, self.noise)

    @staticmethod
    def check(rollout: int, noise: float, ramp: int = 0) -> None:
        """A ``ValueError`` unless ``rollout`` is an int >= 1, ``noise`` >= 0 and ``ramp``
        an int >= 0."""
        if not isinstance(rollout, int) or isinstance(rollout, bool) or rollout < 1:
            raise ValueError(f"`rollout`: expected frames >= 1, got {rollout!r}")
        if not (isinstance(noise, (int, float)) and noise >= 0):
            raise ValueError(f"`rollout_noise`: expected metres >= 0, got {noise!r}")
        if not isinstance(ramp, int) or isinstance(ramp, bool) or ramp < 0:
            raise ValueError(f"`rollout_ramp`: expected optimizer steps >= 0, got {ramp!r}")

    @staticmethod
    def length(rollout: int, ramp: int, step: int) -> int:
        """The rollout length at optimizer step ``step``: ``1 + (rollout - 1) min(1, step /
        ramp)`` rounded down, growing from 1 to ``rollout`` over ``ramp`` steps (HOOD: by
        one every 5,000 iterations); ``rollout`` from the start where ``ramp`` is 0."""
        if not ramp:
            return rollout
        return 1 + int((rollout - 1) * min(1.0, step / ramp))


def _cat(*parts: Optional[Tensor]) -> Optional[Tensor]:
    kept = [p for p in parts if p is not None]
    return torch.cat(kept, -1) if kept else None


def recurrent_steps(model: nn.Module, inputs: GarmentInputs, static: StaticFeatures,
                    prev: Tensor, cur: Tensor, joints: Tensor, R: Tensor,
                    code: Optional[Tensor], state: Optional[Tensor] = None,
                    teacher: Optional[TeacherForcing] = None,
                    prev_final: Optional[Tensor] = None) -> Tuple[Tensor, Tensor, Tensor]:
    """The frames of ``inputs`` in order with a latent per vertex (module doc), for
    ``model``, a :class:`~garmentgnn.models.GarTrans`, from its coarse step; ``state``
    ``[V, L]``: the latent after the frame before (``None``: zeros).  Returns the garment
    ``[B, V, 3]``, the stack's ``a`` ``[B, V, 3]`` and the last latent."""
    _no_prev_final(prev_final)
    if teacher is not None:
        raise ValueError("`teacher`: a recurrent latent trains on the chunk's own frames; "
                         "teacher forcing is for `autoregressive`")
    L, (B, V) = model.vertex_state, cur.shape[:2]
    h = cur.new_zeros(V, L) if state is None else _checked(state, (V, L))
    accel = []
    for b in range(B):
        sl = slice(b, b + 1)
        o = model.deform(inputs, prev[sl], cur[sl], joints[:, sl], R[sl],
                         _cat(None if code is None else code[sl], h[None]))[0]
        z, c = torch.sigmoid(o[:, 3:3 + L]), torch.tanh(o[:, 3 + L:])
        h = (1 - z) * h + z * c
        accel.append(o[:, :3])
    a = torch.stack(accel)
    final = model.post_steps(inputs, static, cur + model._gate(2, a * model.unit))
    return final, a, h


def autoregressive_steps(model: nn.Module, inputs: GarmentInputs, static: StaticFeatures,
                         prev: Tensor, cur: Tensor, joints: Tensor, R: Tensor,
                         code: Optional[Tensor], state: Optional[Tensor] = None,
                         teacher: Optional[TeacherForcing] = None,
                         prev_final: Optional[Tensor] = None
                         ) -> Tuple[Tensor, Tensor, Tensor]:
    """The frames of ``inputs`` in order, each from the model's own offsets at the two
    frames before (module doc), for ``model``, a :class:`~garmentgnn.models.GarTrans`,
    from its coarse step; ``state`` ``[2, V, 3]``: the offsets of the two frames
    before the first (``None``: zeros, the coarse mesh); ``teacher``: training rollouts.

    With ``teacher``, rollouts of ``k = teacher.rollout`` frames start at frames ``0, k,
    2k, ...``, each from the (noisy) simulated offsets at ``s-2, s-1`` (``state``'s before
    the chunk's first frame).
    All rollouts take their ``j``-th step together (one pass of the stack over their
    frames), so a step costs ``B / k`` frames.  Returns the garment ``[B, V, 3]``, the
    stack's ``a`` and the offsets of the last two frames."""
    _no_prev_final(prev_final)
    B, V = cur.shape[:2]
    start = cur.new_zeros(2, V, 3) if state is None else _checked(state, (2, V, 3))
    if teacher is None:
        k, known = B, cur.new_zeros(B, V, 3)
    else:
        if teacher.gt.shape != cur.shape:
            raise ValueError(f"`teacher.gt`: expected {tuple(cur.shape)}, got "
                             f"{tuple(teacher.gt.shape)}")
        k, gt = teacher.rollout, teacher.gt
        if teacher.noise:
            gt = gt + teacher.noise * torch.randn_like(gt)
        known = gt - cur
    D = torch.cat([start, known])  # D[f + 2]: the offset at frame f
    final, accel = torch.empty_like(cur), torch.empty_like(cur)  # every frame written below
    for j in range(min(k, B)):
        f = torch.arange(j, B, k, device=cur.device)
        d1, d2 = D[f + 1], D[f]  # the offsets at t-1 and t-2
        feats = [d1 / model.unit, (d1 - d2) * model.fps]
        if model.local_frame:
            feats = [torch.einsum("bvji,bvj->bvi", R[f], x) for x in feats]
        a = model.deform(inputs, prev[f], cur[f], joints[:, f], R[f],
                         _cat(None if code is None else code[f], *feats))
        x = model.post_steps(inputs.select(f), static,
                             cur[f] + d1 + model._gate(2, a * model.unit))
        D = D.index_copy(0, f + 2, x - cur[f])
        final, accel = final.index_copy(0, f, x), accel.index_copy(0, f, a)
    return final, accel, D[-2:]


def _checked(state: Tensor, shape: Tuple[int, ...]) -> Tensor:
    if tuple(state.shape) != shape:
        raise ValueError(f"`state`: expected {shape} (the `state` output of the call on the "
                         f"frames before), got {tuple(state.shape)}")
    return state


def _no_prev_final(prev_final: Optional[Tensor]) -> None:
    if prev_final is not None:
        raise ValueError("`prev_final`: a model with a garment state carries its own; pass "
                         "the `state` output of the call on the frames before")
