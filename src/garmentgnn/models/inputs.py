"""The one model-input type: a garment on a body over a chunk of frames.

Every method (GarTrans, its ablations, the baselines, LBS), every loss, metric and the
bench reads a :class:`GarmentInputs`; it is built in one place: :func:`build_static`
makes the per-garment part once (graph, Nyström features, rest state, masses,
skinning weights, rest body), :func:`with_frames` adds the frames of a chunk.  The
training data module (:class:`garmentgnn.data.SequenceChunks`) and the bench's
in-memory sequences both go through these two functions.

:class:`GarmentInputs` is a PyG :class:`~torch_geometric.data.Data` (one graph: the
garment mesh, ``num_nodes = V``), so it moves with ``.to(device)``, reads as
``inp.gt`` or ``inp["gt"]`` and supports ``"gt" in inp``.

Keys (``V`` garment vertices, ``S`` joints, ``Vb`` body vertices, ``B`` frames,
``H = history + 1`` poses per frame):

* static: ``rest_pos [V, 3]``, ``faces [F, 3]``, ``face_uv [F, 3, 2]``, ``edge_index
  [2, E]`` (both directions, target-sorted), ``nystrom [V, k]``, ``rest``
  (:class:`~garmentgnn.physics.ClothRest`), ``mass [V]``, ``skin_weights [V, S]``,
  ``pinned [V]`` bool, ``rest_joints [S, 3]``, ``parents [S]``, ``body_joint_dists
  [Vb, S]``, ``body_faces [Fb, 3]``, optionally ``material [K]`` (the fabric,
  :func:`~garmentgnn.physics.material_features`: what a learned simulator reads);
* per frame: ``rotations [B, H, S, 3]``, ``translation [B, H, 3]`` (the poses of frames
  ``t - history .. t``; frame 0 repeated before the start), ``body_pos [B, Vb, 3]``
  (the posed body), ``frames [B]``, optionally ``gt [B, V, 3]`` (the simulated
  garment: absent where no ground truth exists), optionally ``converged
  [B]`` (bool: the frames whose simulation converged) and ``valid [B]`` (converged and the
  garment at most 1 cm inside the body: the only frames metrics and supervised losses
  read), and
  ``seq_id`` (str).

Batches: PyG's :class:`~torch_geometric.data.Batch` of ``N`` chunks of the same frame
count ``B`` (:meth:`GarmentInputs.collate`) is one garment graph, the disjoint union of
the ``N`` garments (``rest_pos [sum V, 3]``, ``faces``, ``edge_index`` offset as PyG
does; ``batch [sum V]`` names each vertex's chunk), whose per-frame vertex keys are
concatenated along the vertex axis (``gt``, ``body_pos``: ``[B, sum V, 3]``, ``[B, sum
Vb, 3]``) and whose per-chunk keys are stacked (``rotations [N, B, H, S, 3]``,
``translation [N, B, H, 3]``, ``frames``, ``converged``/``valid [N, B]``, ``rest_joints
[N, S, 3]``, ``parents [N, S]``, ``material [N, K]``); ``rest`` and ``seq_id`` become
lists.  Every chunk's body has the same vertex count (one body model).
"""
from __future__ import annotations

import copy
from typing import Any, List, Optional, Sequence, Tuple

import torch
from torch import Tensor
from torch_geometric.data import Batch, Data

from garmentgnn.body.body import Body
from garmentgnn.body.lbs import blend_transforms, forward_kinematics, linear_blend_skinning
from garmentgnn.geometry import faces_to_edge_index, geodesic_nystrom_features, full_precision
from garmentgnn.geometry.geodesic import NUM_LANDMARKS, NYSTROM_DIM
from garmentgnn.physics import ClothRest

#: the data sizes every entry point defaults to, defined here once: previous poses per
#: frame (``H = HISTORY + 1``) and the frames of a training chunk; the Nyström width and
#: landmarks of the garment's geodesic features are the geometry's
#: (:data:`~garmentgnn.geometry.geodesic.NYSTROM_DIM`,
#: :data:`~garmentgnn.geometry.geodesic.NUM_LANDMARKS`), handed on here
HISTORY = 3
CHUNK = 8

