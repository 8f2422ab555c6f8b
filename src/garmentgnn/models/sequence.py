"""What :class:`~garmentgnn.models.GarTrans` works with besides its layers: the static
branch's output (:class:`StaticFeatures`), the layout of a batch of chunks
(:class:`ChunkLayout`: per-chunk quantities on the union graph) and the frame-parallel
prediction of a whole motion (:meth:`SequencePrediction.predict_sequence`)."""
from __future__ import annotations

import contextlib
import itertools
import weakref
from dataclasses import dataclass
from typing import Dict, Iterator, List, Optional, Sequence, Tuple

import torch
from torch import Tensor

from garmentgnn.geometry import (edge_lengths, project_edge_lengths, push_outside, unique_edges,
                                 full_precision)
from garmentgnn.models.inputs import FRAME_KEYS, GarmentInputs


@dataclass
class StaticFeatures:
    """The static branch's output for the garments of one input (one chunk or a batch)."""

    x2: Tensor  # [V, S]  x'' = (x̄^[1] ⊙ u^[1]) b^[1]
    log_prior: Optional[Tensor] = None  # [V, S] log of prior skinning weights (or None)
    #: ``strain_limit``'s targets: the unique edges ``[E, 2]`` and their rest lengths ``[E]``
    strain_edges: Optional[Tensor] = None
    strain_lengths: Optional[Tensor] = None


