"""DA-style baseline (DeePSD-style static supervised graph network)."""
from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor, nn

from garmentgnn.body.lbs import forward_kinematics
from garmentgnn.geometry import (edge_features, vertex_joint_distances, vertex_normals,
                                 full_precision)
from garmentgnn.models.baselines.common import skin, small_init_
from garmentgnn.models.blocks import Configurable, batch_edges, compiled_forward, mlp
from garmentgnn.models.inputs import GarmentInputs
from garmentgnn.models.sequence import ChunkLayout
from garmentgnn.nn import GATBaselineConv

__all__ = ["DAStyle"]


class DAStyle(Configurable, nn.Module):
    """DeePSD-style static garment network ("DA" in the paper's Tables 2-3; Bertiche,
    Madadi, Tylson & Escalera, *DeePSD: Automatic Deep Skinning And Pose Space
    Deformation For 3D Garment Animation*, ICCV 2021).

    A graph attention network over the garment mesh reads multi-source per-vertex
    attributes -- rest position, rest vertex normal, LBS-skinned position relative to
    the posed root joint, and distances from the skinned vertex to every posed joint --
    and predicts a per-vertex offset added to the LBS result.  Garment-agnostic (the
    mesh is an input), frame-by-frame (static: no history), trained supervised.

    Simplified from DeePSD: no learned skinning weights (the scene's transferred
    weights are used as-is), the pose-space deformation is a posed-space offset rather
    than blend shapes in rest space, GATv2 layers (:class:`garmentgnn.nn.GATBaselineConv`)
    instead of its point-cloud/graph encoder, and no physics regulariser.

    Args:
        num_joints: ``S``.
        hidden: node width (heads are concatenated to it).
        heads: attention heads per layer (must divide ``hidden``).
        num_layers: GAT layers.
        compile: run :meth:`network` (encoder, GAT layers, decoder) through
            ``torch.compile`` as one region (inductor, dynamic shapes) while training
            (:func:`~garmentgnn.models.blocks.compiled_forward`): the
            same loss and gradients up to float round-off; on the CPU 1.1-2.2x eager's
            training vertex-frames per second with one thread, 0.5-1.3x with two
            (docs/results/step_profile).  ``None`` (the default): compiled where that
            was measured faster, on the CPU with one torch thread (as each process of a
            DDP run on the CPU's cores has: docs/results/train_scaling), eager
            otherwise, decided at every training call.  Evaluation runs eager.  Falls
            back to eager, with a warning, where compiling fails.
    """

    def __init__(self, num_joints: int, hidden: int = 64, heads: int = 2,
                 num_layers: int = 3, compile: Optional[bool] = None) -> None:
        super().__init__()
        if num_joints < 1:
            raise ValueError(f"`num_joints`: must be positive, got {num_joints}")
        if hidden < 1 or heads < 1 or hidden % heads:
            raise ValueError(f"`heads`: must divide `hidden` ({hidden}), got {heads}")
        if num_layers < 1:
            raise ValueError(f"`num_layers`: must be positive, got {num_layers}")
        self.num_joints = num_joints
        self.compile = None if compile is None else bool(compile)
        self.encoder = mlp([9 + num_joints, hidden, hidden], nn.ELU(), last_act=False)
        self.layers = nn.ModuleList(
            GATBaselineConv(hidden, hidden // heads, edge_dim=4, heads=heads, concat=True)
            for _ in range(num_layers))
        self.act = nn.ELU()
        self.decoder = mlp([hidden, hidden, 3], nn.ELU(), last_act=False)
        small_init_(self.decoder[-1])

    def features(self, scene: GarmentInputs, skinned: Tensor, joints: Tensor) -> Tensor:
        """``[B, V, 9 + S]`` per-vertex attributes (``joints [B, S, 3]``, or ``[N, B, S,
        3]`` for a batch of ``N`` chunks)."""
        B, V = skinned.shape[:2]
        rest = scene.rest_pos.to(skinned.dtype).expand(B, V, 3)
        normal = vertex_normals(scene.rest_pos, scene.faces).to(skinned.dtype).expand(B, V, 3)
        if joints.dim() == 3:
            rel = skinned - joints[:, :1]
            dist = vertex_joint_distances(skinned, joints)
        else:  # each vertex against its own chunk's joints
            lay = ChunkLayout(scene)
            rel = skinned - lay.per_vertex(joints[:, :, 0])
            dist = lay.joint_distances(skinned, joints.transpose(0, 1))
        return torch.cat([rest, normal, rel, dist], -1)

    @staticmethod
    def skin_batch(scene: GarmentInputs, rotations: Tensor, translation: Tensor):
        """Eq. 1 for a batch of ``N`` chunks: ``rotations [N, B, S, 3]``, ``translation
        [N, B, 3]`` -> (positions ``[B, V, 3]``, posed joints ``[N, B, S, 3]``)."""
        lay = ChunkLayout(scene)
        N, B, S = rotations.shape[:3]
        dt = scene.rest_pos.dtype
        with full_precision(rotations):  # float32 kinematics under autocast
            A, joints = forward_kinematics(rotations.reshape(N * B, S, 3).to(dt),
                                           lay.rest_joints.to(dt).repeat_interleave(B, 0),
                                           lay.parents, translation.reshape(N * B, 3).to(dt))
        W = scene.skin_weights.to(dt).expand(B, -1, -1)
        verts, _ = lay.skin(W, A.view(N, B, *A.shape[1:]), scene.rest_pos)
        return verts, joints.view(N, B, S, 3)

    def forward(self, scene: GarmentInputs, rotations: Tensor,
                translation: Optional[Tensor] = None) -> Tensor:
        """``rotations [B, S, 3]``, ``translation [B, 3]`` -> positions ``[B, V, 3]``; for
        a batch of ``N`` chunks ``[N, B, S, 3]`` and ``[N, B, 3]`` (one union graph)."""
        if scene.num_joints != self.num_joints:
            raise ValueError(f"`scene`: has {scene.num_joints} joints, the model {self.num_joints}")
        if rotations.dim() == 4:
            if translation is None:
                translation = rotations.new_zeros(rotations.shape[:2] + (3,))
            skinned, joints = self.skin_batch(scene, rotations, translation)
        else:
            skinned, joints = skin(scene, rotations, translation)
        dtype = self.encoder[0].weight.dtype
        B, V = skinned.shape[:2]
        x = self.features(scene, skinned, joints).to(dtype).reshape(B * V, -1)
        ei = batch_edges(scene.edge_index, B, V)
        ea = edge_features(scene.rest_pos.to(dtype), scene.edge_index).repeat(B, 1)
        compiled = self.compile if self.compile is not None else (
            x.device.type == "cpu" and torch.get_num_threads() == 1)
        offset = (compiled_forward(self, x, ei, ea, method="network") if compiled
                  else self.network(x, ei, ea)).reshape(B, V, 3)
        return skinned + offset.to(skinned.dtype)

    def network(self, x: Tensor, edge_index: Tensor, edge_attr: Tensor) -> Tensor:
        """Per-vertex attributes ``[N, 9 + S]`` of the batched frames -> offsets ``[N, 3]``:
        the encoder, the GAT layers (each followed by ELU) and the decoder (one region
        under ``compile``)."""
        x = self.encoder(x)
        for layer in self.layers:
            x = self.act(layer(x, edge_index, edge_attr))
        return self.decoder(x)
