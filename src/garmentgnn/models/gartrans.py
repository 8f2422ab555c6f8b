"""GarTrans (paper §3.1, §4.1): dynamic-aware graph construction + SAT deformation.

Pipeline for a garment ``T`` (``V`` vertices) on a body with ``S`` joints:

1. Static branch (depends only on garment and body shape; computed once by
   :meth:`GarTrans.encode_static` and reused for every frame):
   rest features ``x̄ = [p, n, d(p, J)]`` -> FC [128,128,128] tanh -> transformer
   layers [64,64,128] (4 heads, tanh) = ``x̄^[1]``; Nyström geodesic eigenvectors
   -> FC = ``u^[1]``; ``x' = x̄^[1] ⊙ u^[1]``; body-vertex-to-joint distances, one
   column per joint -> FC [512,256,128] = ``b^[1] in R^{128 x S}``;
   ``x'' = x' b^[1]`` (``V x S``, per-vertex x per-joint).
2. Dynamic branch: a 2-layer GRU (128) over the pose history -> ``Θ^[1] in R^S``;
   ``x''' = x'' ⊙ Θ^[1]``; skinning weights ``W^t = softmax(x''')`` and a blend
   shape ``B^t`` from transformer layers [32,32,32,3] (4 heads, ELU); coarse mesh
   ``M^{t,c} = LBS(T + B^t, J, W^t)`` (Eqs. 1-2).
3. Deformation: graph on ``M^{t,c}`` with vertex features (velocity
   ``(M^{t,c} - M^{t-1,c}) / dt``, normal, joint distances) and edge features
   (length, direction) -> 6 layers [32,64,64,64,32,3], 4 heads, ELU, heads averaged
   at the output = acceleration ``a``; ``M^{t,d} = M^{t,c} + a dt^2``.

Choices where the paper is vague (docs/model.md): per-vertex Nyström features
(``V x k`` through FC layers); ``Θ^[1]`` = the GRU's last hidden state -> linear -> ``S``;
``a dt^2`` added to the coarse mesh (frame-parallel); any registry layer in any slot.

Left out where a scene does not need it: the body branch (``body_joint_dists=None``: a
learned per-joint code for ``b^[1]``) and the GRU (a still pose history: ``Θ^[1] = 1``).
"""
from __future__ import annotations

from typing import Dict, Optional, Tuple

import torch
from torch import Tensor, nn

from garmentgnn.body.lbs import blend_transforms, forward_kinematics, linear_blend_skinning
from garmentgnn.geometry import (edge_features, edge_lengths, project_edge_lengths,
                                push_outside, unique_edges, vertex_normals)
from garmentgnn.models.blocks import (AttentionStack, RunningNormalizer, cached_batch_edges,
                                      geometric_init_, mlp)
from garmentgnn.models.sequence import SequencePrediction, StaticFeatures


#: metres per unit of the blend-shape stack's output (it predicts centimetres)
BLEND_UNIT = 0.01
#: ``garment_state``: the offset from the coarse mesh carried from frame to frame is
#: ``STATE_BOUND tanh(d / STATE_BOUND)`` (metres; nearly ``d`` for offsets of a few
#: centimetres), and the state features are ``tanh(d_1 / STATE_BOUND)`` and
#: ``tanh((d_1 - d_2) / STATE_STEP)``: bounded inputs and a bounded carry, so an
#: autoregressive rollout cannot feed its own error back without limit
STATE_BOUND, STATE_STEP = 0.2, 0.02

#: the :class:`GarTrans` arguments of the paper's own form (§3.1, §4.1): no gates, the
#: blend shape, an acceleration output, no strain limit, no collision projection, no
#: garment state, no input normalisers, a world-frame dynamic stack that sees one
#: velocity; where the defaults (those of ``garmentgnn/configs/gartrans.yaml`` and
#: :class:`GarTransModule`) differ, docs/model.md says why
PAPER_FORM: Dict[str, object] = {"lbs_start": False, "gate_init": 0.0,
                                 "collision_projection": None, "blend_shape": True,
                                 "strain_limit": 0, "accel_unit": None,
                                 "garment_state": False, "input_norm": False,
                                 "local_frame": False, "motion_history": 1}