__all__ = ["CHUNK", "FRAME_KEYS", "HISTORY", "NUM_LANDMARKS", "NYSTROM_DIM", "GarmentInputs",
           "build_garment", "build_static", "check_history",
           "check_pose", "history_frames", "nystrom_features", "skin", "with_frames"]

#: the per-frame keys (indexed along the first dimension by :meth:`GarmentInputs.select`)
FRAME_KEYS = ("rotations", "translation", "gt", "body_pos", "frames", "converged", "valid")
#: keys a :class:`~torch_geometric.data.Batch` concatenates along the vertex axis (dim 1)
VERTEX_FRAME_KEYS = ("gt", "body_pos")
#: per-chunk keys a batch stacks (a new leading dimension)
STACKED_KEYS = ("rotations", "translation", "frames", "converged", "valid", "rest_joints",
                "parents", "material")
#: face-like keys: concatenated along dim 0 (PyG would use the last dimension)
FACE_KEYS = ("faces", "face_uv", "body_faces", "body_joint_dists")


class GarmentInputs(Data):
    """One garment on one body over ``B`` frames (see the module doc for the keys)."""

    # -- batching (PyG's ``Batch``) -------------------------------------------------
    def __cat_dim__(self, key: str, value: Any, *args: Any, **kwargs: Any) -> Any:
        if key in VERTEX_FRAME_KEYS:
            return 1
        if key in STACKED_KEYS:
            return None
        if key in FACE_KEYS:
            return 0
        return super().__cat_dim__(key, value, *args, **kwargs)

    def __inc__(self, key: str, value: Any, *args: Any, **kwargs: Any) -> Any:
        if key == "faces":
            return self.num_vertices
        if key == "body_faces":
            return self.body_pos.shape[-2] if "body_pos" in self else \
                self.body_joint_dists.shape[0]
        if key in FACE_KEYS or key in STACKED_KEYS:
            return 0
        return super().__inc__(key, value, *args, **kwargs)

    @staticmethod
    def collate(items: Sequence["GarmentInputs"]) -> "GarmentInputs":
        """``items`` (chunks of the same frame count) as one PyG ``Batch`` (module doc)."""
        items = list(items)
        if not items or not all(isinstance(i, GarmentInputs) for i in items):
            raise TypeError(f"`items`: expected a non-empty sequence of GarmentInputs, got "
                            f"{[type(i).__name__ for i in items]}")
        frames = {i.num_frames for i in items}
        if len(frames) > 1:
            raise ValueError(f"`items`: the chunks of a batch need the same frame count, got "
                             f"{sorted(frames)} (cut sequences into chunks of one length)")
        joints = {i.num_joints for i in items}
        if len(joints) > 1:
            raise ValueError(f"`items`: the chunks of a batch need one skeleton, got joint "
                             f"counts {sorted(joints)}")
        if any(not torch.equal(i.parents, items[0].parents) for i in items):
            raise ValueError("`items`: the chunks of a batch need one skeleton (equal "
                             "`parents`)")
        if "body_pos" in items[0]:
            bodies = {(int(i.body_pos.shape[-2]), int(i.body_faces.shape[0])) for i in items}
            if len(bodies) > 1:
                raise ValueError(f"`items`: the bodies of a batch need one mesh (one body "
                                 f"model), got (vertices, faces) {sorted(bodies)}")
        keys = [set(i.keys()) for i in items]
        if "pinned" in set.union(*keys):  # a garment without pinned vertices: none pinned
            items = [i if "pinned" in k else _with(i, pinned=i.pinned_mask())
                     for i, k in zip(items, keys)]
            keys = [k | {"pinned"} for k in keys]
        odd = set.union(*keys) - set.intersection(*keys)
        if odd:
            raise ValueError(f"`items`: keys {sorted(odd)} are in some chunks only; give "
                             f"every chunk of a batch the same keys")
        return Batch.from_data_list(items)

    @property
    def num_chunks(self) -> int:
        """``N``: the chunks of a batch (1 for one chunk)."""
        return int(self.num_graphs) if isinstance(self, Batch) else 1

    def vertex_chunk(self) -> Tensor:
        """``[V]`` the chunk of each vertex (zeros for one chunk)."""
        b = self.get("batch")
        return b if b is not None else torch.zeros(self.num_vertices, dtype=torch.long,
                                                  device=self.rest_pos.device)

    def chunks(self) -> List["GarmentInputs"]:
        """The chunks of a batch (``[self]`` for one chunk)."""
        return self.to_data_list() if isinstance(self, Batch) else [self]

    @property
    def num_vertices(self) -> int:
        return int(self.rest_pos.shape[0])

    @property
    def num_joints(self) -> int:
        return int(self.rest_joints.shape[-2])

    @property
    def num_frames(self) -> int:
        """``B``: frames per chunk."""
        if "rotations" not in self:
            return 0
        return int(self.rotations.shape[1 if isinstance(self, Batch) else 0])

    def to(self, device, *args: str, non_blocking: bool = False) -> "GarmentInputs":
        """A copy on ``device``, the rest state (``rest``) included; ``args``: only these
        keys.  Unlike PyG's ``Data.to`` (which moves in place), this one never moves
        ``self``: a dataset's cached item stays on the CPU when a copy goes to a GPU."""
        out = copy.copy(self)  # a new store holding the same tensors
        Data.to(out, device, *args, non_blocking=non_blocking)
        if "rest" in out and (not args or "rest" in args):
            rest = out.rest  # one ClothRest, or a batch's list of them
            out.rest = [r.to(device, non_blocking=non_blocking) for r in rest] \
                if isinstance(rest, list) else rest.to(device, non_blocking=non_blocking)
        return out

    def cpu(self, *args: str) -> "GarmentInputs":
        """A copy on the CPU (see :meth:`to`)."""
        return self.to("cpu", *args)

    def cuda(self, device=None, *args: str, non_blocking: bool = True) -> "GarmentInputs":
        """A copy on a GPU, ``cuda`` (the current one) by default (see :meth:`to`)."""
        return self.to("cuda" if device is None else device, *args, non_blocking=non_blocking)

    def pinned_mask(self) -> Tensor:
        """``[V]`` bool (all ``False`` when nothing is pinned)."""
        p = self.get("pinned")
        return (torch.zeros(self.num_vertices, dtype=torch.bool, device=self.rest_pos.device)
                if p is None else p.bool())

    def select(self, idx: Tensor) -> "GarmentInputs":
        """The same garment restricted to frames ``idx`` (per-frame keys indexed, static
        keys shared, not copied); of a batch, the same frames of every chunk (its
        stacked per-frame keys indexed along their frame axis, dim 1)."""
        out = copy.copy(self)
        batched = isinstance(self, Batch)
        for k in FRAME_KEYS:
            if k in self:
                out[k] = (self[k][:, idx] if batched and k in STACKED_KEYS else self[k][idx])
        return out

    def cycled(self, b: int) -> "GarmentInputs":
        """``b`` frames taken cyclically from this chunk (for timing at batch ``b``)."""
        return self.select(torch.arange(b) % self.num_frames)

    def history_slot(self, j: int) -> "GarmentInputs":
        """The inputs whose current pose is history slot ``j`` (``-1``: the frame itself,
        ``-2``: one frame earlier, ...)."""
        H = self.rotations.shape[1]
        if not isinstance(j, int) or not -H <= j <= -1:
            raise ValueError(f"`j`: expected an int with -{H} <= j <= -1, got {j!r}")
        out = copy.copy(self)
        out.rotations = self.rotations[:, :H + j + 1]
        out.translation = self.translation[:, :H + j + 1]
        return out

    def skinned(self) -> Tensor:
        """``[B, V, 3]``: the rest garment skinned to each frame with ``skin_weights``
        (Eq. 1, :func:`skin`): the "LBS only" garment."""
        return skin(self, self.rotations[:, -1], self.translation[:, -1])[0]

    def skinning_transforms(self, dtype: torch.dtype = torch.float64) -> Tensor:
        """``[B, V, 4, 4]``: each vertex's blended skinning transform per frame,
        ``M_v(t) = sum_j W_vj A_j(t)`` (Eq. 1; kinematics in ``dtype``): ``M_v(t)``
        applied to ``rest_pos[v]`` is :meth:`skinned`, and ``M_v(t)^-1`` takes a posed
        garment back to the rest frame."""
        A, _ = forward_kinematics(self.rotations[:, -1].to(dtype), self.rest_joints.to(dtype),
                                  self.parents, self.translation[:, -1].to(dtype))
        return blend_transforms(self.skin_weights.to(dtype), A)

    def without_ground_truth(self) -> "GarmentInputs":
        """A shallow copy without ``gt`` (for methods that must never see it)."""
        out = copy.copy(self)
        if "gt" in out:
            del out.gt
        return out


