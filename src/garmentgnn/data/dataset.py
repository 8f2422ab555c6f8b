"""A lazy PyG dataset over generated sequences: one graph per simulated frame.

Memory bound: the index (built from ``manifest.json`` alone) holds a few integers per
sequence; at most ``cache_size`` sequence files are loaded at a time (least recently
used evicted), so positions occupy about
``cache_size * num_frames * V * 3 * 4`` bytes (float32), plus one rest body per
(body model, shape) and the per-sequence edge index.
"""
from __future__ import annotations

import bisect
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
import torch
from torch_geometric.data import Data, Dataset

from garmentgnn.data import store
from garmentgnn.body.factory import build_body
from garmentgnn.data.keys import body_key
from garmentgnn.geometry.mesh import edge_features, faces_to_edge_index


class GarmentFrame(Data):
    """A :class:`~torch_geometric.data.Data` whose garment ``faces`` and ``body_faces``
    are offset when batched and whose per-graph motion tensors (``pose``,
    ``translation``) are stacked along a new batch dimension."""

    def __inc__(self, key: str, value: Any, *args, **kwargs):
        if key == "faces":
            return self.num_nodes
        if key == "body_faces":
            return self.body_vertices.size(0)
        return super().__inc__(key, value, *args, **kwargs)

    def __cat_dim__(self, key: str, value: Any, *args, **kwargs):
        if key in ("pose", "translation"):
            return None
        if key in ("faces", "body_faces"):
            return 0
        return super().__cat_dim__(key, value, *args, **kwargs)


class GarmentSequenceDataset(Dataset):
    """Frames ``t = 0 .. T-2`` of every ok sequence of ``split`` in ``root/manifest.json``.

    Each item is a :class:`GarmentFrame` with

    * ``pos`` ``[V, 3]``: garment vertices at frame ``t``;
    * ``prev_pos`` ``[V, history, 3]``: frames ``t-1, ..., t-history`` (frame 0 repeated
      before the start);
    * ``y`` ``[V, 3]``: frame ``t+1`` (the target);
    * ``rest_pos`` ``[V, 3]``, ``pinned`` ``[V]``;
    * ``edge_index`` ``[2, E]`` (:func:`faces_to_edge_index`, sorted by target) and
      ``edge_attr`` ``[E, 4]`` (:func:`edge_features` of ``pos``);
    * ``faces`` ``[F, 3]``, ``face_uv`` ``[F, 3, 2]``;
    * ``pose`` ``[history+1, S, 3]`` axis-angle for frames ``t-history .. t`` and
      ``translation`` ``[history+1, 3]`` (batched: ``[B, history+1, ...]``);
    * ``body_vertices`` ``[Vb, 2, 3]``: the posed body at frames ``t`` and ``t+1``
      (recomputed from the body model + stored motion), ``body_faces`` ``[Fb, 3]``;
    * ``seq_id`` (str), ``frame`` (int).

    Args:
        root: the generation output folder.
        split: ``"train" | "val" | "test"`` (or ``None`` for all).
        history: number of previous frames.
        cache_size: sequence files kept loaded (LRU), see the module doc.
    """

    def __init__(self, root, split: Optional[str] = "train", history: int = 2,
                 cache_size: int = 4, transform=None) -> None:
        if history < 0:
            raise ValueError(f"`history`: expected >= 0, got {history}")
        if cache_size < 1:
            raise ValueError(f"`cache_size`: expected >= 1, got {cache_size}")
        self.history, self.cache_size, self.split = history, cache_size, split
        self._root = Path(root)
        super().__init__(None, transform=transform)
        manifest = store.read_manifest(self._root)
        self.records = [r for r in manifest["items"] if r["status"] == "ok"
                        and (split is None or r["split"] == split)]
        # frames t = 0..T-2 of each sequence (t+1 must exist)
        counts = [max(0, int(r["num_frames"]) - 1) for r in self.records]
        self._offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self._cache = store.LRUCache(self.cache_size)
        self._bodies: Dict[str, Any] = {}
        self.num_file_loads = 0

    # PyG Dataset plumbing: no raw/processed files
    @property
    def raw_file_names(self) -> List[str]:
        return []

    @property
    def processed_file_names(self) -> List[str]:
        return []

    def len(self) -> int:
        return int(self._offsets[-1])

    def locate(self, idx: int) -> Tuple[int, int]:
        """``(sequence index, frame)`` of a flat frame index."""
        if not 0 <= idx < self.len():
            raise IndexError(f"frame index {idx} out of range [0, {self.len()})")
        s = bisect.bisect_right(self._offsets, idx) - 1
        return s, int(idx - self._offsets[s])

    def _sequence(self, s: int) -> Dict[str, Any]:
        rec = self.records[s]

        def load() -> Dict[str, Any]:
            seq = store.load_record_sequence(self._root, rec)
            self.num_file_loads += 1
            faces = torch.from_numpy(seq["garment_faces"]).long()
            seq["edge_index"] = faces_to_edge_index(faces, seq["garment_vertices"].shape[0])
            seq["faces_t"] = faces
            return seq

        return self._cache.get_or_build(rec["id"], load)

    def _body(self, spec: Dict[str, Any]):
        key = body_key(spec)
        if key not in self._bodies:
            self._bodies[key] = build_body(spec)
        return self._bodies[key]

    def get(self, idx: int) -> GarmentFrame:
        s, t = self.locate(idx)
        seq = self._sequence(s)
        meta = seq["meta"]
        P = seq["positions"]
        T = P.shape[0]
        prev = [max(t - k, 0) for k in range(1, self.history + 1)]
        hist = [max(t - k, 0) for k in range(self.history, -1, -1)]  # t-h .. t
        pos = torch.from_numpy(np.array(P[t]))
        rot = torch.from_numpy(np.array(seq["motion_rotations"]))
        tr = torch.from_numpy(np.array(seq["motion_translation"]))
        body = self._body(meta["body"])
        nxt = min(t + 1, T - 1)
        with torch.no_grad():
            bverts, _ = body.pose(rot[[t, nxt]], tr[[t, nxt]])
        ei = seq["edge_index"]
        return GarmentFrame(
            pos=pos,
            prev_pos=torch.from_numpy(np.ascontiguousarray(P[prev].transpose(1, 0, 2)))
            if prev else pos.new_zeros(pos.shape[0], 0, 3),
            y=torch.from_numpy(np.array(P[nxt])),
            rest_pos=torch.from_numpy(seq["garment_vertices"]),
            pinned=torch.from_numpy(seq["garment_pinned"]),
            edge_index=ei,
            edge_attr=edge_features(pos, ei),
            faces=seq["faces_t"],
            face_uv=torch.from_numpy(seq["garment_face_uv"]),
            pose=rot[hist],
            translation=tr[hist],
            body_vertices=bverts.transpose(0, 1).contiguous().float(),
            body_faces=body.faces.long(),
            seq_id=meta["id"],
            frame=t,
            num_nodes=pos.shape[0],
        )


__all__ = ["GarmentFrame", "GarmentSequenceDataset"]
