"""The dataset reader: chunks of consecutive frames of a generated dataset, as model inputs.

A *chunk* is one garment on one body over ``B`` consecutive frames of one generated
sequence (the ``.npz`` files written by ``garmentgnn generate``, loaded with
:func:`garmentgnn.data.store.load_sequence`).  GarTrans predicts the frames of a
chunk in parallel and shares one static encoding (``encode_static``) between them.

Each item is a :class:`~garmentgnn.models.inputs.GarmentInputs` (a PyG ``Data``),
built by
:func:`~garmentgnn.models.inputs.build_static` and
:func:`~garmentgnn.models.inputs.with_frames`: the model inputs every method, loss and
metric reads.  ``skin_weights`` are the ones stored with the sequence (the weights the
engine skinned the garment with); files written before they were stored get the same
transfer recomputed.

The static inputs (edge index, Nyström features, ClothRest, masses, rest body) are
computed once per sequence and cached (``static_cache`` entries, LRU; by default every
sequence of the split, up to :data:`STATIC_CACHE`); positions and
motion are cached per sequence file (LRU: at most ``cache_size`` files and
``cache_bytes`` bytes of their arrays; the defaults hold a few hundred ``learn``-sized
sequences, so shuffled training rarely reads one again); each chunk's posed body is kept
by chunk after its first visit (LRU within ``cache_bytes`` too).  The Nyström features,
most of a static build's time, are also kept on disk beside the dataset, as PyG keeps a
dataset's ``processed`` folder: ``ROOT/processed/nystrom-k<nystrom_dim>-z<num_landmarks>/
<sequence sha256>.npy``, written once by whichever run first needs them (atomically; a
cut-off or foreign file is computed again; a read-only dataset computes them each time).

Each item with ground truth carries ``valid [B]`` (:meth:`SequenceChunks.valid`): the
frames that are ground truth (converged, and the body not through the cloth), the only
ones training targets and metrics use; ``converged [B]`` is the engine's own flag.

``chunks[[i, j, ...]]`` collates those chunks (of one frame count) as one PyG ``Batch``
(:meth:`GarmentInputs.collate`): what a batched training step reads
(:class:`garmentgnn.training.GarmentDataModule`).
"""
from __future__ import annotations

import io
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch
from torch.utils.data import Dataset

from garmentgnn.models.inputs import CHUNK, HISTORY, NUM_LANDMARKS, NYSTROM_DIM
from garmentgnn.body.factory import build_body
from garmentgnn.data import store
from garmentgnn.data.validity import sequence_valid
from garmentgnn.garments.skinning import transfer_skinning_weights
from garmentgnn.models.inputs import (GarmentInputs, build_static, check_history,
                                     nystrom_features, posed_body, with_frames)
from garmentgnn.physics import MATERIALS, material_features

__all__ = ["DEFAULT_DENSITY", "SequenceChunks"]

DEFAULT_DENSITY = 0.15


#: the folder beside a dataset's sequences that keeps their preprocessing (PyG's name)
PROCESSED = "processed"
#: default bound of the sequence cache: files, and bytes of their loaded arrays (a
#: ``learn`` sequence is ~0.4 MB; a reload costs ~2 ms: read, SHA-256, checks)
CACHE_SIZE, CACHE_BYTES = 4096, 512 * 2 ** 20
#: default bound of the static-input cache: every sequence of the split up to this many
#: (a `learn` sequence's static inputs are ~0.4 MB; a rebuild costs ~3.5 ms a window with
#: its Nyström features read from disk, and a smaller cache than the split rebuilds most
#: of them under shuffled training: 3.57 against 0.12 ms a window on `learn`)
STATIC_CACHE = 1024


def sequence_material(meta: Dict[str, Any]) -> Optional[torch.Tensor]:
    """The fabric's features (:func:`~garmentgnn.physics.material_features`) of a
    sequence: its ``material_params``, else its named preset, else ``None``."""
    params = meta.get("material_params")
    if params:
        return material_features(params)
    name = meta.get("material")
    return material_features(MATERIALS[name]) if name in MATERIALS else None


