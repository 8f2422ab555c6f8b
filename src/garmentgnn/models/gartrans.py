"""GarTrans (paper §3.1, §4.1): dynamic-aware graph construction + SAT deformation.

:meth:`GarTrans.forward` reads one :class:`~garmentgnn.models.inputs.GarmentInputs` (a
chunk, or a PyG ``Batch`` of chunks of several garments) and runs the paper's pipeline:
:meth:`~GarTrans.encode_static` (rest features, Nyström and body branches: ``x''``, once
per garment) -> :meth:`~GarTrans.coarse` (GRU motion code, skinning weights ``W^t``,
coarse mesh ``M^{t,c}``, Eqs. 1-2) -> :meth:`~GarTrans.deform` (the SAT stack's ``a``) ->
:meth:`~GarTrans.post_steps` (strain limit, collision projection: not in the paper).
The project's defaults differ from the paper where measured better (docs/model.md);
:meth:`GarTrans.paper` (``recipes/ablations/paper.yaml``) is the paper's form.  Choices
where the paper is vague: per-vertex Nyström features (``V x k`` through FC layers);
``Θ^[1]`` = the GRU's last hidden state -> linear -> ``S``; ``a`` added to the coarse mesh
(frame-parallel);
any registry layer in any slot.
"""
from __future__ import annotations

from typing import Any, Dict, Optional, Tuple

import torch
from torch import Tensor, nn

from garmentgnn.models.inputs import NYSTROM_DIM
from garmentgnn.body.lbs import forward_kinematics
from garmentgnn.geometry import (edge_features, edge_lengths, unique_edges, vertex_normals,
                                 full_precision)
from garmentgnn.models.blocks import (AttentionStack, Configurable, RunningNormalizer,
                                      cached_batch_edges, check_arguments, compiled_forward,
                                      geometric_init_, mlp, pad_graph, scaled, sized)
from garmentgnn.models.inputs import GarmentInputs
from garmentgnn.physics import COLLISION_MARGIN
from garmentgnn.models.sequence import (ChunkLayout, PostSteps, SequencePrediction,
                                        StaticFeatures)

#: metres per unit of the blend-shape stack's output (it predicts centimetres)
BLEND_UNIT = 0.01

#: the :class:`GarTrans` arguments of the paper's own form (§3.1, §4.1; the Args below
#: say what each switches off)
PAPER_FORM: Dict[str, Any] = {"skin_prior": False, "lbs_start": False, "gate_init": 0.0,
                              "blend_shape": True, "accel_unit": None, "input_norm": False,
                              "local_frame": False, "strain_limit": 0,
                              "collision_projection": None}