class ChunkLayout:
    """The ``N`` chunks of a :class:`GarmentInputs` (``N = 1`` for one chunk) as seen
    by the model: the per-chunk pose tensors ``[N, B, ...]`` and the operations that
    pair each vertex of the union graph with its own chunk's joints, transforms and body.
    One chunk takes the plain path (no gathering, the same numbers as a lone garment);
    a batch pads each garment to the largest (``[N, Vmax, ...]``) for the per-chunk
    products (its vertex counts read from the host once per batch)."""

    #: the vertex counts and padded positions of recent batches, by their ``batch`` tensor
    _recent: List[Tuple[weakref.ref, Tuple[List[int], int, Tensor]]] = []

    def __init__(self, inputs: GarmentInputs) -> None:
        self.N = inputs.num_chunks
        batched = self.N > 1 or inputs.rotations.dim() == 5
        self.B = inputs.num_frames
        self.V = inputs.num_vertices
        up = (lambda x: x) if batched else (lambda x: x.unsqueeze(0))
        self.rotations = up(inputs.rotations)  # [N, B, H, S, 3]
        self.translation = up(inputs.translation)  # [N, B, H, 3]
        self.rest_joints = up(inputs.rest_joints)  # [N, S, 3]
        parents = inputs.parents
        self.parents = parents[0] if parents.dim() == 2 else parents
        if self.rotations.dim() != 5 or self.rotations.shape[2] < 2:
            raise ValueError(f"`inputs.rotations`: expected pose histories [B, H >= 2, S, 3] "
                             f"(a data `history` >= 1), got {tuple(inputs.rotations.shape)}")
        if self.rotations.shape[-2:] != (self.rest_joints.shape[-2], 3):
            raise ValueError(f"`inputs.rotations`: expected axis-angle rotations of the "
                             f"{self.rest_joints.shape[-2]} joints of `rest_joints`, got "
                             f"{tuple(inputs.rotations.shape)}")
        if self.translation.shape[:3] != self.rotations.shape[:3]:
            raise ValueError(f"`inputs.translation`: expected "
                             f"{tuple(inputs.rotations.shape[:-2]) + (3,)}, got "
                             f"{tuple(inputs.translation.shape)}")
        if self.N == 1:
            self.counts, self.index = [self.V], None
        else:
            self.batch = inputs.vertex_chunk()
            self.counts, self.Vmax, self.index = self._padding(self.batch, self.N)

    @classmethod
    def _padding(cls, batch: Tensor, N: int) -> Tuple[List[int], int, Tensor]:
        """Vertex counts, their largest and each vertex's position in the padded
        ``[N * Vmax]`` layout (one host read per ``batch`` tensor, kept for a few)."""
        for ref, value in cls._recent:
            if ref() is batch:
                return value
        counts_t = torch.bincount(batch, minlength=N)
        ptr = torch.cat([batch.new_zeros(1), counts_t.cumsum(0)])
        counts = counts_t.tolist()
        Vmax = max(counts)
        index = batch * Vmax + torch.arange(batch.shape[0], device=batch.device) - ptr[batch]
        value = (counts, Vmax, index)
        cls._recent = [(weakref.ref(batch), value)] + [r for r in cls._recent
                                                       if r[0]() is not None][:3]
        return value

    # -- padded layout ------------------------------------------------------------------
    def to_padded(self, x: Tensor) -> Tensor:
        """``[V, ...]`` -> ``[N, Vmax, ...]`` (zeros past each garment's vertices)."""
        out = x.new_zeros(self.N * self.Vmax, *x.shape[1:]).index_copy(0, self.index, x)
        return out.view(self.N, self.Vmax, *x.shape[1:])

    def from_padded(self, x: Tensor) -> Tensor:
        """``[N, Vmax, ...]`` -> ``[V, ...]``."""
        return x.reshape(self.N * self.Vmax, *x.shape[2:])[self.index]

    # -- per-chunk operations on the union graph ---------------------------------------------
    def per_vertex(self, code: Tensor) -> Tensor:
        """A per-chunk, per-frame code ``[N, B, S]`` for every vertex: ``[B, V, S]``
        (``[B, 1, S]``, broadcasting, for one chunk)."""
        if self.N == 1:
            return code[0].unsqueeze(1)
        return code.transpose(0, 1)[:, self.batch]

    def per_chunk_matmul(self, x: Tensor, b: Tensor) -> Tensor:
        """``x_v b_{n(v)}``: ``[V, d]`` times each chunk's ``[N, d, S]`` -> ``[V, S]``."""
        if self.N == 1:
            return x @ b[0]
        return self.from_padded(self.to_padded(x) @ b)

    def joint_distances(self, pos: Tensor, joints: Tensor) -> Tensor:
        """Distances ``[F, V, S]`` of vertices ``[F, V, 3]`` to their own chunk's joints
        ``[F, N, S, 3]``."""
        if self.N == 1:
            return torch.cdist(pos, joints[:, 0])
        F = pos.shape[0]
        p = self.to_padded(pos.transpose(0, 1))  # [N, Vmax, F, 3]
        d = torch.cdist(p.permute(2, 0, 1, 3), joints)  # [F, N, Vmax, S]
        return self.from_padded(d.permute(1, 2, 0, 3)).view(self.V, F, -1).transpose(0, 1)

    def blend_transforms(self, W: Tensor, A: Tensor) -> Tensor:
        """Each vertex's blended transform ``sum_j W_vj A_{n(v), j}`` (Eq. 1): weights
        ``[B, V, S]``, transforms ``[N, B, S, 4, 4]`` -> ``[B, V, 4, 4]``."""
        if self.N == 1:
            return torch.einsum("bvs,bsij->bvij", W, A[0])
        Wp = self.to_padded(W.transpose(0, 1))  # [N, Vmax, B, S]
        M = torch.einsum("nvbs,nbsij->nvbij", Wp, A)
        return self.from_padded(M).transpose(0, 1)

    def skin(self, W: Tensor, A: Tensor, template: Tensor) -> Tuple[Tensor, Tensor]:
        """Eq. 1 in float32 (also under autocast): ``template`` ``[B, V, 3]`` (or ``[V,
        3]``) posed by the blended transforms ``M`` ``[B, V, 4, 4]`` of weights ``W`` ``[B,
        V, S]`` and ``A`` ``[N, B, S, 4, 4]``: (positions ``[B, V, 3]``, ``M``)."""
        with full_precision(template) as up:
            M = self.blend_transforms(up(W), up(A))
            pos = (M[..., :3, :3] @ up(template).unsqueeze(-1)).squeeze(-1) + M[..., :3, 3]
        return pos, M

    def push_outside(self, x: Tensor, inputs: GarmentInputs, margin: float,
                     compiled: bool = False) -> Tensor:
        """``x`` ``[B, V, 3]`` with each chunk's vertices closer than ``margin`` to its own
        body (or inside it) moved to ``margin`` outside
        (:func:`~garmentgnn.geometry.push_outside`, all chunks in one call: the union
        body's normals, the face search and the projection once for the batch)."""
        faces = inputs.get("body_faces")
        if faces is None:
            raise ValueError("`inputs.body_faces`: needed with `body_pos` for the collision "
                             "projection")
        Vb = inputs.body_pos.shape[1] // self.N
        pairs = {} if self.N == 1 else {  # chunk n's vertices against body n
            "point_ptr": list(itertools.accumulate(self.counts, initial=0)),
            "body_ptr": list(range(0, (self.N + 1) * Vb, Vb))}
        return push_outside(x, inputs.body_pos, faces, margin, compiled=compiled, **pairs)


