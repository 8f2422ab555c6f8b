"""GarTrans's static-branch output (:class:`StaticFeatures`) and its batched whole-sequence
inference (:meth:`SequencePrediction.predict_sequence`), the paper's frame-parallel
prediction of every frame of a motion, as a mixin of :class:`~garmentgnn.models.GarTrans`."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional, Sequence

import torch
from torch import Tensor

from garmentgnn.geometry import edge_features
from garmentgnn.models.inputs import check_history, history_frames


@dataclass
class StaticFeatures:
    """The static branch's output for one garment on one body shape."""

    x2: Tensor  # [V, S]  x'' = (x̄^[1] ⊙ u^[1]) b^[1]
    log_prior: Optional[Tensor] = None  # [V, S] log of prior skinning weights (or None)
    #: ``strain_limit``'s targets: the unique edges ``[E, 2]`` and their rest lengths ``[E]``
    strain_edges: Optional[Tensor] = None
    strain_lengths: Optional[Tensor] = None


class SequencePrediction:
    """:meth:`predict_sequence` for a model with GarTrans's ``forward`` and ``num_joints``."""

    #: default chunk size of :meth:`predict_sequence`: frames per chunk such that a
    #: chunk holds about this many garment vertices (bounds memory, see docs/inference.md)
    CHUNK_VERTICES = 32768
    #: what :meth:`predict_sequence` can return
    SEQUENCE_OUTPUTS = ("final", "coarse", "accel", "weights")

    def predict_sequence(self, static: StaticFeatures, rest_pos: Tensor, faces: Tensor,
                         edge_index: Tensor, rest_joints: Tensor, parents: Tensor,
                         rotations: Tensor, translation: Tensor, history: int = 3,
                         batch_size: Optional[int] = None, body_pos: Optional[Tensor] = None,
                         body_faces: Optional[Tensor] = None,
                         outputs: Sequence[str] = ("final",)) -> Dict[str, Tensor]:
        """Predict every frame of a motion, frame-parallel (the paper's batch inference).

        The pose history of frame ``t`` is frames ``t-history .. t`` clamped at 0 (as
        the training data module builds it); frames are predicted ``batch_size`` at a
        time by :meth:`forward` (static branch ``static`` computed once by the caller,
        dynamic branch batched) under ``torch.inference_mode``.  The batched graph, its
        CSR plans and the rest graph's edge features are built once and reused by every
        chunk.  Equals :meth:`forward` on each frame's history alone up to float
        round-off, whatever ``batch_size``.

        Args:
            static, rest_pos, faces, edge_index, rest_joints, parents: as :meth:`forward`.
            rotations: ``[T, S, 3]`` the motion's joint rotations (axis-angle).
            translation: ``[T, 3]`` its root translations.
            history: previous frames per pose history (``H = history + 1 >= 2``).
            batch_size: frames per chunk; ``None``: about :attr:`CHUNK_VERTICES`
                vertices per chunk (at least one frame).
            body_pos: ``[T, Vb, 3]`` posed body (for ``collision_projection``), with
                ``body_faces``.
            outputs: which of :attr:`SEQUENCE_OUTPUTS` to return (``weights`` is
                ``[T, V, S]``: large).

        Returns:
            ``{name: [T, V, 3]}`` (``weights``: ``[T, V, S]``) for each name in ``outputs``.
        """
        S = self.num_joints
        if not isinstance(rotations, Tensor) or rotations.dim() != 3 \
                or rotations.shape[1:] != (S, 3) or rotations.shape[0] < 1:
            got = tuple(rotations.shape) if isinstance(rotations, Tensor) else type(rotations)
            raise ValueError(f"`rotations`: expected [T>=1, {S}, 3] axis-angle rotations of "
                             f"the whole motion, got {got}")
        T = rotations.shape[0]
        if not isinstance(translation, Tensor) or tuple(translation.shape) != (T, 3):
            got = tuple(translation.shape) if isinstance(translation, Tensor) else type(translation)
            raise ValueError(f"`translation`: expected [{T}, 3], got {got}")
        check_history(history)
        if batch_size is not None and (not isinstance(batch_size, int)
                                       or isinstance(batch_size, bool) or batch_size < 1):
            raise ValueError(f"`batch_size`: expected a positive int or None, got {batch_size!r}")
        bad = [o for o in outputs if o not in self.SEQUENCE_OUTPUTS]
        if isinstance(outputs, str) or bad or not outputs:
            raise ValueError(f"`outputs`: expected a non-empty sequence of "
                             f"{self.SEQUENCE_OUTPUTS}, got {outputs!r}")
        if body_pos is not None and (body_pos.dim() != 3 or body_pos.shape[0] != T):
            raise ValueError(f"`body_pos`: expected [{T}, Vb, 3], got {tuple(body_pos.shape)}")
        V = rest_pos.shape[0]
        b = batch_size or max(1, self.CHUNK_VERTICES // max(V, 1))
        b = min(b, T)
        with torch.inference_mode():
            rest_e = edge_features(rest_pos, edge_index)
            out = {k: rest_pos.new_empty(T, V, S if k == "weights" else 3) for k in outputs}
            for t0 in range(0, T, b):  # chunks of frames, each predicted in one batch
                frames = torch.arange(t0, min(t0 + b, T), device=rotations.device)
                hist = history_frames(frames, history)  # [n, H]
                o = self.forward(static, rest_pos, faces, edge_index, rest_joints, parents,
                                 rotations[hist], translation[hist],
                                 body_pos=None if body_pos is None else body_pos[frames],
                                 body_faces=body_faces, rest_edge_attr=rest_e)
                for k in outputs:
                    out[k][t0:t0 + len(frames)] = o[k]
        return out