def static_inputs(seq: Dict[str, Any], meta: Dict[str, Any], nystrom_dim: int = NYSTROM_DIM,
                  num_landmarks: int = NUM_LANDMARKS, nystrom: Optional[Callable] = None
                  ) -> Tuple[GarmentInputs, Any]:
    """``(static inputs, rest body)`` of a sequence's arrays (a sequence file's, or
    :func:`garmentgnn.data.worker.input_arrays` of a garment, body and motion) and its
    meta (``body``, ``material_params`` / ``material``): what every reader of model
    inputs builds.  ``nystrom(rest_pos, faces)``: the features where cached."""
    rest_pos = torch.from_numpy(np.asarray(seq["garment_vertices"], np.float32))
    faces = torch.from_numpy(np.asarray(seq["garment_faces"])).long()
    body = build_body(meta["body"])
    skin = seq.get("garment_skin_weights")
    if skin is None:  # files written before the weights were stored: the same transfer
        skin = transfer_skinning_weights(rest_pos, faces, body.vertices.float(),
                                         body.weights.float())
    pinned = np.asarray(seq["garment_pinned"]).astype(bool)
    ny = None if nystrom is None else nystrom(rest_pos, faces)
    st = build_static(
        rest_pos, faces, body, torch.as_tensor(np.asarray(skin, np.float32)),
        face_uv=torch.from_numpy(np.asarray(seq["garment_face_uv"], np.float32)),
        density=float((meta.get("material_params") or {}).get("density", DEFAULT_DENSITY)),
        pinned=torch.from_numpy(pinned) if pinned.any() else None,
        nystrom_dim=nystrom_dim, num_landmarks=num_landmarks, nystrom=ny,
        material=sequence_material(meta))
    return st, body