#: the spectral radius estimate of the inextensible projection's Chebyshev acceleration
#: (:func:`~garmentgnn.geometry.project_edge_lengths`), chosen on 24 `learn` val
#: rollouts (docs/results/mgn_learn/inextensible)
STRAIN_CHEBYSHEV = 0.99


class PostSteps:
    """GarTrans's last steps after the dynamic stack (not in the paper): the strain limit
    (``strain_limit`` sweeps) and the collision projection (``collision_projection``).
    ``inextensible`` (sweeps; 0: none): in eval mode, the strain limit is replaced by as
    many sweeps that pull every edge toward its rest length, compressed ones too, with
    Chebyshev's acceleration (:data:`STRAIN_CHEBYSHEV`); in training mode, and without
    it, only stretched edges are shortened (Provot's strain limit).  Within
    :meth:`inextensible_projection`, its sweeps in either mode."""

    inextensible = 0
    _inextensible_now = 0

    def strain_sweeps(self) -> Tuple[int, bool]:
        """``(sweeps, inextensible)`` of the edge-length projection in the module's
        current mode (within :meth:`inextensible_projection`, its sweeps; else
        ``inextensible`` in eval mode where it is set; else ``strain_limit``'s
        stretched edges)."""
        if self._inextensible_now:
            return self._inextensible_now, True
        if self.inextensible and not self.training:
            return self.inextensible, True
        return self.strain_limit, False

    @contextlib.contextmanager
    def inextensible_projection(self, sweeps: int) -> Iterator[None]:
        """Within: ``sweeps`` of the inextensible projection (every edge toward rest, as
        eval mode's ``inextensible``) in either mode, e.g. a training rollout projected
        as validation and ``predict`` project theirs; ``sweeps=0``: no change."""
        if not isinstance(sweeps, int) or isinstance(sweeps, bool) or sweeps < 0:
            raise ValueError(f"`sweeps`: expected an int >= 0, got {sweeps!r}")
        old = self._inextensible_now
        self._inextensible_now = sweeps or old
        try:
            yield
        finally:
            self._inextensible_now = old

    def post_steps(self, inputs: GarmentInputs, static: StaticFeatures, x: Tensor,
                   layout: Optional[ChunkLayout] = None) -> Tensor:
        """The strain limit, then the collision projection against each chunk's body (in
        float32, also under autocast); ``layout``: ``inputs``' :class:`ChunkLayout` where
        the caller has it (else built here)."""
        with full_precision(x) as up:
            return self._post_steps(inputs, static, up(x), layout)

    def _post_steps(self, inputs: GarmentInputs, static: StaticFeatures, x: Tensor,
                    layout: Optional[ChunkLayout] = None) -> Tensor:
        sweeps, both = self.strain_sweeps()
        if sweeps:
            edges, lengths = static.strain_edges, static.strain_lengths
            if edges is None:  # static features made by a model without the strain limit
                edges = unique_edges(inputs.faces, inputs.num_vertices).edges
                lengths = edge_lengths(inputs.rest_pos, edges)
            x = project_edge_lengths(x, edges, lengths, sweeps, stretch_only=not both,
                                     chebyshev=STRAIN_CHEBYSHEV if both else None)
        body = inputs.get("body_pos")
        if self.collision_projection is None or body is None:
            return x
        return (layout or ChunkLayout(inputs)).push_outside(
            x, inputs, self.collision_projection, compiled=self.compile_search)


