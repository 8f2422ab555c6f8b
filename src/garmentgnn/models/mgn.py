"""MGN-style learned simulator: MeshGraphNets' encode-process-decode on the toolkit's layers.

MeshGraphNets (Pfaff, Fortunato, Sanchez-Gonzalez & Battaglia, *Learning Mesh-Based
Simulation with Graph Networks*, ICLR 2021) carries the garment's state from frame to
frame: from the two latest garment states ``x_{t-2}, x_{t-1}`` and the body it predicts an
acceleration ``a``, and the next state is ``x_t = 2 x_{t-1} - x_{t-2} + a`` (a in metres
per frame squared, so the model is tied to the frame rate it learned at, ``fps``).
:class:`MGNStyle` is that network, with

* **encode**: node inputs (the velocity ``x_{t-1} - x_{t-2}``, the LBS garment's motion
  ``l_t - l_{t-1}`` and the offset from it ``x_{t-1} - l_{t-1}``, all in the body's
  local frame -- the root joint's rotation at ``t-1`` -- plus the pinned flag and the
  fabric, :func:`~garmentgnn.physics.material_features`), mesh-edge inputs (current
  relative position in the local frame and length, rest relative position and length) and
  **body edges**: each garment vertex to its ``body_k`` nearest body vertices within
  ``body_radius`` (MeshGraphNets' world edges, HOOD's body edges), with the offset to the
  body at ``t`` in the local frame, its length and the body's motion ``b_t - b_{t-1}``.
  Body edges are encoded and summed into their garment vertex, once (the default) or
  updated in every block as HOOD and MeshGraphNets do (``body_blocks``).
  With ``coarse_levels``, the mesh graph's coarse levels
  (:func:`~garmentgnn.geometry.coarse_levels`: each a maximal independent set of the
  level below, joined within three of its edges; built once per batch or sequence from
  the rest mesh) carry edges with the mesh edges' inputs, so that a few blocks reach
  across the garment, as HOOD's hierarchy does.
  All inputs are normalised by running statistics (:class:`RunningNormalizer`);
* **process** and **decode**: MeshGraphNets' network,
  :class:`~garmentgnn.models.EncodeProcessDecode` (``network``), with ``layers`` blocks of
  a :mod:`garmentgnn.nn` layer (``layer``: SATConv by default; Eqs. 5-6) to the
  normalised local-frame acceleration; :meth:`acceleration` undoes the normalisation
  (running statistics of the training targets) and the frame.

**The anchor.**  The garment's state is read as its offset from the LBS garment (an
input), and :meth:`integrate` can bound how far a rollout drifts from it: the offset
decays by ``anchor_decay`` a frame (``x_t = l_t + (1 - anchor_decay) (x~_t - l_t)``, with
``x~_t`` the free update) and its length is clipped to ``anchor_clip`` metres.  The loss
asks the network for the acceleration that lands on the target through the same
integration (:meth:`target_acceleration`, its exact inverse), so the decay changes what
the model learns to predict, not what it can reach.

**The projection.**  After each step (:meth:`step`, :meth:`project`) the toolkit's strain
limit shortens stretched edges (``strain_limit`` sweeps) and its collision projection
moves vertices inside each garment's own body ``collision_projection`` outside, as GarTrans's
post-steps do; on by default (the measurement: the class's arguments).  In eval mode the
strain limit gives way to an inextensible projection (``inextensible`` sweeps toward every
edge's rest length), too costly for training batches.

Pinned vertices follow the LBS garment.  Under ``torch.autocast`` (``--trainer.precision
bf16-mixed``) the kinematics, the inputs, their statistics, the acceleration and the
integration stay float32 (:func:`~garmentgnn.geometry.full_precision`: bfloat16 rounds a
position at 1 m to ~4 mm, the size of a mesh edge's change in a frame) and the encoders,
processor and decoder run in the low precision.  The model never reads the ground truth
itself: the training module (:class:`~garmentgnn.training.RolloutModule`) hands it the
states and the target frame of :meth:`loss`.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Optional, Tuple

import torch
from torch import Tensor, nn

from garmentgnn.body.lbs import forward_kinematics
from garmentgnn.geometry import full_precision
from garmentgnn.geometry.coarsen import coarse_levels as build_levels
from garmentgnn.geometry.measures import edge_lengths
from garmentgnn.geometry.mesh import unique_edges
from garmentgnn.models.blocks import Configurable, RunningNormalizer
from garmentgnn.models.encode_process_decode import EncodeProcessDecode
from garmentgnn.models.inputs import GarmentInputs
from garmentgnn.models.sequence import ChunkLayout, PostSteps
from garmentgnn.physics import COLLISION_MARGIN, MATERIAL_FEATURES

__all__ = ["MGNStyle", "SceneMotion"]


@dataclass
class SceneMotion:
    """What a step of :class:`MGNStyle` reads besides the garment states, for the ``N``
    garments of a :class:`GarmentInputs` over its ``T`` frames (computed once per batch
    or sequence by :meth:`MGNStyle.scene_motion`).

    Attributes:
        lbs: ``[T, V, 3]`` the rest garment skinned to each frame (Eq. 1).
        body: ``[T, N, Vb, 3]`` each garment's body per frame.
        frame: ``[T, V, 3, 3]`` the body's local frame per vertex (its root joint's
            world rotation).
        vertex_chunk: ``[V]`` the garment of each vertex.
        layout: the garments' :class:`~garmentgnn.models.sequence.ChunkLayout` (their
            padded ``[N, Vmax]`` layout).
        material: ``[V, K]`` the fabric of each vertex.
        pinned: ``[V]`` bool.
        strain_edges, strain_lengths: the unique mesh edges ``[E, 2]`` and their rest
            lengths ``[E]`` (for the strain limit; ``None`` without it).
        coarse_edges: the edges ``[2, E_l]`` of each coarse level (none without them).
    """

    lbs: Tensor
    body: Tensor
    frame: Tensor
    vertex_chunk: Tensor
    layout: ChunkLayout
    material: Tensor
    pinned: Tensor
    strain_edges: Optional[Tensor] = None
    strain_lengths: Optional[Tensor] = None
    coarse_edges: Tuple[Tensor, ...] = ()

    @property
    def num_frames(self) -> int:
        return int(self.lbs.shape[0])


def _local(frame: Tensor, v: Tensor) -> Tensor:
    """``R^T v`` per row: ``frame [..., 3, 3]``, ``v [..., 3]``."""
    return (v.unsqueeze(-2) @ frame).squeeze(-2)


def _edge_inputs(xl: Tensor, rest: Tensor, edge_index: Tensor) -> Tensor:
    """Edge inputs ``[E, 8]``: the current relative position (``xl``: local frame) and its
    length, the rest relative position and its length."""
    src, dst = edge_index
    d = xl[src] - xl[dst]
    d0 = rest[src] - rest[dst]
    return torch.cat([d, d.norm(dim=1, keepdim=True), d0, d0.norm(dim=1, keepdim=True)], 1)


class MGNStyle(Configurable, PostSteps, nn.Module):
    """MGN-style learned simulator (module doc): ``x_t = 2 x_{t-1} - x_{t-2} + a``.

    Args:
        hidden: latent width of every MLP and layer.
        layers: processor blocks (MeshGraphNets: 15).
        layer: the :mod:`garmentgnn.nn` layer of each block (``"sat"``, ``"gt"``,
            ``"gt_edge"``, ``"structure_aware"``, ``"gat"``).
        heads: attention heads of each layer (``hidden`` must be a multiple).
        body_radius: body edges reach body vertices within this distance (m).
        body_k: body edges per garment vertex (its nearest body vertices).
        fps: the frame rate the accelerations are learned at (frames per second).
        norm_updates: training calls that update the input and target statistics
            (MeshGraphNets: the first 1,000 steps).
        body_blocks: update the body edges in every processor block (HOOD,
            MeshGraphNets); else they are encoded once.
        anchor_decay: the share of the offset from the LBS garment that a step takes
            away (0: none; module doc, "The anchor").
        anchor_clip: the longest offset from the LBS garment a step leaves (m; ``None``:
            no clip).
        strain_limit: sweeps of the strain limit after each step (Provot's,
            :func:`~garmentgnn.geometry.project_edge_lengths` on stretched edges; 0: none).
        inextensible: in eval mode (validation, test, ``predict``), the strain limit is
            replaced by this many sweeps that pull every edge toward its rest length,
            compressed ones too, Chebyshev-accelerated
            (:meth:`~garmentgnn.models.sequence.PostSteps.strain_sweeps`; 0: the strain
            limit in every mode).  Training keeps the cheaper strain limit: 100 sweeps
            over a batch of 16 garments a frame would cost more than the step.  On the
            107 `learn` test sequences it took the committed model from 5.3 % to 1.7 %
            E_len, from 0.067 to 0.044 E_curv (LBS: 5.0 % and 0.046) and from 0.668x to
            0.642x LBS's E_dist (docs/results/mgn_learn/inextensible).
        coarse_levels: coarse levels of the mesh graph the processor also runs on
            (module doc; every second block; 0: the mesh graph alone).
        collision_projection: after each step, vertices closer than this to the body (or
            inside it) are moved this far outside (:func:`~garmentgnn.geometry.push_outside`;
            ``None``: no projection).  Both on by default: on 24 `learn` test sequences
            they took the committed model's rollouts from 0.949x to 0.904x LBS's E_dist
            (lower on 23 of 24), its stretch from 11.0 % to 8.2 % and the vertices inside
            the body from 3.0 % to 0.001 % (docs/results/mgn_learn/projection).
    """

    NODE_IN = 10 + len(MATERIAL_FEATURES)
    EDGE_IN = 8
    BODY_IN = 7

    def __init__(self, hidden: int = 64, layers: int = 8, layer: str = "sat", heads: int = 4,
                 body_radius: float = 0.05, body_k: int = 4, fps: float = 30.0,
                 norm_updates: int = 1000, body_blocks: bool = False,
                 anchor_decay: float = 0.0, anchor_clip: Optional[float] = None,
                 strain_limit: int = 10, inextensible: int = 100,
                 collision_projection: Optional[float] = COLLISION_MARGIN,
                 coarse_levels: int = 0) -> None:
        super().__init__()
        if not isinstance(body_k, int) or isinstance(body_k, bool) or body_k < 1:
            raise ValueError(f"`body_k`: expected a positive int, got {body_k!r}")
        if not body_radius > 0:
            raise ValueError(f"`body_radius`: expected metres > 0, got {body_radius!r}")
        if not fps > 0:
            raise ValueError(f"`fps`: expected frames per second > 0, got {fps!r}")
        if not (isinstance(anchor_decay, (int, float)) and 0 <= anchor_decay < 1):
            raise ValueError(f"`anchor_decay`: expected a share in [0, 1), got "
                             f"{anchor_decay!r}")
        if anchor_clip is not None and not (isinstance(anchor_clip, (int, float))
                                            and anchor_clip > 0):
            raise ValueError(f"`anchor_clip`: expected metres > 0 or None, got "
                             f"{anchor_clip!r}")
        for name, sweeps in (("strain_limit", strain_limit), ("inextensible", inextensible)):
            if not isinstance(sweeps, int) or isinstance(sweeps, bool) or sweeps < 0:
                raise ValueError(f"`{name}`: expected sweeps >= 0, got {sweeps!r}")
        if collision_projection is not None and not (
                isinstance(collision_projection, (int, float)) and collision_projection >= 0):
            raise ValueError(f"`collision_projection`: expected metres >= 0 or None, got "
                             f"{collision_projection!r}")
        self.strain_limit, self.inextensible = strain_limit, inextensible
        self.collision_projection = (None if collision_projection is None
                                     else float(collision_projection))
        self.compile_search = False  # PostSteps: the face search eager (one frame a call)
        self.hidden, self.fps = hidden, float(fps)
        self.body_radius, self.body_k = float(body_radius), body_k
        self.anchor_decay = float(anchor_decay)
        self.anchor_clip = None if anchor_clip is None else float(anchor_clip)
        self.node_norm = RunningNormalizer(self.NODE_IN, norm_updates)
        self.edge_norm = RunningNormalizer(self.EDGE_IN, norm_updates)
        self.body_norm = RunningNormalizer(self.BODY_IN, norm_updates)
        #: statistics of the training targets (local-frame accelerations)
        self.target_norm = RunningNormalizer(3, norm_updates)
        self.network = EncodeProcessDecode(self.NODE_IN, self.EDGE_IN, 3, hidden=hidden,
                                           layers=layers, layer=layer, heads=heads,
                                           contact_in=self.BODY_IN, contact_blocks=body_blocks,
                                           levels=coarse_levels)
        self.coarse_levels = coarse_levels
        self.coarse_norms = nn.ModuleList(RunningNormalizer(self.EDGE_IN, norm_updates)
                                          for _ in range(coarse_levels))

    # -- what a step reads ---------------------------------------------------------------
    def scene_motion(self, scene: GarmentInputs) -> SceneMotion:
        """The LBS garment, bodies, local frames and fabric of ``scene``'s frames."""
        for key in ("body_pos", "material"):
            if key not in scene:
                fix = ("set it with garmentgnn.physics.material_features(MATERIALS[name])"
                       if key == "material" else "build the inputs with a body")
                raise ValueError(f"`scene.{key}`: missing; the MGN-style model reads it ({fix})")
        layout = ChunkLayout(scene)
        N, T = layout.N, layout.B
        rot = layout.rotations[:, :, -1]  # [N, T, S, 3]
        tr = layout.translation[:, :, -1]  # [N, T, 3]
        with full_precision(scene.rest_pos) as up:  # float32 under autocast
            A, _ = forward_kinematics(up(rot.reshape(N * T, *rot.shape[2:])),
                                      up(layout.rest_joints.repeat_interleave(T, 0)),
                                      layout.parents, up(tr.reshape(N * T, 3)))
        A = A.view(N, T, *A.shape[1:])
        W = scene.skin_weights.unsqueeze(0).expand(T, -1, -1)
        lbs, _ = layout.skin(W, A, scene.rest_pos)
        root = A[:, :, 0, :3, :3]  # [N, T, 3, 3] the root joint's world rotation
        chunk = scene.vertex_chunk()
        frame = root.transpose(0, 1)[:, chunk]  # [T, V, 3, 3]
        body = scene.body_pos.view(T, N, -1, 3)
        material = scene.material.reshape(N, -1).to(lbs.dtype)[chunk]
        edges = lengths = None
        if self.strain_limit or self.inextensible:
            edges = unique_edges(scene.faces, scene.num_vertices).edges
            lengths = edge_lengths(scene.rest_pos, edges)
        coarse = tuple(build_levels(scene.edge_index, scene.num_vertices, self.coarse_levels,
                                    batch=chunk)) if self.coarse_levels else ()
        return SceneMotion(lbs=lbs, body=body, frame=frame, vertex_chunk=chunk, layout=layout,
                           material=material, pinned=scene.pinned_mask(),
                           strain_edges=edges, strain_lengths=lengths, coarse_edges=coarse)

    def body_edges(self, motion: SceneMotion, x: Tensor, t: int) -> Tuple[Tensor, Tensor]:
        """``(garment vertex [Eb], body vertex [Eb] of its own garment's body at ``t``)``:
        each vertex's ``body_k`` nearest body vertices within ``body_radius`` of ``x``."""
        body = motion.body[t]  # [N, Vb, 3]
        Vb = body.shape[1]
        k = min(self.body_k, Vb)
        with torch.no_grad():
            layout = motion.layout
            if layout.N == 1:
                d, j = torch.cdist(x.unsqueeze(0), body).topk(k, -1, largest=False)
                d, j = d[0], j[0]
            else:  # each garment against its own body, in the padded layout
                d, j = torch.cdist(layout.to_padded(x), body).topk(k, -1, largest=False)
                d, j = layout.from_padded(d), layout.from_padded(j)
            keep = d < self.body_radius
            src = torch.arange(x.shape[0], device=x.device).unsqueeze(1).expand_as(j)[keep]
            dst = (j + (motion.vertex_chunk * Vb).unsqueeze(1))[keep]
        return src, dst

    # -- the network -------------------------------------------------------------------------
    def forward(self, scene: GarmentInputs, motion: SceneMotion, t: int, x_prev: Tensor,
                x_curr: Tensor) -> Tensor:
        """The normalised local-frame acceleration ``[V, 3]`` that takes ``x_prev``
        (``x_{t-2}``) and ``x_curr`` (``x_{t-1}``) to frame ``t`` of ``motion``
        (:meth:`acceleration` turns it into metres per frame squared)."""
        V = scene.num_vertices
        if not 1 <= t < motion.num_frames:
            raise ValueError(f"`t`: expected a frame in [1, {motion.num_frames}), got {t}")
        for name, s in (("x_prev", x_prev), ("x_curr", x_curr)):
            if s.shape != (V, 3):
                raise ValueError(f"`{name}`: expected [{V}, 3], got {tuple(s.shape)}")
        with full_precision(x_curr) as up:  # the inputs in float32 under autocast
            node, edge, bedge, bs = self.inputs(scene, motion, t, up(x_prev), up(x_curr))
            node, edge, bedge = self.node_norm(node), self.edge_norm(edge), self.body_norm(bedge)
            coarse = []
            if motion.coarse_edges:  # the coarse edges read the mesh edges' inputs
                xl = _local(motion.frame[t - 1], up(x_curr))
                coarse = [(ei, norm(_edge_inputs(xl, scene.rest_pos, ei)))
                          for ei, norm in zip(motion.coarse_edges, self.coarse_norms)]
        return self.network(node, scene.edge_index, edge, bedge, bs, coarse)

    def inputs(self, scene: GarmentInputs, motion: SceneMotion, t: int, x_prev: Tensor,
               x_curr: Tensor) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
        """The unnormalised inputs of frame ``t``: node ``[V, NODE_IN]``, mesh-edge ``[E,
        EDGE_IN]`` and body-edge ``[Eb, BODY_IN]`` features, and each body edge's garment
        vertex ``[Eb]`` (module doc)."""
        R = motion.frame[t - 1]  # [V, 3, 3]
        lbs_prev, lbs_next = motion.lbs[t - 1], motion.lbs[t]
        # node inputs (local frame): velocity, the LBS garment's motion and the offset from it
        node = torch.cat([_local(R, x_curr - x_prev), _local(R, lbs_next - lbs_prev),
                          _local(R, x_curr - lbs_prev),
                          motion.pinned.to(x_curr.dtype).unsqueeze(1), motion.material], 1)
        edge = _edge_inputs(_local(R, x_curr), scene.rest_pos, scene.edge_index)
        # body edges: offset to the body at t, its length, the body's motion
        bs, bd = self.body_edges(motion, x_curr, t)
        body_t = motion.body[t].reshape(-1, 3)
        body_prev = motion.body[t - 1].reshape(-1, 3)
        Rb = R[bs]
        off = _local(Rb, body_t[bd] - x_curr[bs])
        bedge = torch.cat([off, off.norm(dim=1, keepdim=True),
                           _local(Rb, body_t[bd] - body_prev[bd])], 1)
        return node, edge, bedge, bs

    def acceleration(self, out: Tensor, motion: SceneMotion, t: int) -> Tensor:
        """The network's output ``out [V, 3]`` for frame ``t`` in metres per frame
        squared, world frame."""
        with full_precision(out) as up:  # float32 under autocast
            out = up(out)
            mean, std = self.target_norm.mean_std()
            a_local = out * std.to(out.dtype) + mean.to(out.dtype)
            return (motion.frame[t - 1] @ a_local.unsqueeze(-1)).squeeze(-1)

    def normalized_target(self, a: Tensor, motion: SceneMotion, t: int) -> Tensor:
        """A world-frame acceleration ``a [V, 3]`` of frame ``t`` as the network's output
        would give it (the target statistics are updated in training mode)."""
        with full_precision(a) as up:  # float32 under autocast
            return self.target_norm(_local(motion.frame[t - 1], up(a)))

    # -- the update equation and its inverse ----------------------------------------------
    def integrate(self, motion: SceneMotion, t: int, x_prev: Tensor, x_curr: Tensor,
                  a: Tensor) -> Tensor:
        """Frame ``t`` ``[V, 3]`` from ``x_{t-2}, x_{t-1}`` and the acceleration ``a``
        (metres per frame squared): ``x~_t = 2 x_{t-1} - x_{t-2} + a``, its offset from
        the LBS garment ``l_t`` decayed by ``anchor_decay`` and clipped to
        ``anchor_clip``; pinned vertices on ``l_t``."""
        lbs = motion.lbs[t]
        x = 2 * x_curr - x_prev + a
        if self.anchor_decay or self.anchor_clip is not None:
            off = (1.0 - self.anchor_decay) * (x - lbs)
            if self.anchor_clip is not None:
                n = off.norm(dim=1, keepdim=True)
                off = off * (self.anchor_clip / n.clamp_min(self.anchor_clip))
            x = lbs + off
        return torch.where(motion.pinned.unsqueeze(1), lbs, x)

    def target_acceleration(self, motion: SceneMotion, t: int, x_prev: Tensor,
                            x_curr: Tensor, x_next: Tensor) -> Tensor:
        """The acceleration that :meth:`integrate` takes to ``x_next`` (its inverse; the
        clip is not inverted: a target beyond it asks for the unclipped step)."""
        lbs = motion.lbs[t]
        return lbs + (x_next - lbs) / (1.0 - self.anchor_decay) - (2 * x_curr - x_prev)

    def step(self, scene: GarmentInputs, motion: SceneMotion, t: int, x_prev: Tensor,
             x_curr: Tensor) -> Tensor:
        """Frame ``t`` ``[V, 3]``: :meth:`integrate` of the network's acceleration, then
        :meth:`project`."""
        a = self.acceleration(self(scene, motion, t, x_prev, x_curr), motion, t)
        return self.project(scene, motion, t, self.integrate(motion, t, x_prev, x_curr, a))

    def project(self, scene: GarmentInputs, motion: SceneMotion, t: int, x: Tensor) -> Tensor:
        """Frame ``t`` after the strain limit (``strain_limit`` sweeps over the stretched
        edges; in eval mode, ``inextensible`` sweeps over every edge) and the collision
        projection against each garment's own body (``collision_projection``;
        :class:`~garmentgnn.models.sequence.PostSteps`, as GarTrans's), pinned vertices
        back on LBS; ``x`` itself without them."""
        if not self.strain_sweeps()[0] and self.collision_projection is None:
            return x
        frame = copy.copy(scene)  # GarTrans's post-steps on frame t alone
        frame.body_pos = motion.body[t].reshape(1, -1, 3)
        x = self.post_steps(frame, motion, x.unsqueeze(0), motion.layout)[0]
        return torch.where(motion.pinned.unsqueeze(1), motion.lbs[t], x)

    def loss(self, scene: GarmentInputs, motion: SceneMotion, t: int, x_prev: Tensor,
             x_curr: Tensor, x_next: Tensor, weight: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
        """MeshGraphNets' loss of one step: the squared error of the normalised
        local-frame acceleration against the one that lands on ``x_next``, averaged over
        the vertices with their ``weight [V]``.  Returns ``(loss, the predicted frame t
        as :meth:`step` gives it (detached, projected), its mean distance to x_next in
        metres)``."""
        out = self(scene, motion, t, x_prev, x_curr)
        want = self.normalized_target(
            self.target_acceleration(motion, t, x_prev, x_curr, x_next), motion, t)
        w = weight.to(out.dtype)
        total = w.sum().clamp_min(1.0)
        loss = (((out - want) ** 2).sum(1) * w).sum() / total
        with torch.no_grad():
            x = self.project(scene, motion, t, self.integrate(
                motion, t, x_prev, x_curr, self.acceleration(out.detach(), motion, t)))
            err = ((x - x_next).norm(dim=1) * w).sum() / total
        return loss, x, err

    def rollout(self, scene: GarmentInputs, x0: Tensor, x1: Tensor,
                motion: Optional[SceneMotion] = None) -> Tensor:
        """The garment ``[T, V, 3]`` over every frame of ``scene``, rolled out from its
        states at frames 0 and 1 (``x0, x1 [V, 3]``, returned as the first two frames).
        Wrap in ``torch.no_grad()`` for inference."""
        motion = self.scene_motion(scene) if motion is None else motion
        T, V = motion.num_frames, scene.num_vertices
        if T < 2:
            raise ValueError(f"`scene`: a rollout needs at least 2 frames, got {T}")
        if x0.shape != (V, 3) or x1.shape != (V, 3):
            raise ValueError(f"`x0`/`x1`: expected [{V}, 3], got {tuple(x0.shape)}, "
                             f"{tuple(x1.shape)}")
        out = [x0, x1]
        for t in range(2, T):
            out.append(self.step(scene, motion, t, out[-2], out[-1]))
        return torch.stack(out)
