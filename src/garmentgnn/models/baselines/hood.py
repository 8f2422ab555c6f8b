"""HOOD-style baseline: hierarchical message passing predicting accelerations."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np
import torch
from torch import Tensor, nn
from torch_geometric.nn.conv import MessagePassing
from torch_geometric.utils import scatter

from garmentgnn.geometry import farthest_point_sampling, vertex_normals, full_precision
from garmentgnn.models.baselines.common import small_init_
from garmentgnn.models.blocks import Configurable, RunningNormalizer, batch_edges, mlp
from garmentgnn.models.inputs import GarmentInputs

__all__ = ["CoarseLevel", "HOODStyle", "MLPMessagePassing"]


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
        device = rest_pos.device  # the sampling runs on the CPU (numpy, scipy)
        idx, dist = farthest_point_sampling(rest_pos.detach().cpu().double().numpy(),
                                            faces.cpu().numpy(), Z, seed=seed)
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
        return cls(landmarks=idx.long().to(device), assign=assign.long().to(device),
                   edge_index=ei.to(device))

    @property
    def num_nodes(self) -> int:
        return self.landmarks.shape[0]


def _mlp_ln(sizes: Sequence[int]) -> nn.Sequential:
    """An ELU MLP ending in ``LayerNorm`` (MeshGraphNets' encoder and block MLPs)."""
    return mlp(sizes, nn.ELU(), last_act=False).append(nn.LayerNorm(sizes[-1]))


class MLPMessagePassing(MessagePassing):
    """One MeshGraphNets-style block: ``e' = e + f_e([h_i, h_j, e])``,
    ``h' = h + f_v([h, sum_j e'_ji])`` (residual MLPs with LayerNorm)."""

    def __init__(self, hidden: int) -> None:
        super().__init__(aggr="sum")
        self.edge_mlp = _mlp_ln([3 * hidden, hidden, hidden])
        self.node_mlp = _mlp_ln([2 * hidden, hidden, hidden])

    def forward(self, h: Tensor, edge_index: Tensor, e: Tensor) -> Tuple[Tensor, Tensor]:
        src, dst = edge_index
        e = e + self.edge_mlp(torch.cat([h[dst], h[src], e], -1))
        agg = self.propagate(edge_index, e=e, size=(h.shape[0], h.shape[0]))
        return h + self.node_mlp(torch.cat([h, agg], -1)), e

    def message(self, e: Tensor) -> Tensor:  # noqa: D102 - the edge state is the message
        return e


class HOODStyle(Configurable, nn.Module):
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
    body-garment edges, no material parameters as inputs; the input normalisation of
    HOOD and MeshGraphNets (running statistics of the node and edge inputs) is optional.

    Args:
        hidden: width of every MLP.
        fine_blocks: message-passing blocks before and after the coarse level (each).
        coarse_blocks: blocks on the coarse level.
        dt: frame time step (s).
        normalize: normalise the node, edge and coarse-edge inputs by running statistics
            accumulated in training (:class:`~garmentgnn.models.blocks.RunningNormalizer`).
        accel_scale: the decoder's output unit in m/s^2 (the decoder starts near 0, and
            holding cloth against gravity takes about 10 m/s^2).
    """

    NODE_IN = 11
    EDGE_IN = 8

    def __init__(self, hidden: int = 64, fine_blocks: int = 1, coarse_blocks: int = 2,
                 dt: float = 1.0 / 30.0, normalize: bool = False,
                 accel_scale: float = 1.0) -> None:
        super().__init__()
        if hidden < 1:
            raise ValueError(f"`hidden`: must be positive, got {hidden}")
        if fine_blocks < 1 or coarse_blocks < 1:
            raise ValueError("`fine_blocks`/`coarse_blocks`: must be positive")
        if not dt > 0:
            raise ValueError(f"`dt`: must be positive, got {dt}")
        if not accel_scale > 0:
            raise ValueError(f"`accel_scale`: must be positive (m/s^2), got {accel_scale}")
        self.dt = float(dt)
        self.accel_scale = float(accel_scale)
        self.normalize = bool(normalize)
        if self.normalize:
            self.node_norm = RunningNormalizer(self.NODE_IN)
            self.edge_norm = RunningNormalizer(self.EDGE_IN)
            self.coarse_edge_norm = RunningNormalizer(self.EDGE_IN)
        self.node_enc = _mlp_ln([self.NODE_IN, hidden, hidden])
        self.edge_enc = _mlp_ln([self.EDGE_IN, hidden, hidden])
        self.coarse_edge_enc = _mlp_ln([self.EDGE_IN, hidden, hidden])
        self.fine_down = nn.ModuleList(MLPMessagePassing(hidden) for _ in range(fine_blocks))
        self.coarse = nn.ModuleList(MLPMessagePassing(hidden) for _ in range(coarse_blocks))
        self.fine_up = nn.ModuleList(MLPMessagePassing(hidden) for _ in range(fine_blocks))
        self.decoder = mlp([hidden, hidden, 3], nn.ELU(), last_act=False)
        small_init_(self.decoder[-1])

    @staticmethod
    def _edge_in(x: Tensor, rest: Tensor, edge_index: Tensor) -> Tensor:
        """``[B, E, 8]``: current and rest relative positions and lengths."""
        src, dst = edge_index
        d = x[:, dst] - x[:, src]
        d0 = (rest[dst] - rest[src]).expand_as(d)
        return torch.cat([d, d.norm(dim=-1, keepdim=True), d0, d0.norm(dim=-1, keepdim=True)], -1)

    def forward(self, scene: GarmentInputs, coarse: CoarseLevel, x_prev: Tensor, x_curr: Tensor,
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
            raise ValueError(f"`coarse`: built for {coarse.assign.shape[0]} vertices, scene has "
                             f"{V}")
        dtype = self.decoder[-1].weight.dtype
        x_prev, x_curr, body = x_prev.to(dtype), x_curr.to(dtype), body.to(dtype)
        rest = scene.rest_pos.to(dtype)
        vel = (x_curr - x_prev) / self.dt
        normal = vertex_normals(x_curr, scene.faces)
        nearest = torch.cdist(x_curr, body).argmin(-1)  # [B, V]
        to_body = torch.gather(body, 1, nearest.unsqueeze(-1).expand(B, V, 3)) - x_curr
        pinned = scene.pinned_mask().to(dtype).view(1, V, 1).expand(B, V, 1)
        node = torch.cat([vel, normal, pinned, to_body, to_body.norm(dim=-1, keepdim=True)], -1)

        e_in = self._edge_in(x_curr, rest, scene.edge_index)
        lm = coarse.landmarks
        ec_in = self._edge_in(x_curr[:, lm], rest[lm], coarse.edge_index)
        if self.normalize:
            node, e_in = self.node_norm(node), self.edge_norm(e_in)
            ec_in = self.coarse_edge_norm(ec_in)
        h = self.node_enc(node).reshape(B * V, -1)
        ei = batch_edges(scene.edge_index, B, V)
        e = self.edge_enc(e_in)
        e = e.reshape(-1, e.shape[-1])  # copy-major, like `ei`
        for block in self.fine_down:
            h, e = block(h, ei, e)
        Z = coarse.num_nodes
        cluster = (coarse.assign.view(1, V)
                   + Z * torch.arange(B, device=h.device).view(B, 1)).reshape(-1)
        hc = scatter(h, cluster, dim=0, dim_size=B * Z, reduce="mean")
        eic = batch_edges(coarse.edge_index, B, Z)
        ec = self.coarse_edge_enc(ec_in)
        ec = ec.reshape(-1, ec.shape[-1])
        for block in self.coarse:
            hc, ec = block(hc, eic, ec)
        h = h + hc[cluster]
        for block in self.fine_up:
            h, e = block(h, ei, e)
        return self.decoder(h).reshape(B, V, 3) * self.accel_scale

    def step(self, scene: GarmentInputs, coarse: CoarseLevel, x_prev: Tensor, x_curr: Tensor,
             body: Tensor, pinned_target: Optional[Tensor] = None) -> Tensor:
        """Next state ``[B, V, 3]``: ``2 x_curr - x_prev + a dt^2``; pinned vertices are
        set to ``pinned_target [B, V, 3]`` when given (else kept at ``x_curr``)."""
        a = self(scene, coarse, x_prev, x_curr, body)
        with full_precision(x_curr) as up:  # the integration in float32 under autocast
            a = up(a)
            x_next = 2 * x_curr.to(a.dtype) - x_prev.to(a.dtype) + a * self.dt ** 2
            if scene.get("pinned") is not None:
                target = x_curr if pinned_target is None else pinned_target
                x_next = torch.where(scene.pinned_mask().view(1, -1, 1), target.to(a.dtype),
                                     x_next)
        return x_next

    def rollout(self, scene: GarmentInputs, coarse: CoarseLevel, x0: Tensor, x1: Tensor,
                body_frames: Tensor, pinned_targets: Optional[Tensor] = None) -> Tensor:
        """Autoregressive rollout: ``x0, x1 [V, 3]`` (frames 0 and 1), ``body_frames
        [T, Vb, 3]`` -> ``[T, V, 3]`` whose first two frames are ``x0, x1``.

        ``pinned_targets [T, V, 3]`` (e.g. the LBS positions) drive pinned vertices.
        Differentiable; wrap in ``torch.no_grad()`` for inference.
        """
        V = scene.num_vertices
        if x0.shape != (V, 3) or x1.shape != (V, 3):
            raise ValueError(f"`x0`/`x1`: expected [{V}, 3], got {tuple(x0.shape)}, "
                             f"{tuple(x1.shape)}")
        if body_frames.dim() != 3 or body_frames.shape[0] < 2 or body_frames.shape[2] != 3:
            raise ValueError(f"`body_frames`: expected [T >= 2, Vb, 3], got "
                             f"{tuple(body_frames.shape)}")
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