class SequencePrediction:
    """:meth:`predict_sequence` and :meth:`rollout` for a model with GarTrans's
    ``forward(inputs, static, prev_final)`` and ``encode_static(inputs)``."""

    #: default chunk size of :meth:`predict_sequence`: frames per chunk such that a
    #: chunk holds about this many garment vertices (bounds memory, see docs/inference.md)
    CHUNK_VERTICES = 32768
    #: what :meth:`predict_sequence` can return
    SEQUENCE_OUTPUTS = ("final", "coarse", "accel", "weights")

    def predict_sequence(self, inputs: GarmentInputs, batch_size: Optional[int] = None,
                         outputs: Sequence[str] = ("final",),
                         static: Optional[StaticFeatures] = None) -> Dict[str, Tensor]:
        """Predict every frame of ``inputs`` (one garment over a whole motion, e.g.
        :func:`~garmentgnn.models.inputs.with_frames` of all its frames), frame-parallel,
        ``batch_size`` frames at a time under ``torch.inference_mode``; the static branch
        once (``static``: a cached one), the batched graph and its CSR plans once.
        Equals :meth:`forward` on each frame alone up to float round-off.

        Args:
            batch_size: frames per call; ``None``: about :attr:`CHUNK_VERTICES` vertices.
            outputs: which of :attr:`SEQUENCE_OUTPUTS` to return (``weights`` is
                ``[T, V, S]``: large).

        Returns:
            ``{name: [T, V, 3]}`` (``weights``: ``[T, V, S]``) for each name in ``outputs``.
        """
        if not isinstance(inputs, GarmentInputs) or inputs.num_chunks != 1 \
                or inputs.num_frames < 1:
            raise ValueError(f"`inputs`: expected the GarmentInputs of one garment over "
                             f"T >= 1 frames, got {type(inputs).__name__}")
        if batch_size is not None and (not isinstance(batch_size, int)
                                       or isinstance(batch_size, bool) or batch_size < 1):
            raise ValueError(f"`batch_size`: expected a positive int or None, got {batch_size!r}")
        bad = [o for o in outputs if o not in self.SEQUENCE_OUTPUTS]
        if isinstance(outputs, str) or bad or not outputs:
            raise ValueError(f"`outputs`: expected a non-empty sequence of "
                             f"{self.SEQUENCE_OUTPUTS}, got {outputs!r}")
        T, V = inputs.num_frames, inputs.num_vertices
        for k in FRAME_KEYS:
            if k in inputs and inputs[k].shape[0] != T:
                raise ValueError(f"`inputs.{k}`: expected one row per frame ({T}), got "
                                 f"{tuple(inputs[k].shape)}")
        b = min(batch_size or max(1, self.CHUNK_VERTICES // max(V, 1)), T)
        with torch.inference_mode():
            static = self.encode_static(inputs) if static is None else static
            out = {k: inputs.rest_pos.new_empty(T, V, self.num_joints if k == "weights"
                                                else 3) for k in outputs}
            for t0 in range(0, T, b):
                o = self.forward(inputs.select(torch.arange(t0, min(t0 + b, T))), static)
                for k in outputs:
                    out[k][t0:t0 + b] = o[k]
        return out

    def rollout(self, inputs: GarmentInputs, static: Optional[StaticFeatures] = None,
                first: Optional[Tensor] = None) -> Dict[str, Tensor]:
        """Autoregressive inference over the frames of one chunk, in order: each frame's
        velocity from the model's own previous prediction (``first`` ``[V, 3]``: the
        garment before frame 0; default the coarse mesh).  Outputs as :meth:`forward`."""
        if inputs.num_chunks != 1:
            raise ValueError("`inputs`: a rollout runs over one chunk, got a batch of "
                             f"{inputs.num_chunks}")
        static = self.encode_static(inputs) if static is None else static
        outs, prev = [], None if first is None else first.unsqueeze(0)
        for t in range(inputs.num_frames):
            o = self.forward(inputs.select(torch.tensor([t])), static, prev_final=prev)
            prev = o["final"]
            outs.append(o)
        return {k: torch.cat([o[k] for o in outs]) for k in outs[0]}