class SequenceChunks(Dataset):
    """Chunks of ``chunk`` consecutive frames of every ok sequence of ``split``.

    Args:
        root: generation output folder (``manifest.json`` + ``sequences/``).
        split: ``"train" | "val" | "test"`` or ``None`` for all; a split the manifest
            does not list, or one without ok sequences, is a ``ValueError``.
        chunk: frames per chunk ``B``; a sequence is cut into ``ceil(T / chunk)``
            chunks (the last may be shorter) -- ``drop_last=True`` drops a short one.
        stride: frames between the starts of consecutive chunks (default ``chunk``:
            disjoint chunks); ``stride < chunk`` gives overlapping windows, each
            starting at ``0, stride, 2 stride, ...`` (e.g. every frame triple of a
            sequence with ``chunk=3, stride=1, drop_last=True``: a learned simulator's
            one-step samples).
        history: previous frames per pose history (``H = history + 1 >= 2``).
        nystrom_dim, num_landmarks: Nyström features (``k`` must equal the model's
            ``nystrom_dim``).
        cache_size, static_cache: sequence files / static inputs kept (LRU; the
            static inputs by default of every sequence of the split, up to
            :data:`STATIC_CACHE`).
        cache_bytes: at most this many bytes of loaded sequence files kept (LRU, with
            ``cache_size``; the arrays as loaded, :func:`~garmentgnn.data.store.nbytes`),
            and as many of the chunks' posed bodies (LRU by chunk: posing the body
            takes ~1.3 ms a chunk of 8 frames; ``learn``'s 2,136 chunks hold ~250 MB).
        ids: keep only these sequence ids (e.g. one garment's sequences).

    ``chunks[i]`` is one chunk; ``chunks[[i, j, ...]]`` those chunks as one batch.
    """

    def __init__(self, root, split: Optional[str] = "train", chunk: int = CHUNK,
                 history: int = HISTORY, nystrom_dim: int = NYSTROM_DIM,
                 num_landmarks: int = NUM_LANDMARKS, drop_last: bool = False,
                 cache_size: int = CACHE_SIZE, static_cache: Optional[int] = None,
                 cache_bytes: int = CACHE_BYTES,
                 ids: Optional[Sequence[str]] = None, stride: Optional[int] = None) -> None:
        if chunk < 1:
            raise ValueError(f"`chunk`: expected >= 1, got {chunk}")
        stride = chunk if stride is None else stride
        if not isinstance(stride, int) or isinstance(stride, bool) or stride < 1:
            raise ValueError(f"`stride`: expected frames >= 1 (or None: `chunk`), got "
                             f"{stride!r}")
        if not isinstance(num_landmarks, int) or num_landmarks < 1:
            raise ValueError(f"`num_landmarks`: expected an int >= 1, got {num_landmarks!r}")
        if not isinstance(nystrom_dim, int) or not 1 <= nystrom_dim <= num_landmarks:
            raise ValueError(f"`nystrom_dim`: expected an int in [1, num_landmarks="
                             f"{num_landmarks}] (the features are eigenvectors over the "
                             f"landmarks), got {nystrom_dim!r}; lower nystrom_dim or raise "
                             f"num_landmarks")
        check_history(history)
        self.root = Path(root)
        self.split, self.chunk, self.history, self.stride = split, chunk, history, stride
        self.nystrom_dim, self.num_landmarks = nystrom_dim, num_landmarks
        if not isinstance(cache_bytes, int) or isinstance(cache_bytes, bool) or cache_bytes < 0:
            raise ValueError(f"`cache_bytes`: expected bytes >= 0, got {cache_bytes!r}")
        self.cache_size = max(1, cache_size)
        self.cache_bytes = cache_bytes
        manifest = store.read_manifest(self.root)
        items = manifest["items"]
        if not items:
            raise ValueError(f"`root`: {root}/{store.MANIFEST} lists no sequences; simulate "
                             f"the dataset with `garmentgnn generate --out {root}` (or "
                             f"rebuild the manifest from its files: `garmentgnn manifest "
                             f"--out {root}`)")
        if split is not None:
            splits = sorted({str(r.get("split")) for r in items})
            if split not in splits:
                raise ValueError(f"`split`: {root} has no {split!r} split; name one that its "
                                 f"manifest lists: {', '.join(splits)}")
        keep = None if ids is None else set(ids)
        self.records = [r for r in items if r["status"] == "ok"
                        and (split is None or r["split"] == split)
                        and (keep is None or r["id"] in keep)]
        if keep is not None and len(self.records) != len(keep):
            found = {r["id"] for r in self.records}
            raise ValueError(f"`ids`: not ok {split!r} sequences under {root}: "
                             f"{sorted(keep - found)[:5]}")
        if not self.records:
            listed = [r for r in items if split is None or r["split"] == split]
            status: Dict[str, int] = {}
            for r in listed:
                status[str(r["status"])] = status.get(str(r["status"]), 0) + 1
            what = "sequences" if split is None else f"{split!r} sequences"
            raise ValueError(f"`split`: no ok {what} under {root} (the manifest lists "
                             f"{len(listed)}: {status or 'none'}); simulate them with "
                             f"`garmentgnn generate --out {root}` (failed ones with "
                             f"--retry-failed)")
        self.index: List[Tuple[int, int, int]] = []  # (record, first frame, frames)
        for i, r in enumerate(self.records):
            T = int(r["num_frames"])
            for t0 in range(0, T, stride):
                n = min(chunk, T - t0)
                if n == chunk or not drop_last:
                    self.index.append((i, t0, n))
                if t0 + chunk >= T:  # this window reached the end
                    break
        self.static_cache = (min(len(self.records), STATIC_CACHE) if static_cache is None
                             else max(1, static_cache))
        self._init_caches()

    def _init_caches(self) -> None:
        """Empty caches (sequence files, static inputs, each chunk's posed body) bounded by
        ``cache_size``, ``static_cache`` and ``cache_bytes``, and zeroed counters."""
        self._seqs = store.LRUCache(self.cache_size, self.cache_bytes)
        self._static = store.LRUCache(self.static_cache)
        self._bodies = store.LRUCache(self.cache_size, self.cache_bytes)  # posed, by chunk
        self.num_file_loads = 0
        self.num_static_builds = 0
        self.num_nystrom_builds = 0

    def __len__(self) -> int:
        return len(self.index)

    def valid(self, idx: int) -> torch.Tensor:
        """``[n]`` bool: which frames of item ``idx`` are valid ground truth
        (:func:`garmentgnn.data.validity.valid_frames`: the engine converged and the
        garment is at most :data:`~garmentgnn.data.validity.VALID_PENETRATION` inside the
        body); training targets and metrics leave the others out
        (:func:`garmentgnn.metrics.evaluate_inputs`'s ``keep``)."""
        i, t0, n = self.index[idx]
        ok = sequence_valid(self.sequence(i))
        return torch.from_numpy(np.ascontiguousarray(ok[t0:t0 + n]))

    def converged(self, idx: int) -> torch.Tensor:
        """``[n]`` bool: which frames of item ``idx`` the engine converged on (the sequence
        file's ``converged``); what is scored is :meth:`valid`, a subset of these."""
        i, t0, n = self.index[idx]
        conv = self.sequence(i).get("converged")
        if conv is None:
            return torch.ones(n, dtype=torch.bool)
        return torch.from_numpy(np.asarray(conv[t0:t0 + n], dtype=bool))

    # -- caches -----------------------------------------------------------------
    def sequence(self, i: int) -> Dict[str, Any]:
        rec = self.records[i]

        def load() -> Dict[str, Any]:
            self.num_file_loads += 1
            return store.load_record_sequence(self.root, rec)

        return self._seqs.get_or_build(rec["id"], load)

    def static(self, i: int) -> GarmentInputs:
        """The per-sequence static inputs (cached)."""
        return self._static_and_body(i)[0]

    def _static_and_body(self, i: int) -> Tuple[GarmentInputs, Any]:
        return self._static.get_or_build(self.records[i]["id"], lambda: self._build_static(i))

    def _build_static(self, i: int) -> Tuple[GarmentInputs, Any]:
        seq = self.sequence(i)
        try:
            st, body = static_inputs(seq, seq["meta"], self.nystrom_dim, self.num_landmarks,
                                     nystrom=lambda rest_pos, faces: self._nystrom(
                                         i, rest_pos, faces))
        except ValueError as exc:  # the Nyström features' `k` is our nystrom_dim
            msg = str(exc)
            if not msg.startswith(("`k`", "`num_landmarks`")):
                raise
            path = store.sequence_path(self.root, self.records[i])
            raise ValueError(f"`nystrom_dim`: {self.nystrom_dim} Nyström features with "
                             f"num_landmarks={self.num_landmarks} do not fit the garment of "
                             f"{path} ({len(seq['garment_vertices'])} vertices; "
                             f"{msg.split(': ', 1)[-1]}); lower nystrom_dim or raise "
                             f"num_landmarks") from None
        self.num_static_builds += 1
        return st, body

    def nystrom_path(self, i: int) -> Optional[Path]:
        """Where sequence ``i``'s Nyström features are kept (``None``: a record without
        its file's ``sha256``, whose features are computed each time)."""
        sha = self.records[i].get("sha256")
        if not sha:
            return None
        return (self.root / PROCESSED / f"nystrom-k{self.nystrom_dim}-z{self.num_landmarks}"
                / f"{sha}.npy")

    def _nystrom(self, i: int, rest_pos: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
        """Sequence ``i``'s Nyström features ``[V, nystrom_dim]``: read from
        :meth:`nystrom_path`, or computed and written there."""
        path = self.nystrom_path(i)
        if path is not None and path.is_file():
            try:
                ny = np.load(path, allow_pickle=False)
                if ny.shape == (len(rest_pos), self.nystrom_dim) and ny.dtype == np.float32 \
                        and np.isfinite(ny).all():
                    return torch.from_numpy(ny)
            except (OSError, ValueError, EOFError):  # cut off by a kill: computed again
                pass
        ny = nystrom_features(rest_pos, faces, self.nystrom_dim, self.num_landmarks)
        self.num_nystrom_builds += 1
        if path is not None:
            buf = io.BytesIO()
            np.save(buf, ny.numpy(), allow_pickle=False)
            try:
                store.atomic_write_bytes(path, buf.getvalue())
            except OSError:  # a read-only dataset
                pass
        return ny

    # -- items --------------------------------------------------------------------
    def frame_counts(self) -> List[int]:
        """Frames of each chunk (what a batch of chunks must share)."""
        return [n for _, _, n in self.index]

    def __getitem__(self, idx: Union[int, Sequence[int]]) -> GarmentInputs:
        if isinstance(idx, (list, tuple)):
            return GarmentInputs.collate([self[i] for i in idx])
        if not 0 <= idx < len(self):
            raise IndexError(f"chunk index {idx} out of range [0, {len(self)})")
        i, t0, n = self.index[idx]
        seq, (st, body) = self.sequence(i), self._static_and_body(i)
        rot = torch.from_numpy(np.asarray(seq["motion_rotations"], np.float32))
        tr = torch.from_numpy(np.asarray(seq["motion_translation"], np.float32))
        pos = np.asarray(seq["positions"])
        gt = None
        if pos.shape[1:2] == (st.num_vertices,):
            gt = torch.from_numpy(np.asarray(pos[t0:t0 + n], np.float32))
        frames = torch.arange(t0, t0 + n)
        # the posed body of a chunk: built on its first visit, kept for the next epochs
        bpos = self._bodies.get_or_build(idx, lambda: posed_body(body, rot, tr, frames))
        item = with_frames(st, body, rot, tr, frames, self.history, gt=gt,
                           seq_id=self.records[i]["id"], body_pos=bpos)
        if gt is not None:  # which frames the engine converged on, and which are scored
            item.converged = self.converged(idx)
            item.valid = self.valid(idx)
        return item