def check_history(history: int) -> int:
    """``history`` (previous poses per frame, ``H = history + 1``) if it is an int >= 1
    (GarTrans needs ``H >= 2``), else a ``ValueError``."""
    if not isinstance(history, int) or isinstance(history, bool) or history < 1:
        raise ValueError(f"`history`: expected an int >= 1 (GarTrans needs H = history + 1 >= 2), "
                         f"got {history!r}")
    return history


def history_frames(frames: Tensor, history: int) -> Tensor:
    """``[B, H]`` indices of the frames ``t - history .. t`` for each ``t`` of ``frames [B]``
    (frame 0 repeated before the start of the motion)."""
    offsets = torch.arange(-history, 1, device=frames.device)
    return (frames.view(-1, 1) + offsets).clamp_min(0)


def check_pose(scene: GarmentInputs, rotations: Tensor, translation: Optional[Tensor],
                name: str = "rotations") -> None:
    if rotations.dim() != 3 or rotations.shape[1:] != (scene.num_joints, 3):
        raise ValueError(f"`{name}`: expected [B, {scene.num_joints}, 3] axis-angle, got "
                         f"{tuple(rotations.shape)}")
    if translation is not None and translation.shape != (rotations.shape[0], 3):
        raise ValueError(f"`translation`: expected [{rotations.shape[0]}, 3], got "
                         f"{tuple(translation.shape)}")