class GarTrans(SequencePrediction, nn.Module):
    """The full model.  Layer slots take registry names (``sat``, ``gt``, ``gt_edge``,
    ``structure_aware``, ``gat``), so the paper's ablations are one argument.  The
    defaults are the project's (the same in :class:`GarTransModule` and
    ``garmentgnn/configs/gartrans.yaml``); ``GarTrans(..., **PAPER_FORM)`` is the paper's
    form (:data:`PAPER_FORM`).

    Args:
        num_joints: ``S``.
        num_body_vertices: body vertex count (input width of the body FC branch).
        nystrom_dim: number of Nyström eigenvector features per vertex.
        rest_layer, blend_layer, dynamic_layer: registry names of the three slots.
        heads: attention heads (4 in the paper).
        fps: frame rate (for velocities and ``dt^2``).
        lbs_start: ReZero-style gates (Bachlechner et al., 2021), three learnable
            scalars (started at ``gate_init``) that scale what each learned branch adds
            to plain skinning: ``W^t = softmax(log W_prior + g_W x3)``,
            ``T^t = T + g_B B^t``, ``M^{t,d} = M^{t,c} + g_a a u`` (``u``: ``accel_unit``).
            With a skinning prior and gates at 0 the untrained model is exactly LBS with
            the prior weights (docs/model.md).  The layers keep the §4.1 initialisation.
            ``False``: the paper's form.
        collision_projection: margin ``eps`` (metres) of a last, differentiable step that
            moves the vertices of ``M^{t,d}`` closer than ``eps`` to the body (or inside
            it) to ``eps`` outside (:func:`garmentgnn.geometry.push_outside`); applied
            when :meth:`forward` gets the posed body.  ``None`` (the paper): no
            projection; the collision loss (Eq. 10) alone keeps the garment out.
            Default 2 mm.
        blend_shape: ``False`` (the default) leaves out the blend shape ``B^t``
            (``T^t = T``) and its transformer stack; ``True`` is the paper.
        strain_limit: sweeps of a differentiable step, before the collision projection,
            that shortens the edges of ``M^{t,d}`` longer than on the rest garment
            (:func:`garmentgnn.geometry.project_edge_lengths` with ``stretch_only``:
            Provot's strain limiting); ``0`` (the paper): none.  Default 10.
        compile_search: ``torch.compile`` the projection's nearest-face search (``compiled``
            of :func:`garmentgnn.geometry.signed_distance`: same result, faster on CPU).
        gate_init: the value the ``lbs_start`` gates start from.  ``0`` makes the
            untrained model exactly LBS but gives every branch behind a gate an exactly
            zero gradient until the gates have moved; at ``1`` every branch learns from
            the first step, and the untrained model is still within a few percent of
            LBS (its learned logits and outputs start small; docs/model.md,
            ``benchmarks/learning.py``).
        accel_unit: metres of displacement per unit of the dynamic stack's output
            (``0.01``: centimetres); ``None`` (the paper): an acceleration, ``a dt^2``
            (at 30 fps, 1.1 mm per unit).
        garment_state: not in the paper: the dynamic graph also sees where the garment
            *is* -- its offsets from the coarse mesh at frames ``t-1`` and ``t-2``,
            ``d_1 = x_{t-1} - M^{t-1,c}`` and ``d_1 - d_2`` (bounded, see
            :data:`STATE_BOUND`), given as ``forward(state=...)`` -- and the output keeps
            the previous offset, ``M^{t,d} = M^{t,c} + b tanh(d_1 / b) + g_a a``.  Without
            a state (``state=None``) the offsets are zero and the model is the paper's
            frame-parallel one.
            :meth:`rollout` feeds its own predictions back as the state; training feeds
            the simulated frames (``GarTransModule``).  Needs a pose history ``H >= 3``.
        input_norm: not in the paper: MeshGraphNets-style normalisers
            (:class:`~garmentgnn.models.blocks.RunningNormalizer`) make the rest and
            dynamic stacks' vertex and edge features ``(x - mean) / std`` per feature,
            from running statistics of training (saved in the checkpoint).  Default on.
        local_frame: not in the paper: the dynamic stack works in each vertex's skinned
            local frame, the rotation part ``R_v`` of its blended skinning transform
            ``M_v(t) = sum_j W_vj A_j(t)`` (Eq. 1).  Its vector inputs (velocity, normal)
            enter as ``R_v^T x``, with the gravity direction ``R_v^T (0, 0, -1)`` and the
            rest position ``T_v`` (which vertex it is) as six more features, and its output
            is rotated back, ``M^{t,d} = M^{t,c} + g_a R_v a u``: a drape that stays put on
            the limb is one output whatever the pose (the frame in which the "static
            oracle" of ``benchmarks/error_split.py`` is a constant).  The edge features
            stay in the world frame.  Default on
            (with ``input_norm`` it fits the training data better: docs/model.md).
        motion_history: not in the paper beyond ``1``: how many of the coarse mesh's
            per-vertex velocities the dynamic stack sees, ``(M^{s,c} - M^{s-1,c}) / dt``
            for ``s = t, t-1, ..., t - motion_history + 1`` (with ``local_frame``, turned
            by frame t's ``R_v^T``), so that it sees how the garment's skinned frame has
            been moving, not only its last step; needs a pose history
            ``H >= motion_history + 1``.  ``1``: the paper's single velocity.
    """

    def __init__(self, num_joints: int, num_body_vertices: int, nystrom_dim: int = 16,
                 rest_layer: str = "gt", blend_layer: str = "gt", dynamic_layer: str = "sat",
                 heads: int = 4, fps: float = 30.0, edge_dim: int = 4,
                 lbs_start: bool = True, collision_projection: Optional[float] = 0.002,
                 blend_shape: bool = False, strain_limit: int = 10,
                 compile_search: bool = False, gate_init: float = 1.0,
                 accel_unit: Optional[float] = 0.01, garment_state: bool = False,
                 input_norm: bool = True, local_frame: bool = True,
                 motion_history: int = 1) -> None:
        super().__init__()
        self.local_frame = bool(local_frame)
        if not isinstance(motion_history, int) or isinstance(motion_history, bool) \
                or motion_history < 1:
            raise ValueError(f"`motion_history`: expected a number of velocities >= 1, got "
                             f"{motion_history!r}")
        self.motion_history = motion_history
        self.garment_state = bool(garment_state)
        if not gate_init >= 0:
            raise ValueError(f"`gate_init`: expected a value >= 0, got {gate_init}")
        if accel_unit is not None and not accel_unit > 0:
            raise ValueError(f"`accel_unit`: expected metres per output unit > 0 or None, "
                             f"got {accel_unit}")
        self.gate_init = float(gate_init)
        #: metres of displacement per unit of the dynamic stack's output (``None``: the
        #: paper's acceleration, ``dt^2``)
        self.accel_unit = accel_unit
        if not isinstance(strain_limit, int) or isinstance(strain_limit, bool) or strain_limit < 0:
            raise ValueError(f"`strain_limit`: expected a number of sweeps >= 0, got "
                             f"{strain_limit!r}")
        self.strain_limit, self.compile_search = strain_limit, bool(compile_search)
        if collision_projection is not None and not collision_projection >= 0:
            raise ValueError(f"`collision_projection`: expected a margin >= 0 in metres or "
                             f"None, got {collision_projection}")
        self.collision_projection = collision_projection
        S = num_joints
        self.num_joints, self.fps, self.edge_dim = S, fps, edge_dim
        self.rest_fc = mlp([6 + S, 128, 128, 128], nn.Tanh())
        self.rest_attn = AttentionStack(rest_layer, 128, [64, 64, 128], heads, edge_dim, "tanh",
                                        last_act=True)
        # the paper's 128 is the last rest layer's width; make concat widths line up
        d = self.rest_attn.out_channels
        self.nystrom_fc = mlp([nystrom_dim, 64, d], nn.Tanh())
        self.body_fc = mlp([num_body_vertices, 512, 256, d], nn.Tanh())
        self.body_default = nn.Parameter(torch.randn(d, S) / d ** 0.5)
        self.gru = nn.GRU(3 * S + 3, 128, num_layers=2, batch_first=True)
        self.gru_out = nn.Linear(128, S)
        self.blend = AttentionStack(blend_layer, S, [32, 32, 32, 3], heads, edge_dim, "elu",
                                    last_act=False) if blend_shape else None
        state_dim = 6 if self.garment_state else 0
        local_dim = 6 if self.local_frame else 0  # rest position and local gravity
        local_dim += 3 * (motion_history - 1)  # the earlier velocities
        self.dynamic = AttentionStack(dynamic_layer, 3 + 3 + S + state_dim + local_dim,
                                      [32, 64, 64, 64, 32, 3], heads,
                                      edge_dim, "elu", last_act=False)
        #: (g_W, g_B, g_a) of ``lbs_start``; ``None``: no gates (the paper)
        self.gates = nn.Parameter(torch.zeros(3)) if lbs_start else None
        # ``input_norm``: the rest and dynamic vertex and edge features' normalisers
        self.input_norm = bool(input_norm)
        norm = RunningNormalizer if self.input_norm else (lambda size: nn.Identity())
        self.rest_norm, self.rest_edge_norm = norm(6 + S), norm(edge_dim)
        self.dynamic_norm = norm(3 + 3 + S + state_dim + local_dim)
        self.dynamic_edge_norm = norm(edge_dim)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """§4.1: geometric init for the FC layers, Kaiming for the GRU and transformers."""
        for m in (self.rest_fc, self.nystrom_fc, self.body_fc, self.gru_out):
            geometric_init_(m)
        for name, p in self.gru.named_parameters():
            if "weight" in name:
                nn.init.kaiming_uniform_(p, a=5 ** 0.5)
            else:
                nn.init.zeros_(p)
        for stack in (self.rest_attn, self.blend, self.dynamic):
            if stack is not None:
                stack.reset_parameters()
        if self.gates is not None:
            nn.init.constant_(self.gates, self.gate_init)

    def _gate(self, i: int, x: Tensor) -> Tensor:
        return x if self.gates is None else self.gates[i] * x

    # -- static branch --------------------------------------------------------
    def encode_static(self, rest_pos: Tensor, faces: Tensor, edge_index: Tensor,
                      rest_joints: Tensor, nystrom: Tensor,
                      body_joint_dists: Optional[Tensor] = None,
                      skin_prior: Optional[Tensor] = None) -> StaticFeatures:
        """Once per garment and body shape.

        Args:
            rest_pos: ``[V, 3]`` garment on the rest body; ``faces [F, 3]``;
            edge_index: ``[2, E]`` garment graph (sorted by target for speed).
            rest_joints: ``[S, 3]``; nystrom: ``[V, k]`` eigenvector features;
            body_joint_dists: ``[Vb, S]`` body-vertex-to-joint distances, or ``None``
                for a scene without a body.
            skin_prior: ``[V, S]`` skinning weights (rows summing to 1) that the learned
                ``W^t`` starts from, ``W^t = softmax(x3 + log(prior))`` with ``x3`` the
                motion-modulated features -- e.g. the body's weights transferred to the
                garment.  ``None`` (the paper) learns ``W^t`` from scratch, which on
                small datasets leaves the coarse mesh far from even plain LBS
                (docs/model.md).
        """
        n = vertex_normals(rest_pos, faces)
        dj = torch.cdist(rest_pos, rest_joints)
        x = self.rest_fc(self.rest_norm(torch.cat([rest_pos, n, dj], -1)))
        e = self.rest_edge_norm(edge_features(rest_pos, edge_index))
        x = self.rest_attn(x, edge_index, e)
        x1 = x * self.nystrom_fc(nystrom)  # x' = x̄^[1] ⊙ u^[1]
        b = (self.body_default if body_joint_dists is None
             else self.body_fc(body_joint_dists.t()).t())
        log_prior = None
        if skin_prior is not None:
            if skin_prior.shape != (rest_pos.shape[0], self.num_joints):
                raise ValueError(f"`skin_prior`: expected [{rest_pos.shape[0]}, "
                                 f"{self.num_joints}], got {tuple(skin_prior.shape)}")
            log_prior = skin_prior.to(x1.dtype).clamp_min(1e-4).log()
        static = StaticFeatures(x2=x1 @ b, log_prior=log_prior)  # x'' = x' ⊗ b^[1]: [V, S]
        if self.strain_limit:
            static.strain_edges, static.strain_lengths = self._strain_targets(rest_pos, faces)
        return static

    @staticmethod
    def _strain_targets(rest_pos: Tensor, faces: Tensor) -> Tuple[Tensor, Tensor]:
        """The strain limit's unique edges ``[E, 2]`` and their rest lengths ``[E]``."""
        edges = unique_edges(faces, rest_pos.shape[0]).edges
        return edges, edge_lengths(rest_pos, edges)

    # -- dynamic branch -------------------------------------------------------
    def motion_code(self, rotations: Tensor, translation: Tensor) -> Tensor:
        """``Θ^[1]`` ``[B, S]`` from a pose history ``[B, H, S, 3]``, ``[B, H, 3]``;
        ones (no modulation) for a history whose frames are all the same pose (each
        history on its own, so a frame's code does not depend on the other frames of
        its batch); the GRU is skipped when every history is such."""
        B = rotations.shape[0]
        still = ((rotations == rotations[:, :1]).reshape(B, -1).all(1)
                 & (translation == translation[:, :1]).reshape(B, -1).all(1))
        ones = rotations.new_ones(B, self.num_joints)
        if bool(still.all()):
            return ones
        vel = torch.diff(translation, dim=1, prepend=translation[:, :1]) * self.fps
        seq = torch.cat([rotations.flatten(2), vel], -1)
        h, _ = self.gru(seq)
        code = self.gru_out(h[:, -1])
        return torch.where(still.unsqueeze(1), ones, code) if bool(still.any()) else code

    def coarse(self, static: StaticFeatures, rest_pos: Tensor, edge_index: Tensor,
               rest_joints: Tensor, parents: Tensor, rotations: Tensor, translation: Tensor,
               rest_edge_attr: Optional[Tensor] = None, frames: int = 2,
               with_rotation: bool = False):
        """Coarse meshes ``M^{t,c}`` for the last ``frames`` frames of each history:
        ``[B, frames, V, 3]`` (oldest first, current last), plus the skinning weights
        ``[B, V, S]`` and the posed joints ``[B, S, 3]`` of frame t.  ``rest_edge_attr``:
        the rest graph's :func:`edge_features` ``[E, 4]`` when the caller has them
        (computed here otherwise).  ``with_rotation``: also the rotation part ``[B, V, 3,
        3]`` of each vertex's blended skinning transform at frame t (``local_frame``)."""
        B, H = rotations.shape[:2]
        V = rest_pos.shape[0]
        x3 = static.x2.unsqueeze(0) * self.motion_code(rotations, translation).unsqueeze(1)
        logits = x3 if static.log_prior is None else self._gate(0, x3) + static.log_prior
        W = torch.softmax(logits, -1)  # W^t
        template = rest_pos.unsqueeze(0).expand(B, V, 3)
        if self.blend is not None:
            e = edge_features(rest_pos, edge_index) if rest_edge_attr is None else rest_edge_attr
            e = self.rest_edge_norm(e)
            blend = self.blend(x3.reshape(B * V, -1), cached_batch_edges(edge_index, B, V),
                               e.repeat(B, 1))
            # T^t = T + B^t (Eq. 2); the stack outputs B^t in centimetres (BLEND_UNIT), so
            # a freshly initialised model starts near its skinned rest garment, not ~30 cm off
            template = template + self._gate(1, BLEND_UNIT * blend.view(B, V, 3))
        k = frames
        rot2 = rotations[:, -k:].reshape(B * k, *rotations.shape[2:])
        tr2 = translation[:, -k:].reshape(B * k, 3)
        A, joints = forward_kinematics(rot2, rest_joints, parents, tr2)
        # Eq. 1 with the frame's own template and weights, for the last k frames
        verts = linear_blend_skinning(template.repeat_interleave(k, 0),
                                      W.repeat_interleave(k, 0), A)
        out = (verts.view(B, k, V, 3), W, joints.view(B, k, -1, 3)[:, -1])
        if with_rotation:
            A_t = A.view(B, k, *A.shape[1:])[:, -1, :, :3, :3]  # [B, S, 3, 3] of frame t
            out = out + (blend_transforms(W, A_t),)
        return out

    def forward(self, static: StaticFeatures, rest_pos: Tensor, faces: Tensor,
                edge_index: Tensor, rest_joints: Tensor, parents: Tensor, rotations: Tensor,
                translation: Tensor, prev_final: Optional[Tensor] = None,
                body_pos: Optional[Tensor] = None, body_faces: Optional[Tensor] = None,
                rest_edge_attr: Optional[Tensor] = None, state: Optional[Tensor] = None):
        """Predict ``M^{t,d}`` for a batch of frames (frame-parallel).

        Args:
            rotations: ``[B, H, S, 3]`` pose histories (last = frame t, H >= 2).
            translation: ``[B, H, 3]`` root translations.
            prev_final: ``[B, V, 3]`` the garment at frame ``t-1`` (autoregressive use,
                see :meth:`rollout`); default: the coarse mesh ``M^{t-1,c}`` (§3.1, the
                frame-parallel mode the paper trains and batches).
            body_pos: ``[B, Vb, 3]`` the posed body of each frame, with ``body_faces``
                ``[Fb, 3]``: used by ``collision_projection`` only (ignored without it;
                a scene without a body passes ``None``).
            rest_edge_attr: ``edge_features(rest_pos, edge_index)`` ``[E, 4]``, when the
                caller keeps them across calls (:meth:`predict_sequence`); computed
                here otherwise.
            state: ``garment_state`` only: ``[B, 2, V, 3]`` the garment at frames
                ``t-2`` and ``t-1``; ``None``: the coarse meshes of those frames (zero
                offsets: the frame-parallel model).

        Returns:
            dict with ``final [B, V, 3]``, ``coarse [B, V, 3]``, ``accel [B, V, 3]``,
            ``weights [B, V, S]``.
        """
        if rotations.dim() != 4 or rotations.shape[1] < 2:
            raise ValueError(f"`rotations`: expected [B, H>=2, S, 3], got {tuple(rotations.shape)}")
        B = rotations.shape[0]
        V = rest_pos.shape[0]
        if state is not None and not self.garment_state:
            raise ValueError("`state`: this model has no garment state (build it with "
                             "`garment_state=True`)")
        if self.garment_state and rotations.shape[1] < 3:
            raise ValueError(f"`rotations`: a model with `garment_state` needs a pose history "
                             f"of H >= 3 frames, got {tuple(rotations.shape)}")
        if rotations.shape[1] < self.motion_history + 1:
            raise ValueError(f"`rotations`: `motion_history={self.motion_history}` needs a pose "
                             f"history of H >= {self.motion_history + 1} frames, got "
                             f"{tuple(rotations.shape)} (a longer data `history`)")
        k = max(3 if self.garment_state else 2, self.motion_history + 1)
        coarse_k, W, joints, *rot = self.coarse(static, rest_pos, edge_index, rest_joints,
                                                parents, rotations, translation,
                                                rest_edge_attr, frames=k,
                                                with_rotation=self.local_frame)
        prev, cur = coarse_k[:, -2], coarse_k[:, -1]
        offset = None
        if self.garment_state:
            if state is None:
                d = cur.new_zeros(B, 2, V, 3)
            else:
                if state.shape != (B, 2, V, 3):
                    raise ValueError(f"`state`: expected [{B}, 2, {V}, 3] (the garment at "
                                     f"frames t-2, t-1), got {tuple(state.shape)}")
                d = state - coarse_k[:, -3:-1]  # offsets from the coarse mesh, t-2 and t-1
            # bounded: a rollout whose state drifts far stays bounded (no feedback loop)
            offset = STATE_BOUND * torch.tanh(d[:, 1] / STATE_BOUND)
            extra = torch.cat([torch.tanh(d[:, 1] / STATE_BOUND),
                               torch.tanh((d[:, 1] - d[:, 0]) / STATE_STEP)], -1)
        if prev_final is not None:
            if prev_final.shape != cur.shape:
                raise ValueError(f"`prev_final`: expected {tuple(cur.shape)}, got "
                                 f"{tuple(prev_final.shape)}")
            prev = prev_final
        vel = (cur - prev) * self.fps
        n = vertex_normals(cur, faces)
        dj = torch.cdist(cur, joints)
        m = self.motion_history  # the coarse mesh's earlier velocities, newest first
        past = ((coarse_k[:, -m:-1] - coarse_k[:, -m - 1:-2]) * self.fps).flip(1) \
            if m > 1 else coarse_k.new_zeros(B, 0, V, 3)
        local = []
        if self.local_frame:  # R_v^T x: the skinned local frame of each vertex
            R = rot[0]
            down = R.new_tensor([0.0, 0.0, -1.0]).expand(B, V, 3)
            vel, n, down = (torch.einsum("bvji,bvj->bvi", R, x) for x in (vel, n, down))
            past = torch.einsum("bvji,bkvj->bkvi", R, past)
            local = [rest_pos.unsqueeze(0).expand(B, V, 3), down]
        feats = ([vel, n, dj] + ([extra] if offset is not None else [])
                 + [past.transpose(1, 2).reshape(B, V, -1)] + local)
        x = self.dynamic_norm(torch.cat(feats, -1).reshape(B * V, -1))
        ei = cached_batch_edges(edge_index, B, V)
        e = self.dynamic_edge_norm(edge_features(cur.reshape(B * V, 3), ei))
        accel = self.dynamic(x, ei, e).view(B, V, 3)
        unit = self.fps ** -2 if self.accel_unit is None else self.accel_unit
        if self.local_frame:  # back to the world: R_v a
            accel = torch.einsum("bvij,bvj->bvi", R, accel)
        final = cur + self._gate(2, accel * unit)
        if offset is not None:
            final = final + offset
        if self.strain_limit:
            edges, lengths = static.strain_edges, static.strain_lengths
            if edges is None:  # static features made before strain_limit was switched on
                edges, lengths = self._strain_targets(rest_pos, faces)
            final = project_edge_lengths(final, edges, lengths, self.strain_limit,
                                         stretch_only=True)
        if self.collision_projection is not None and body_pos is not None:
            if body_faces is None:
                raise ValueError("`body_faces`: needed with `body_pos` for the collision "
                                 "projection")
            final = push_outside(final, body_pos, body_faces, self.collision_projection,
                                 compiled=self.compile_search)
        return {"final": final, "coarse": cur, "accel": accel, "weights": W}

    def rollout(self, static: StaticFeatures, rest_pos: Tensor, faces: Tensor,
                edge_index: Tensor, rest_joints: Tensor, parents: Tensor, rotations: Tensor,
                translation: Tensor, first: Optional[Tensor] = None,
                body_pos: Optional[Tensor] = None, body_faces: Optional[Tensor] = None,
                state: Optional[Tensor] = None):
        """Autoregressive inference: the ``T`` frames one after another, the dynamic
        graph's velocity taken from the model's own previous prediction (``first``
        ``[V, 3]``: the garment before frame 0; default: the coarse mesh).  Same inputs
        and outputs as :meth:`forward` with ``B = T`` consecutive frames; ``T`` times
        the calls of the frame-parallel mode, and errors can accumulate.

        With ``garment_state`` the state of frame ``t`` is the model's own frames
        ``t-2, t-1``; before them ``state`` ``[2, V, 3]`` (the garment at the two frames
        before frame 0), else ``first`` twice, else no state at frame 0 and frame 0
        twice at frame 1 (as the data module clamps histories at the first frame)."""
        outs = []
        prev = None if first is None else first.unsqueeze(0)
        past = [] if first is None else [first]
        if state is not None:
            if not self.garment_state or state.shape != (2,) + tuple(rest_pos.shape):
                raise ValueError(f"`state`: expected [2, {rest_pos.shape[0]}, 3] for a model "
                                 f"with `garment_state`, got {tuple(state.shape)}")
            past = [state[0], state[1]]
        for t in range(rotations.shape[0]):
            state = None
            if self.garment_state:
                state = torch.stack([past[max(len(past) - 2, 0)], past[-1]])[None] \
                    if past else None
            o = self.forward(static, rest_pos, faces, edge_index, rest_joints, parents,
                             rotations[t:t + 1], translation[t:t + 1],
                             prev_final=None if self.garment_state else prev,
                             body_pos=None if body_pos is None else body_pos[t:t + 1],
                             body_faces=body_faces, state=state)
            prev = o["final"]
            past.append(prev[0])
            outs.append(o)
        return {k: torch.cat([o[k] for o in outs]) for k in outs[0]}