class GarTrans(Configurable, PostSteps, SequencePrediction, nn.Module):
    """The full model.  Layer slots take registry names (``sat``, ``gt``, ``gt_edge``,
    ``structure_aware``, ``gat``), so the paper's ablations are one argument.  The
    defaults are the project's; :meth:`paper` builds the paper's form (:data:`PAPER_FORM`).

    Args:
        num_joints: ``S``.
        num_body_vertices: body vertex count (input width of the body FC branch).
        nystrom_dim: number of Nyström eigenvector features per vertex.
        rest_layer, blend_layer, dynamic_layer: the layers of the three slots: names of
            :data:`garmentgnn.nn.LAYERS` or layer class paths (:func:`~garmentgnn.nn.make_layer`).
        heads: attention heads (4 in the paper).  fps: frame rate (velocities, ``dt^2``).
        use_body: feed the body-vertex-to-joint distances (``False``: a learned per-joint
            code for ``b^[1]``, for scenes without a body).
        skin_prior: ``W^t`` starts from the garment's skinning weights (``softmax(log
            W_prior + x''')``); ``False`` (the paper): learned from scratch.
        lbs_start: ReZero-style gates (three learnable scalars started at ``gate_init``)
            on what each learned branch adds to plain skinning: the skinning logits, the
            blend shape and the dynamic output (needs ``skin_prior``).  At 0 the untrained
            model is LBS but gated branches get no gradient until the gates move.
        blend_shape: the blend shape ``B^t`` and its stack (the paper).
        accel_unit: metres per unit of the dynamic output (``0.01``: centimetres); ``None``
            (the paper): an acceleration, ``a dt^2``.
        input_norm: MeshGraphNets-style running normalisers of the stacks' vertex and
            edge features (statistics of training, saved in the checkpoint).
        local_frame: the dynamic stack works in each vertex's skinned local frame ``R_v``
            (the rotation of its blended skinning transform, Eq. 1): velocity and normal
            enter as ``R_v^T x`` with the local gravity direction and the rest position as
            six more features, and the output is turned back by ``R_v``.
        strain_limit: sweeps of Provot's strain limit, shortening edges longer than at
            rest (:func:`~garmentgnn.geometry.project_edge_lengths`); ``0`` (the paper): none.
        collision_projection: margin ``eps`` (metres) of a last differentiable step moving
            vertices closer than ``eps`` to the body (or inside it) to ``eps`` outside
            (:func:`~garmentgnn.geometry.push_outside`); ``None`` (the paper): none.
        compile_search: ``torch.compile`` the projection's nearest-face search (faster).
        compile_stack: ``None`` (the default): the dynamic stack runs eager (on the CPU
            the fastest: eager takes the sparse kernels, a compiled layer message
            passing, docs/inference.md).  A ``torch.compile`` mode (``"default"``,
            ``"reduce-overhead"``: CUDA graphs on a GPU, ``"max-autotune"``): while
            training, the dynamic stack runs compiled with static shapes on its graph
            padded to :func:`~garmentgnn.models.blocks.bucket` sizes
            (:func:`~garmentgnn.models.blocks.pad_graph`: the real vertices' outputs and
            gradients are the unpadded ones), so a few compiled graphs serve every batch
            and a GPU replays each step's stack as one CUDA graph (dynamo keeps up to its
            ``recompile_limit``, 8, bucket pairs; further ones run eager, with its warning).
        width, depth: the size, factors of the default (the paper's): hidden widths times
            ``width``, stacked layers ``depth`` times as many (:func:`~.blocks.sized`).
    """

    def __init__(self, num_joints: int, num_body_vertices: int, nystrom_dim: int = NYSTROM_DIM,
                 rest_layer: str = "gt", blend_layer: str = "gt", dynamic_layer: str = "sat",
                 heads: int = 4, fps: float = 30.0, edge_dim: int = 4, use_body: bool = True,
                 skin_prior: bool = True, lbs_start: bool = True, gate_init: float = 1.0,
                 blend_shape: bool = False, accel_unit: Optional[float] = 0.01,
                 input_norm: bool = True, local_frame: bool = True, strain_limit: int = 10,
                 collision_projection: Optional[float] = COLLISION_MARGIN,
                 compile_search: bool = False, compile_stack: Optional[str] = None,
                 width: float = 1.0, depth: float = 1.0) -> None:
        super().__init__()
        check_arguments(lbs_start=lbs_start, skin_prior=skin_prior, gate_init=gate_init,
                        accel_unit=accel_unit, strain_limit=strain_limit, width=width, depth=depth,
                        collision_projection=collision_projection, compile_stack=compile_stack)
        S = num_joints
        self.num_joints, self.num_body_vertices, self.fps, self.edge_dim = \
            S, num_body_vertices, fps, edge_dim
        self.use_body, self.skin_prior = bool(use_body), bool(skin_prior)
        self.gate_init, self.accel_unit = float(gate_init), accel_unit
        self.input_norm, self.local_frame = bool(input_norm), bool(local_frame)
        self.strain_limit, self.collision_projection = strain_limit, collision_projection
        self.compile_search, self.compile_stack = bool(compile_search), compile_stack
        self.rest_fc = mlp([6 + S, *scaled(width, 128, 128, 128)], nn.Tanh())
        self.rest_attn = AttentionStack(rest_layer, *scaled(width, 128), sized(
            [64, 64, 128], width, depth), heads, edge_dim, "tanh", last_act=True)
        d = self.rest_attn.out_channels  # the paper's 128: the last rest layer's width
        self.nystrom_fc = mlp([nystrom_dim, *scaled(width, 64), d], nn.Tanh())
        self.body_fc = mlp([num_body_vertices, *scaled(width, 512, 256), d], nn.Tanh())
        self.body_default = nn.Parameter(torch.randn(d, S) / d ** 0.5)
        self.gru = nn.GRU(3 * S + 3, *scaled(width, 128), max(1, round(2 * depth)),
                          batch_first=True)
        self.gru_out = nn.Linear(*scaled(width, 128), S)
        self.blend = AttentionStack(blend_layer, S, sized([32, 32, 32, 3], width, depth, True),
                                    heads, edge_dim, "elu", False) if blend_shape else None
        dyn_in = 3 + 3 + S + (6 if self.local_frame else 0)  # + rest, gravity: local frame
        self.dynamic = AttentionStack(dynamic_layer, dyn_in, sized(
            [32, 64, 64, 64, 32, 3], width, depth, True), heads, edge_dim, "elu", False)
        #: (g_W, g_B, g_a) of ``lbs_start``; ``None``: no gates (the paper)
        self.gates = nn.Parameter(torch.zeros(3)) if lbs_start else None
        norm = RunningNormalizer if self.input_norm else (lambda size: nn.Identity())
        self.rest_norm, self.rest_edge_norm = norm(6 + S), norm(edge_dim)
        self.dynamic_norm, self.dynamic_edge_norm = norm(dyn_in), norm(edge_dim)
        self.reset_parameters()
        # only one body code path is used: the other never gets a gradient (DDP needs
        # every trainable parameter to receive one)
        (self.body_default if self.use_body else self.body_fc).requires_grad_(False)

    @classmethod
    def paper(cls, num_joints: int, num_body_vertices: int, **kwargs: Any) -> "GarTrans":
        """The paper's form (:data:`PAPER_FORM`; ``kwargs`` override it)."""
        return cls(num_joints, num_body_vertices, **{**PAPER_FORM, **kwargs})

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

    def _gate(self, i: int, x: Tensor) -> Tensor:  # the lbs_start gate i on x
        return x if self.gates is None else self.gates[i] * x

    # -- 1. static branch -------------------------------------------------------------
    def encode_static(self, inputs: GarmentInputs) -> StaticFeatures:
        """``x''`` ``[V, S]`` of every garment of ``inputs`` (and the skinning prior and
        strain-limit targets): once per garment and body shape, reused by every frame."""
        if inputs.num_joints != self.num_joints:
            raise ValueError(f"`inputs.rest_joints`: a skeleton of {inputs.num_joints} joints, "
                             f"this model has {self.num_joints} (`num_joints`)")
        lay = ChunkLayout(inputs)
        rest_pos, faces, edge_index = inputs.rest_pos, inputs.faces, inputs.edge_index
        dj = lay.joint_distances(rest_pos.unsqueeze(0), lay.rest_joints.unsqueeze(0))[0]
        x = self.rest_fc(self.rest_norm(torch.cat([rest_pos, vertex_normals(rest_pos, faces),
                                                   dj], -1)))
        x = self.rest_attn(x, edge_index, self.rest_edge_norm(edge_features(rest_pos,
                                                                          edge_index)))
        x1 = x * self.nystrom_fc(inputs.nystrom)  # x' = x̄^[1] ⊙ u^[1]
        if self.use_body and inputs.get("body_joint_dists") is not None:
            bd = inputs.body_joint_dists.view(lay.N, -1, self.num_joints)  # [N, Vb, S]
            b = self.body_fc(bd.transpose(1, 2)).transpose(1, 2)  # b^[1]: [N, d, S]
        else:
            b = self.body_default.unsqueeze(0).expand(lay.N, -1, -1)
        x2 = lay.per_chunk_matmul(x1, b)  # x'' = x' b^[1]: [V, S]
        log_prior = None
        if self.skin_prior:
            prior = inputs.skin_weights
            if prior.shape != x2.shape:
                raise ValueError(f"`inputs.skin_weights`: expected {tuple(x2.shape)}, got "
                                 f"{tuple(prior.shape)}")
            log_prior = prior.to(x1.dtype).clamp_min(1e-4).log()
        static = StaticFeatures(x2=x2, log_prior=log_prior)
        if self.strain_limit:
            edges = unique_edges(faces, rest_pos.shape[0]).edges
            static.strain_edges, static.strain_lengths = edges, edge_lengths(rest_pos, edges)
        return static

    # -- 2. dynamic graph ---------------------------------------------------------------
    def motion_code(self, rotations: Tensor, translation: Tensor) -> Tensor:
        """``Θ^[1]`` ``[M, S]`` from pose histories ``[M, H, S, 3]``, ``[M, H, 3]``; ones
        (no modulation) for a history whose frames are all one pose (each on its own);
        the GRU is skipped when every history is such."""
        M = rotations.shape[0]
        still = ((rotations == rotations[:, :1]).reshape(M, -1).all(1)
                 & (translation == translation[:, :1]).reshape(M, -1).all(1))
        ones = rotations.new_ones(M, self.num_joints)
        if bool(still.all()):
            return ones
        vel = torch.diff(translation, dim=1, prepend=translation[:, :1]) * self.fps
        h, _ = self.gru(torch.cat([rotations.flatten(2), vel], -1))
        code = self.gru_out(h[:, -1])
        return torch.where(still.unsqueeze(1), ones, code) if bool(still.any()) else code

    def coarse(self, inputs: GarmentInputs, static: StaticFeatures
               ) -> Tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Coarse meshes ``M^{t-1,c}, M^{t,c}`` ``[B, V, 3]`` (frame t's weights for
        both), the skinning weights ``W^t`` ``[B, V, S]``, the posed joints ``[N, B, S,
        3]`` and each vertex's skinning rotation ``R_v`` ``[B, V, 3, 3]`` at frame t."""
        lay = ChunkLayout(inputs)
        N, B, V = lay.N, lay.B, inputs.num_vertices
        code = self.motion_code(lay.rotations.flatten(0, 1), lay.translation.flatten(0, 1))
        code = lay.per_vertex(code.view(N, B, -1))
        x3 = static.x2.unsqueeze(0) * code  # [B, V, S]
        logits = x3 if static.log_prior is None else self._gate(0, x3) + static.log_prior
        W = torch.softmax(logits, -1)  # W^t
        template = inputs.rest_pos.unsqueeze(0).expand(B, V, 3)
        if self.blend is not None:
            e = self.rest_edge_norm(edge_features(inputs.rest_pos, inputs.edge_index))
            blend = self.blend(x3.reshape(B * V, -1),
                               cached_batch_edges(inputs.edge_index, B, V), e.repeat(B, 1))
            # T^t = T + B^t (Eq. 2), in centimetres (BLEND_UNIT): a fresh model starts near
            # its skinned rest garment
            template = template + self._gate(1, BLEND_UNIT * blend.view(B, V, 3))
        rot2, tr2 = lay.rotations[:, :, -2:], lay.translation[:, :, -2:]  # [N, B, 2, ...]
        rj = lay.rest_joints.repeat_interleave(B * 2, 0)
        with full_precision(rot2):  # float32 kinematics under autocast
            A, joints = forward_kinematics(rot2.reshape(N * B * 2, self.num_joints, 3), rj,
                                           lay.parents, tr2.reshape(N * B * 2, 3))
        A, joints = A.view(N, B, 2, *A.shape[1:]), joints.view(N, B, 2, -1, 3)
        # Eq. 1 with frame t's template and weights, frames t-1 and t (float32)
        (prev, _), (cur, M) = (lay.skin(W, A[:, :, k], template) for k in (0, 1))
        return prev, cur, W, joints[:, :, 1], M[..., :3, :3]

    # -- 3. SAT deformation ---------------------------------------------------------------
    def deform(self, inputs: GarmentInputs, prev: Tensor, cur: Tensor, joints: Tensor,
               R: Tensor) -> Tensor:
        """The dynamic stack's output ``a`` ``[B, V, 3]`` for the coarse mesh ``cur``
        (world frame, in units of :attr:`unit` metres), from its velocity since
        ``prev``."""
        lay = ChunkLayout(inputs)
        B, V = cur.shape[:2]
        vel, n = (cur - prev) * self.fps, vertex_normals(cur, inputs.faces)
        dj = lay.joint_distances(cur, joints.transpose(0, 1))
        feats = [vel, n, dj]
        if self.local_frame:  # R_v^T x: the skinned local frame of each vertex
            down = R.new_tensor([0.0, 0.0, -1.0]).expand(B, V, 3)
            vel, n, down = (torch.einsum("bvji,bvj->bvi", R, x) for x in (vel, n, down))
            feats = [vel, n, dj, inputs.rest_pos.unsqueeze(0).expand(B, V, 3), down]
        x = self.dynamic_norm(torch.cat(feats, -1).reshape(B * V, -1))
        ei = cached_batch_edges(inputs.edge_index, B, V)
        e = self.dynamic_edge_norm(edge_features(cur.reshape(B * V, 3), ei))
        a = self.dynamic_stack(x, ei, e).view(B, V, -1)
        if self.local_frame:  # back to the world: R_v a
            a = torch.cat([torch.einsum("bvij,bvj->bvi", R, a[..., :3]), a[..., 3:]], -1)
        return a

    def dynamic_stack(self, x: Tensor, edge_index: Tensor, edge_attr: Tensor) -> Tensor:
        """The dynamic stack on the batched graph: eager, or (``compile_stack``, while
        training) compiled with static shapes on the graph padded to bucket sizes."""
        if self.compile_stack is None or not torch.is_grad_enabled():
            return self.dynamic(x, edge_index, edge_attr)
        out = compiled_forward(self.dynamic, *pad_graph(x, edge_index, edge_attr),
                               mode=self.compile_stack, dynamic=False)
        return out[:x.size(0)]

    @property
    def unit(self) -> float:
        """Metres per unit of the dynamic output (``dt^2``: the paper's acceleration)."""
        return self.fps ** -2 if self.accel_unit is None else self.accel_unit

    def forward(self, inputs: GarmentInputs, static: Optional[StaticFeatures] = None,
                prev_final: Optional[Tensor] = None) -> Dict[str, Tensor]:
        """``M^{t,d}`` of every frame of ``inputs`` (frame-parallel; a ``Batch`` of chunks
        as one union graph).  ``static``: a cached :meth:`encode_static` of the same
        garments; ``prev_final`` ``[B, V, 3]``: the garment at frame ``t-1`` in place of
        the coarse ``M^{t-1,c}`` (autoregressive use, :meth:`rollout`).

        Returns ``final``, ``coarse``, ``accel`` (``[B, V, 3]``) and ``weights`` (``[B, V,
        S]``)."""
        static = self.encode_static(inputs) if static is None else static
        prev, cur, W, joints, R = self.coarse(inputs, static)
        out = {"coarse": cur, "weights": W}
        if prev_final is not None:
            if prev_final.shape != cur.shape:
                raise ValueError(f"`prev_final`: expected {tuple(cur.shape)}, got "
                                 f"{tuple(prev_final.shape)}")
            prev = prev_final
        out["accel"] = a = self.deform(inputs, prev, cur, joints, R)
        out["final"] = self.post_steps(inputs, static, cur + self._gate(2, a * self.unit))
        return out
