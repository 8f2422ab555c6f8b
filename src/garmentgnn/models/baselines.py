"""Baselines of the paper's comparison (§4.3, Tables 2-3), written from their papers'
descriptions (no code copied), small enough to train on a CPU.

* :class:`LBSBaseline` -- no learning: the rest garment skinned to the frame (Eq. 1).
* :class:`DAStyle` -- "DA" / DeePSD-style static, supervised graph network on
  multi-source per-vertex attributes, predicting an offset on top of LBS.
* :class:`HOODStyle` -- HOOD-style hierarchical message passing predicting per-vertex
  accelerations from the two previous garment states and the body; autoregressive.
* :class:`NCSStyle` -- NCS-style garment-specific MLP from the pose history to
  per-vertex offsets, skinned.

Every model works on a :class:`GarmentScene` (rest mesh + skinning weights + skeleton),
which holds plain tensors; this package never builds garments or runs the simulator
(``garmentgnn.bench.scenes.build_scene`` makes a scene with the simulator's skinning
weights).  Training losses are not re-implemented here: the physics-trained baselines
(HOOD, NCS) are meant to be trained with :class:`garmentgnn.losses.GarTransLoss` with
only its physics terms enabled (collision, gravity, stretch, shear, bending, and
inertia for the dynamic ones); DA with its supervised terms.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Sequence, Tuple

import numpy as np
import torch
from torch import Tensor, nn
from torch_geometric.nn.conv import MessagePassing
from torch_geometric.utils import scatter

from garmentgnn.body.lbs import forward_kinematics, linear_blend_skinning
from garmentgnn.geometry import (edge_features, faces_to_edge_index, farthest_point_sampling,
                                 vertex_joint_distances, vertex_normals)
from garmentgnn.geometry.rotations import axis_angle_to_matrix
from garmentgnn.nn import GATBaselineConv

__all__ = ["GarmentScene", "CoarseLevel", "skin", "LBSBaseline", "DAStyle", "HOODStyle",
           "NCSStyle", "MLPMessagePassing"]


# --------------------------------------------------------------------------- inputs
@dataclass
class GarmentScene:
    """One garment dressed on one body shape, as tensors.

    Attributes:
        rest_pos: ``[V, 3]`` garment rest vertices (on the rest body).
        faces: ``[F, 3]`` long.
        weights: ``[V, S]`` garment skinning weights (rows sum to 1), e.g. from
            :func:`garmentgnn.garments.skinning.transfer_skinning_weights`.
        rest_joints: ``[S, 3]`` the body's rest joints.
        parents: ``[S]`` parent indices (root ``-1``).
        pinned: optional ``[V]`` bool mask of vertices that follow the skinned body.
        edge_index: ``[2, E]`` mesh graph (both directions, target-sorted); derived.
    """

    rest_pos: Tensor
    faces: Tensor
    weights: Tensor
    rest_joints: Tensor
    parents: Tensor
    pinned: Optional[Tensor] = None
    edge_index: Tensor = field(init=False)

    def __post_init__(self) -> None:
        if self.rest_pos.dim() != 2 or self.rest_pos.shape[1] != 3:
            raise ValueError(f"`rest_pos`: expected [V, 3], got {tuple(self.rest_pos.shape)}")
        V = self.rest_pos.shape[0]
        if self.faces.dim() != 2 or self.faces.shape[1] != 3:
            raise ValueError(f"`faces`: expected [F, 3], got {tuple(self.faces.shape)}")
        S = self.rest_joints.shape[0]
        if self.rest_joints.dim() != 2 or self.rest_joints.shape[1] != 3:
            raise ValueError(f"`rest_joints`: expected [S, 3], got {tuple(self.rest_joints.shape)}")
        if self.weights.shape != (V, S):
            raise ValueError(f"`weights`: expected [{V}, {S}], got {tuple(self.weights.shape)}")
        if self.parents.shape != (S,):
            raise ValueError(f"`parents`: expected [{S}], got {tuple(self.parents.shape)}")
        if self.pinned is not None and self.pinned.shape != (V,):
            raise ValueError(f"`pinned`: expected [{V}] bool, got {tuple(self.pinned.shape)}")
        if not torch.isfinite(self.rest_pos).all():
            raise ValueError("`rest_pos`: contains NaN/inf")
        self.faces = self.faces.long()
        self.edge_index = faces_to_edge_index(self.faces, V)

    @property
    def num_vertices(self) -> int:
        return self.rest_pos.shape[0]

    @property
    def num_joints(self) -> int:
        return self.rest_joints.shape[0]

    def pinned_mask(self) -> Tensor:
        """``[V]`` bool (all False when the scene has no pinned vertices)."""
        if self.pinned is None:
            return torch.zeros(self.num_vertices, dtype=torch.bool)
        return self.pinned.bool()


def _check_pose(scene: GarmentScene, rotations: Tensor, translation: Optional[Tensor],
                name: str = "rotations") -> None:
    if rotations.dim() != 3 or rotations.shape[1:] != (scene.num_joints, 3):
        raise ValueError(f"`{name}`: expected [B, {scene.num_joints}, 3] axis-angle, got "
                         f"{tuple(rotations.shape)}")
    if translation is not None and translation.shape != (rotations.shape[0], 3):
        raise ValueError(f"`translation`: expected [{rotations.shape[0]}, 3], got "
                         f"{tuple(translation.shape)}")


def skin(scene: GarmentScene, rotations: Tensor, translation: Optional[Tensor] = None,
         offsets: Optional[Tensor] = None) -> Tuple[Tensor, Tensor]:
    """Linear blend skinning (Eq. 1) of the rest garment, plus optional canonical offsets.

    Args:
        rotations: ``[B, S, 3]`` local axis-angle joint rotations.
        translation: ``[B, 3]`` root translation (default zero).
        offsets: ``[B, V, 3]`` added to the rest vertices *before* skinning.

    Returns:
        ``(positions [B, V, 3], posed joints [B, S, 3])`` in the dtype of ``rest_pos``
        (the computation follows the simulator's: kinematics in that dtype).
    """
    _check_pose(scene, rotations, translation)
    dt = scene.rest_pos.dtype
    A, joints = forward_kinematics(rotations.to(dt), scene.rest_joints.to(dt), scene.parents,
                                   None if translation is None else translation.to(dt))
    verts = scene.rest_pos if offsets is None else scene.rest_pos + offsets
    return linear_blend_skinning(verts, scene.weights.to(dt), A), joints


def _mlp(sizes: Sequence[int], act: type = nn.ELU, norm: bool = False) -> nn.Sequential:
    layers = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        layers.append(nn.Linear(a, b))
        if i < len(sizes) - 2:
            layers.append(act())
    if norm:
        layers.append(nn.LayerNorm(sizes[-1]))
    return nn.Sequential(*layers)


def _small_init_(linear: nn.Linear, scale: float = 1e-2) -> None:
    """Start an output layer near zero (so a fresh model predicts ~LBS / ~free fall)
    while keeping every upstream gradient non-zero."""
    with torch.no_grad():
        linear.weight.mul_(scale)
        linear.bias.zero_()


def _batched_graph(edge_index: Tensor, copies: int, num_nodes: int) -> Tensor:
    offsets = torch.arange(copies, device=edge_index.device) * num_nodes
    return (edge_index.unsqueeze(1) + offsets.view(1, -1, 1)).reshape(2, -1)


# --------------------------------------------------------------------------- LBS
class LBSBaseline(nn.Module):
    """No learning: the garment rest mesh skinned to each frame by linear blend
    skinning (the paper's Eq. 1) with the scene's weights -- the same initial state the
    reference simulator starts from.  Static and body-tight by construction: no
    gravity, no dynamics, no collision handling."""

    def forward(self, scene: GarmentScene, rotations: Tensor,
                translation: Optional[Tensor] = None) -> Tensor:
        """``rotations [B, S, 3]``, ``translation [B, 3]`` -> positions ``[B, V, 3]``."""
        return skin(scene, rotations, translation)[0]


# --------------------------------------------------------------------------- DA
class DAStyle(nn.Module):
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
    """

    def __init__(self, num_joints: int, hidden: int = 64, heads: int = 2,
                 num_layers: int = 3) -> None:
        super().__init__()
        if num_joints < 1:
            raise ValueError(f"`num_joints`: must be positive, got {num_joints}")
        if hidden < 1 or heads < 1 or hidden % heads:
            raise ValueError(f"`heads`: must divide `hidden` ({hidden}), got {heads}")
        if num_layers < 1:
            raise ValueError(f"`num_layers`: must be positive, got {num_layers}")
        self.num_joints = num_joints
        self.encoder = _mlp([9 + num_joints, hidden, hidden])
        self.layers = nn.ModuleList(
            GATBaselineConv(hidden, hidden // heads, edge_dim=4, heads=heads, concat=True)
            for _ in range(num_layers))
        self.act = nn.ELU()
        self.decoder = _mlp([hidden, hidden, 3])
        _small_init_(self.decoder[-1])

    def features(self, scene: GarmentScene, skinned: Tensor, joints: Tensor) -> Tensor:
        """``[B, V, 9 + S]`` per-vertex attributes."""
        B, V = skinned.shape[:2]
        rest = scene.rest_pos.to(skinned.dtype).expand(B, V, 3)
        normal = vertex_normals(scene.rest_pos, scene.faces).to(skinned.dtype).expand(B, V, 3)
        rel = skinned - joints[:, :1]
        dist = vertex_joint_distances(skinned, joints)
        return torch.cat([rest, normal, rel, dist], -1)

    def forward(self, scene: GarmentScene, rotations: Tensor,
                translation: Optional[Tensor] = None) -> Tensor:
        """``rotations [B, S, 3]``, ``translation [B, 3]`` -> positions ``[B, V, 3]``."""
        if scene.num_joints != self.num_joints:
            raise ValueError(f"`scene`: has {scene.num_joints} joints, the model {self.num_joints}")
        skinned, joints = skin(scene, rotations, translation)
        dtype = self.encoder[0].weight.dtype
        B, V = skinned.shape[:2]
        x = self.encoder(self.features(scene, skinned, joints).to(dtype)).reshape(B * V, -1)
        ei = _batched_graph(scene.edge_index, B, V)
        ea = edge_features(scene.rest_pos.to(dtype), scene.edge_index).repeat(B, 1)
        for layer in self.layers:
            x = self.act(layer(x, ei, ea))
        offset = self.decoder(x).reshape(B, V, 3)
        return skinned + offset.to(skinned.dtype)


# --------------------------------------------------------------------------- HOOD
@dataclass
class CoarseLevel:
    """The coarse level of a two-level mesh hierarchy.

    Attributes:
        landmarks: ``[Z]`` fine-vertex indices of the coarse nodes.
        assign: ``[V]`` coarse node of each fine vertex (geodesically nearest landmark).
        edge_index: ``[2, Ec]`` coarse graph (both directions, target-sorted).
    """

    landmarks: Tensor
    assign: Tensor
    edge_index: Tensor

    @classmethod
    def build(cls, rest_pos: Tensor, faces: Tensor, ratio: int = 4, k: int = 6,
              seed: int = 0) -> "CoarseLevel":
        """Geodesic farthest-point sampling of ``V // ratio`` landmarks
        (:func:`garmentgnn.geometry.farthest_point_sampling`, graph geodesics on the rest
        mesh); each landmark is linked to its ``k`` geodesically nearest landmarks
        (symmetrised); each vertex is assigned to its nearest landmark."""
        V = rest_pos.shape[0]
        if not isinstance(ratio, int) or ratio < 1:
            raise ValueError(f"`ratio`: must be a positive int, got {ratio!r}")
        if not isinstance(k, int) or k < 1:
            raise ValueError(f"`k`: must be a positive int, got {k!r}")
        Z = max(2, V // ratio)
        if Z > V:
            raise ValueError(f"`rest_pos`: needs at least 2 vertices, got {V}")
        idx, dist = farthest_point_sampling(rest_pos.detach().double().numpy(),
                                            faces.numpy(), Z, seed=seed)
        d = dist.numpy()  # [Z, V]
        d = np.where(np.isfinite(d), d, 1e30)  # disconnected panels: far apart
        assign = torch.from_numpy(d.argmin(0))
        dzz = d[:, idx.numpy()]  # [Z, Z]
        np.fill_diagonal(dzz, np.inf)
        kk = min(k, Z - 1)
        nn_idx = np.argsort(dzz, axis=1)[:, :kk]
        src = np.repeat(np.arange(Z), kk)
        dst = nn_idx.reshape(-1)
        pairs = np.unique(np.concatenate([np.stack([src, dst], 1), np.stack([dst, src], 1)]),
                          axis=0)
        order = np.lexsort((pairs[:, 0], pairs[:, 1]))  # sort by target, then source
        ei = torch.from_numpy(pairs[order].T.copy()).long()
        return cls(landmarks=idx.long(), assign=assign.long(), edge_index=ei)

    @property
    def num_nodes(self) -> int:
        return self.landmarks.shape[0]


class MLPMessagePassing(MessagePassing):
    """One MeshGraphNets-style block: ``e' = e + f_e([h_i, h_j, e])``,
    ``h' = h + f_v([h, sum_j e'_ji])`` (residual MLPs with LayerNorm)."""

    def __init__(self, hidden: int) -> None:
        super().__init__(aggr="sum")
        self.edge_mlp = _mlp([3 * hidden, hidden, hidden], norm=True)
        self.node_mlp = _mlp([2 * hidden, hidden, hidden], norm=True)

    def forward(self, h: Tensor, edge_index: Tensor, e: Tensor) -> Tuple[Tensor, Tensor]:
        src, dst = edge_index
        e = e + self.edge_mlp(torch.cat([h[dst], h[src], e], -1))
        agg = self.propagate(edge_index, e=e, size=(h.shape[0], h.shape[0]))
        return h + self.node_mlp(torch.cat([h, agg], -1)), e

    def message(self, e: Tensor) -> Tensor:  # noqa: D102 - the edge state is the message
        return e


class HOODStyle(nn.Module):
    """HOOD-style dynamic garment network (Grigorev, Thomaszewski, Black & Hilliges,
    *HOOD: Hierarchical Graphs for Generalized Modelling of Clothing Dynamics*, CVPR
    2023).

    Predicts per-vertex accelerations ``a`` from the two previous garment states
    ``x_{t-2}, x_{t-1}`` and the body at ``t``; the next state is
    ``x_t = 2 x_{t-1} - x_{t-2} + a dt^2`` and :meth:`rollout` applies it
    autoregressively.  Message passing is hierarchical: fine-mesh blocks, pooling
    (mean) onto a coarse level (:class:`CoarseLevel`), coarse blocks with long-range
    edges, unpooling (copy back, residual) and a final fine block.  Features are
    translation-invariant: vertex velocity and normal, pinned flag, vector and
    distance to the nearest body vertex; edges carry current and rest relative
    positions and lengths.  Garment-agnostic; trained with physics losses only
    (``GarTransLoss`` physics terms incl. inertia), one step at a time like HOOD.

    Simplified from HOOD: two levels instead of several (coarse nodes by geodesic
    farthest-point sampling with k-NN geodesic edges instead of HOOD's graph
    coarsening), body interaction as a nearest-body-vertex node feature instead of
    body-garment edges, no material parameters as inputs, no normalisation statistics.

    Args:
        hidden: width of every MLP.
        fine_blocks: message-passing blocks before and after the coarse level (each).
        coarse_blocks: blocks on the coarse level.
        dt: frame time step (s).
    """

    NODE_IN = 11
    EDGE_IN = 8

    def __init__(self, hidden: int = 64, fine_blocks: int = 1, coarse_blocks: int = 2,
                 dt: float = 1.0 / 30.0) -> None:
        super().__init__()
        if hidden < 1:
            raise ValueError(f"`hidden`: must be positive, got {hidden}")
        if fine_blocks < 1 or coarse_blocks < 1:
            raise ValueError("`fine_blocks`/`coarse_blocks`: must be positive")
        if not dt > 0:
            raise ValueError(f"`dt`: must be positive, got {dt}")
        self.dt = float(dt)
        self.node_enc = _mlp([self.NODE_IN, hidden, hidden], norm=True)
        self.edge_enc = _mlp([self.EDGE_IN, hidden, hidden], norm=True)
        self.coarse_edge_enc = _mlp([self.EDGE_IN, hidden, hidden], norm=True)
        self.fine_down = nn.ModuleList(MLPMessagePassing(hidden) for _ in range(fine_blocks))
        self.coarse = nn.ModuleList(MLPMessagePassing(hidden) for _ in range(coarse_blocks))
        self.fine_up = nn.ModuleList(MLPMessagePassing(hidden) for _ in range(fine_blocks))
        self.decoder = _mlp([hidden, hidden, 3])
        _small_init_(self.decoder[-1])

    @staticmethod
    def _edge_in(x: Tensor, rest: Tensor, edge_index: Tensor) -> Tensor:
        """``[B, E, 8]``: current and rest relative positions and lengths."""
        src, dst = edge_index
        d = x[:, dst] - x[:, src]
        d0 = (rest[dst] - rest[src]).expand_as(d)
        return torch.cat([d, d.norm(dim=-1, keepdim=True), d0, d0.norm(dim=-1, keepdim=True)], -1)

    def forward(self, scene: GarmentScene, coarse: CoarseLevel, x_prev: Tensor, x_curr: Tensor,
                body: Tensor) -> Tensor:
        """Accelerations ``[B, V, 3]`` (m/s^2).

        Args:
            x_prev, x_curr: ``[B, V, 3]`` garment at ``t-2`` and ``t-1``.
            body: ``[B, Vb, 3]`` body vertices at ``t``.
        """
        V = scene.num_vertices
        for name, t in (("x_prev", x_prev), ("x_curr", x_curr)):
            if t.dim() != 3 or t.shape[1:] != (V, 3):
                raise ValueError(f"`{name}`: expected [B, {V}, 3], got {tuple(t.shape)}")
        if x_prev.shape != x_curr.shape:
            raise ValueError("`x_prev`/`x_curr`: shapes differ")
        B = x_curr.shape[0]
        if body.dim() != 3 or body.shape[0] != B or body.shape[2] != 3:
            raise ValueError(f"`body`: expected [{B}, Vb, 3], got {tuple(body.shape)}")
        if coarse.assign.shape != (V,):
            raise ValueError(f"`coarse`: built for {coarse.assign.shape[0]} vertices, scene has {V}")
        dtype = self.decoder[-1].weight.dtype
        x_prev, x_curr, body = x_prev.to(dtype), x_curr.to(dtype), body.to(dtype)
        rest = scene.rest_pos.to(dtype)
        vel = (x_curr - x_prev) / self.dt
        normal = vertex_normals(x_curr, scene.faces)
        nearest = torch.cdist(x_curr, body).argmin(-1)  # [B, V]
        to_body = torch.gather(body, 1, nearest.unsqueeze(-1).expand(B, V, 3)) - x_curr
        pinned = scene.pinned_mask().to(dtype).view(1, V, 1).expand(B, V, 1)
        node = torch.cat([vel, normal, pinned, to_body, to_body.norm(dim=-1, keepdim=True)], -1)

        h = self.node_enc(node).reshape(B * V, -1)
        ei = _batched_graph(scene.edge_index, B, V)
        e = self.edge_enc(self._edge_in(x_curr, rest, scene.edge_index))
        e = e.reshape(-1, e.shape[-1])  # copy-major, like `ei`
        for block in self.fine_down:
            h, e = block(h, ei, e)
        Z = coarse.num_nodes
        cluster = (coarse.assign.view(1, V) + Z * torch.arange(B).view(B, 1)).reshape(-1)
        hc = scatter(h, cluster, dim=0, dim_size=B * Z, reduce="mean")
        lm = coarse.landmarks
        eic = _batched_graph(coarse.edge_index, B, Z)
        ec = self.coarse_edge_enc(self._edge_in(x_curr[:, lm], rest[lm], coarse.edge_index))
        ec = ec.reshape(-1, ec.shape[-1])
        for block in self.coarse:
            hc, ec = block(hc, eic, ec)
        h = h + hc[cluster]
        for block in self.fine_up:
            h, e = block(h, ei, e)
        return self.decoder(h).reshape(B, V, 3)

    def step(self, scene: GarmentScene, coarse: CoarseLevel, x_prev: Tensor, x_curr: Tensor,
             body: Tensor, pinned_target: Optional[Tensor] = None) -> Tensor:
        """Next state ``[B, V, 3]``: ``2 x_curr - x_prev + a dt^2``; pinned vertices are
        set to ``pinned_target [B, V, 3]`` when given (else kept at ``x_curr``)."""
        a = self(scene, coarse, x_prev, x_curr, body)
        x_next = 2 * x_curr.to(a.dtype) - x_prev.to(a.dtype) + a * self.dt ** 2
        if scene.pinned is not None:
            target = x_curr.to(a.dtype) if pinned_target is None else pinned_target.to(a.dtype)
            x_next = torch.where(scene.pinned_mask().view(1, -1, 1), target, x_next)
        return x_next

    def rollout(self, scene: GarmentScene, coarse: CoarseLevel, x0: Tensor, x1: Tensor,
                body_frames: Tensor, pinned_targets: Optional[Tensor] = None) -> Tensor:
        """Autoregressive rollout: ``x0, x1 [V, 3]`` (frames 0 and 1), ``body_frames
        [T, Vb, 3]`` -> ``[T, V, 3]`` whose first two frames are ``x0, x1``.

        ``pinned_targets [T, V, 3]`` (e.g. the LBS positions) drive pinned vertices.
        Differentiable; wrap in ``torch.no_grad()`` for inference.
        """
        V = scene.num_vertices
        if x0.shape != (V, 3) or x1.shape != (V, 3):
            raise ValueError(f"`x0`/`x1`: expected [{V}, 3], got {tuple(x0.shape)}, {tuple(x1.shape)}")
        if body_frames.dim() != 3 or body_frames.shape[0] < 2 or body_frames.shape[2] != 3:
            raise ValueError(f"`body_frames`: expected [T >= 2, Vb, 3], got {tuple(body_frames.shape)}")
        T = body_frames.shape[0]
        if pinned_targets is not None and pinned_targets.shape != (T, V, 3):
            raise ValueError(f"`pinned_targets`: expected [{T}, {V}, 3], got "
                             f"{tuple(pinned_targets.shape)}")
        dtype = self.decoder[-1].weight.dtype
        out = [x0.to(dtype), x1.to(dtype)]
        for t in range(2, T):
            target = None if pinned_targets is None else pinned_targets[t:t + 1]
            out.append(self.step(scene, coarse, out[-2].unsqueeze(0), out[-1].unsqueeze(0),
                                 body_frames[t:t + 1], target)[0])
        return torch.stack(out)


# --------------------------------------------------------------------------- NCS
class NCSStyle(nn.Module):
    """NCS-style garment-specific network (Bertiche, Madadi & Escalera, *Neural Cloth
    Simulation*, SIGGRAPH Asia 2022).

    One model per garment (fixed vertex count and order): an MLP reads the pose of the
    current and the ``history`` previous frames (joint rotation matrices) and outputs
    per-vertex offsets in the garment's rest (canonical) space, which are then skinned
    with the scene's LBS weights, so the garment follows the body and the network only
    learns the pose- and motion-dependent deformation.  Trained unsupervised, with
    physics losses only (``GarTransLoss`` physics terms; inertia over consecutive
    frames for the dynamics).

    Simplified from NCS: no separate static/dynamic encoders nor learned blend-shape
    basis (a direct linear output layer instead), no learned skinning weights, the root
    (global) orientation is left out of the input (the offsets do not depend on
    heading; NCS feeds the root's motion to its dynamic encoder), and the motion
    history is a fixed number of frames instead of a recurrent encoder.

    Args:
        num_vertices: ``V`` of the garment this model is trained for.
        num_joints: ``S``.
        history: previous frames in the input (1 = current + previous).
        hidden: MLP width.
    """

    def __init__(self, num_vertices: int, num_joints: int, history: int = 1,
                 hidden: int = 128) -> None:
        super().__init__()
        if num_vertices < 1:
            raise ValueError(f"`num_vertices`: must be positive, got {num_vertices}")
        if num_joints < 2:
            raise ValueError(f"`num_joints`: needs a root and at least one joint, got {num_joints}")
        if history < 0:
            raise ValueError(f"`history`: must be non-negative, got {history}")
        if hidden < 1:
            raise ValueError(f"`hidden`: must be positive, got {hidden}")
        self.num_vertices, self.num_joints, self.history = num_vertices, num_joints, history
        self.mlp = _mlp([(history + 1) * (num_joints - 1) * 9, hidden, hidden, num_vertices * 3],
                        act=nn.Tanh)
        _small_init_(self.mlp[-1])

    def offsets(self, rotations: Tensor) -> Tensor:
        """``rotations [B, history + 1, S, 3]`` (last = current frame) -> canonical
        offsets ``[B, V, 3]``."""
        H = self.history + 1
        if rotations.dim() != 4 or rotations.shape[1:] != (H, self.num_joints, 3):
            raise ValueError(f"`rotations`: expected [B, {H}, {self.num_joints}, 3] axis-angle, "
                             f"got {tuple(rotations.shape)}")
        dtype = self.mlp[0].weight.dtype
        R = axis_angle_to_matrix(rotations[:, :, 1:].to(dtype))
        return self.mlp(R.reshape(R.shape[0], -1)).reshape(-1, self.num_vertices, 3)

    def forward(self, scene: GarmentScene, rotations: Tensor,
                translation: Optional[Tensor] = None) -> Tensor:
        """``rotations [B, history + 1, S, 3]``, ``translation [B, 3]`` (current frame)
        -> positions ``[B, V, 3]``."""
        if scene.num_vertices != self.num_vertices:
            raise ValueError(f"`scene`: has {scene.num_vertices} vertices; this garment-specific "
                             f"model was built for {self.num_vertices}")
        d = self.offsets(rotations)
        return skin(scene, rotations[:, -1], translation, d.to(scene.rest_pos.dtype))[0]