def skin(scene: GarmentInputs, rotations: Tensor, translation: Optional[Tensor] = None,
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
    check_pose(scene, rotations, translation)
    dt = scene.rest_pos.dtype
    with full_precision(scene.rest_pos) as up:  # float32 under autocast
        A, joints = forward_kinematics(rotations.to(dt), scene.rest_joints.to(dt),
                                       scene.parents,
                                       None if translation is None else translation.to(dt))
        verts = scene.rest_pos if offsets is None else scene.rest_pos + up(offsets)
        return linear_blend_skinning(verts, scene.skin_weights.to(dt), A), joints


def build_garment(rest_pos: Tensor, faces: Tensor, skin_weights: Tensor, rest_joints: Tensor,
                  parents: Tensor, pinned: Optional[Tensor] = None) -> GarmentInputs:
    """The skinned garment alone (mesh, graph, skinning weights, skeleton, pinned mask):
    what the pose-driven baselines and LBS read; :func:`build_static` adds the rest.

    Args:
        rest_pos: ``[V, 3]`` garment on the rest body; ``faces [F, 3]``.
        skin_weights: ``[V, S]`` the garment's skinning weights (e.g. the body's
            transferred to the garment, as the simulator skins it).
        rest_joints: ``[S, 3]``; ``parents [S]`` (root ``-1``).
        pinned: optional ``[V]`` bool mask of vertices that follow the body.
    """
    rest_pos, faces = torch.as_tensor(rest_pos), torch.as_tensor(faces).long()
    if rest_pos.dim() != 2 or rest_pos.shape[1] != 3:
        raise ValueError(f"`rest_pos`: expected [V, 3], got {tuple(rest_pos.shape)}")
    if faces.dim() != 2 or faces.shape[1] != 3:
        raise ValueError(f"`faces`: expected [F, 3], got {tuple(faces.shape)}")
    if not torch.isfinite(rest_pos).all():
        raise ValueError("`rest_pos`: contains NaN/inf")
    if rest_joints.dim() != 2 or rest_joints.shape[1] != 3:
        raise ValueError(f"`rest_joints`: expected [S, 3], got {tuple(rest_joints.shape)}")
    V, S = rest_pos.shape[0], rest_joints.shape[0]
    if skin_weights.shape != (V, S):
        raise ValueError(f"`skin_weights`: expected [{V}, {S}], got {tuple(skin_weights.shape)}")
    if parents.shape != (S,):
        raise ValueError(f"`parents`: expected [{S}], got {tuple(parents.shape)}")
    if pinned is not None:
        pinned = torch.as_tensor(pinned).bool()
        if pinned.shape != (V,):
            raise ValueError(f"`pinned`: expected [{V}] bool, got {tuple(pinned.shape)}")
    return GarmentInputs(rest_pos=rest_pos, faces=faces, edge_index=faces_to_edge_index(faces, V),
                         skin_weights=skin_weights, rest_joints=rest_joints,
                         parents=parents.long(), pinned=pinned, num_nodes=V)


def nystrom_features(rest_pos: Tensor, faces: Tensor, nystrom_dim: int = NYSTROM_DIM,
                     num_landmarks: int = NUM_LANDMARKS) -> Tensor:
    """The garment's Nyström features ``[V, nystrom_dim]`` float32 (paper §3.1,
    :func:`~garmentgnn.geometry.geodesic_nystrom_features` in float64), zero-padded to
    ``nystrom_dim`` columns on meshes with fewer landmarks."""
    rest_pos = torch.as_tensor(rest_pos)
    ny = geodesic_nystrom_features(rest_pos.double(), torch.as_tensor(faces).long(),
                                   k=nystrom_dim, num_landmarks=num_landmarks).float()
    if ny.shape[1] < nystrom_dim:  # tiny meshes: fewer landmarks than k
        ny = torch.cat([ny, ny.new_zeros(len(ny), nystrom_dim - ny.shape[1])], 1)
    return ny


def build_static(rest_pos: Tensor, faces: Tensor, body: Body, skin_weights: Tensor,
                 face_uv: Optional[Tensor] = None, density: float = 0.15,
                 pinned: Optional[Tensor] = None, nystrom_dim: int = NYSTROM_DIM,
                 num_landmarks: int = NUM_LANDMARKS, nystrom: Optional[Tensor] = None,
                 material: Optional[Tensor] = None) -> GarmentInputs:
    """The per-garment, per-body-shape part of the inputs (computed once per sequence):
    :func:`build_garment` in float32 plus the Nyström features, the cloth rest state,
    vertex masses and the rest body.

    Args:
        rest_pos, faces, skin_weights, pinned: as :func:`build_garment`.
        body: the body in its rest pose (vertices, joints, skeleton, faces).
        face_uv: ``[F, 3, 2]`` material coordinates (default: each rest triangle laid
            flat, :meth:`ClothRest.from_mesh`).
        density: surface density (kg/m^2) for the vertex masses.
        nystrom_dim, num_landmarks: the Nyström features (:func:`nystrom_features`).
        nystrom: those features where already computed (``[V, nystrom_dim]``).
        material: the fabric's features ``[K]``
            (:func:`~garmentgnn.physics.material_features`), kept as ``material``.
    """
    if not isinstance(body, Body):
        raise TypeError(f"`body`: expected a garmentgnn.body.Body, got {type(body).__name__}")
    bverts, joints = body.vertices.float(), body.joints.float()
    out = build_garment(torch.as_tensor(rest_pos).float(), faces,
                        torch.as_tensor(skin_weights).float(), joints, body.skeleton.parents,
                        pinned)
    V = out.num_vertices
    if nystrom is None:
        ny = nystrom_features(out.rest_pos, out.faces, nystrom_dim, num_landmarks)
    else:
        ny = torch.as_tensor(nystrom).float()
        if ny.shape != (V, nystrom_dim):
            raise ValueError(f"`nystrom`: expected [{V}, {nystrom_dim}] (vertices, "
                             f"nystrom_dim), got {tuple(ny.shape)}")
    face_uv = None if face_uv is None else torch.as_tensor(face_uv).float()
    rest = ClothRest.from_mesh(out.rest_pos, out.faces, face_uv)
    out.nystrom, out.rest = ny, rest
    out.mass = rest.vertex_masses(density, V).float()
    out.body_joint_dists = torch.cdist(bverts, joints)
    out.body_faces = body.faces.long()
    if face_uv is not None:
        out.face_uv = face_uv
    if material is not None:
        material = torch.as_tensor(material).float()
        if material.dim() != 1 or not torch.isfinite(material).all():
            raise ValueError(f"`material`: expected finite features [K] "
                             f"(garmentgnn.physics.material_features), got "
                             f"{tuple(material.shape)}")
        out.material = material
    return out


def posed_body(body: Body, rotations: Tensor, translation: Tensor, frames: Tensor) -> Tensor:
    """The body's vertices ``[B, Vb, 3]`` (float32) posed at ``frames`` of a motion
    (``rotations [T, S, 3]``, ``translation [T, 3]``), without autograd."""
    with torch.no_grad():
        dt = body.vertices.dtype
        bpos, _ = body.pose(rotations[frames].to(dt), translation[frames].to(dt))
    return bpos.float()


def with_frames(static: GarmentInputs, body: Body, rotations: Tensor, translation: Tensor,
                frames: Tensor, history: int, gt: Optional[Tensor] = None,
                seq_id: Optional[str] = None,
                body_pos: Optional[Tensor] = None) -> GarmentInputs:
    """``static`` plus frames ``frames`` of a motion.

    Args:
        body: the rest body (posed here for ``body_pos``).
        rotations, translation: the whole motion, ``[T, S, 3]`` and ``[T, 3]``.
        frames: ``[B]`` frame indices.
        history: previous poses per frame (``H = history + 1 >= 2``).
        gt: ``[B, V, 3]`` the simulated garment of those frames, or ``None``.
        body_pos: ``[B, Vb, 3]``, :func:`posed_body` of these frames kept by the caller
            (``None``: posed here).
    """
    check_history(history)
    rotations, translation = torch.as_tensor(rotations).float(), \
        torch.as_tensor(translation).float()
    S = static.num_joints
    if rotations.dim() != 3 or rotations.shape[1:] != (S, 3):
        raise ValueError(f"`rotations`: expected the motion's [T, {S}, 3] axis-angle "
                         f"rotations, got {tuple(rotations.shape)}")
    T = rotations.shape[0]
    if translation.shape != (T, 3):
        raise ValueError(f"`translation`: expected [{T}, 3] (one per frame of `rotations`), "
                         f"got {tuple(translation.shape)}")
    frames = torch.as_tensor(frames).long()
    if frames.numel() and not (0 <= int(frames.min()) and int(frames.max()) < T):
        raise ValueError(f"`frames`: indices must lie in [0, {T}), got "
                         f"[{int(frames.min())}, {int(frames.max())}]")
    hist = history_frames(frames, history)  # [B, H]
    if body_pos is None:
        body_pos = posed_body(body, rotations, translation, frames)
    elif body_pos.shape != (frames.shape[0], body.vertices.shape[0], 3):
        raise ValueError(f"`body_pos`: expected [{frames.shape[0]}, {body.vertices.shape[0]}, "
                         f"3] (the body posed at `frames`), got {tuple(body_pos.shape)}")
    out = copy.copy(static)
    out.rotations, out.translation = rotations[hist], translation[hist]
    out.body_pos, out.frames = body_pos.float(), frames
    if gt is not None:
        gt = torch.as_tensor(gt).float()
        if gt.shape != (frames.shape[0], static.num_vertices, 3):
            raise ValueError(f"`gt`: expected [{frames.shape[0]}, {static.num_vertices}, 3], "
                             f"got {tuple(gt.shape)}")
        out.gt = gt
    if seq_id is not None:
        out.seq_id = seq_id
    return out



def _with(inputs: GarmentInputs, **values: Any) -> GarmentInputs:
    """A shallow copy of ``inputs`` with ``values`` set."""
    out = copy.copy(inputs)
    for k, v in values.items():
        out[k] = v
    return out
