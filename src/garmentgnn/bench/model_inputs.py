"""GarTrans inputs for a bench sequence, built by the training data module's own code.

:class:`BenchChunks` is :class:`garmentgnn.data.SequenceChunks` reading one
in-memory :class:`~garmentgnn.bench.sequences.BenchSequence` instead of a generated
``.npz`` file: its items (static inputs from ``SequenceChunks._build_static``: edge
index, Nyström features, ClothRest, masses, body distances, transferred skinning
weights; pose histories from ``SequenceChunks.__getitem__``) are exactly what
``garmentgnn train`` feeds the model, so what the bench times is what training and
evaluation run.  :func:`untrained_module` builds a seeded, untrained
:class:`~garmentgnn.training.GarTransModule` sized for such an item; a
:class:`Predictor` is a trained method as the bench runs it.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable, Dict, Optional, Tuple

import numpy as np
import torch
from torch import Tensor

from garmentgnn.models.inputs import HISTORY, NUM_LANDMARKS, NYSTROM_DIM
from garmentgnn.bench.sequences import BenchSequence
from garmentgnn.models.inputs import GarmentInputs, check_history
from garmentgnn.data import SequenceChunks
from garmentgnn.training import GarTransModule
from garmentgnn.models import GarTrans


@dataclass
class Predictor:
    """A trained method: ``predict(ds, i, item)`` the garment ``[T, V, 3]`` of ``item``,
    item ``i`` of ``ds`` (the whole-sequence test set, or the :class:`BenchChunks` of a
    stability case); ``make_batch(item, b)`` a function predicting ``b`` frames of
    ``item`` per call (inputs prepared outside it) for the timing sweep."""

    predict: Callable[[SequenceChunks, int, GarmentInputs], Tensor]
    make_batch: Callable[[GarmentInputs, int], Callable[[], Any]]
    note: str
    #: the trained module and its weights at the budget's ``equal_steps`` (if reached)
    module: Optional[torch.nn.Module] = None
    snapshot: Optional[Path] = None
    #: the method protocol's ``autoregressive`` and ``family`` (``None``: no learned
    #: method)
    autoregressive: bool = False
    module_family: Optional[str] = None


class BenchChunks(SequenceChunks):
    """Chunks of ``chunk`` consecutive frames of one :class:`BenchSequence`.

    Args:
        seq: the sequence (garment, capsule/anny body spec in ``seq.item``, motion,
            material).
        chunk: frames per item (default: every frame in one item).
        history, nystrom_dim, num_landmarks: as :class:`SequenceChunks`.
        gt: ``[T, V, 3]`` target positions (e.g. the reference simulation) for the
            items' ``gt``; ``None``: items carry no ``gt`` key (nothing is made up).
    """

    def __init__(self, seq: BenchSequence, chunk: Optional[int] = None, history: int = HISTORY,
                 nystrom_dim: int = NYSTROM_DIM, num_landmarks: int = NUM_LANDMARKS,
                 gt: Optional[Tensor] = None) -> None:
        if not isinstance(seq, BenchSequence):
            raise ValueError(f"`seq`: expected a BenchSequence, got {type(seq).__name__}")
        T, V = seq.num_frames, seq.garment.num_vertices
        chunk = T if chunk is None else chunk
        if not isinstance(chunk, int) or chunk < 1:
            raise ValueError(f"`chunk`: expected a positive int, got {chunk!r}")
        check_history(history)
        if gt is not None and tuple(gt.shape) != (T, V, 3):
            raise ValueError(f"`gt`: expected [{T}, {V}, 3], got {tuple(gt.shape)}")
        # the attributes SequenceChunks.__init__ sets (it reads a manifest, so is not called)
        self.root, self.split, self.chunk, self.history = None, None, chunk, history
        self.nystrom_dim, self.num_landmarks = nystrom_dim, num_landmarks
        self.cache_size = self.static_cache = 1
        self.cache_bytes = None  # one sequence, one static entry, one posed body
        self.records = [{"id": seq.name, "num_frames": T, "status": "ok",
                         "garment": seq.item["garment"], "body": seq.item["body"]}]
        self.index = [(0, t0, min(chunk, T - t0)) for t0 in range(0, T, chunk)]
        self._init_caches()
        g, m = seq.garment, seq.motion
        positions = (gt.detach().float().numpy() if gt is not None
                     else np.zeros((T, 0, 3), np.float32))
        # the arrays and meta of a generated sequence file (data.worker.run_item)
        self._data: Dict[str, Any] = {
            "garment_vertices": g.vertices.numpy().astype(np.float32),
            "garment_faces": g.faces.numpy().astype(np.int64),
            "garment_face_uv": g.face_uv.numpy().astype(np.float32),
            "garment_pinned": (g.pinned.numpy() if g.pinned is not None
                               else np.zeros(V, bool)).astype(bool),
            "garment_skin_weights": seq.scene.skin_weights.float().numpy(),
            "motion_rotations": m.rotations.float().numpy(),
            "motion_translation": m.translation.float().numpy(),
            "positions": positions,
            "meta": {"body": seq.item["body"], "material_params": asdict(seq.material),
                     "id": seq.name, "num_frames": T, "num_vertices": V},
        }

    def sequence(self, i: int) -> Dict[str, Any]:
        if i != 0:
            raise IndexError(f"`i`: a BenchChunks holds one sequence, got {i}")
        return self._data



def untrained_module(item: Dict[str, Any], seed: int = 0, **kwargs: Any) -> GarTransModule:
    """A :class:`GarTransModule` in eval mode, initialised under ``torch.manual_seed(seed)``
    (the global RNG state is restored afterwards), sized for ``item`` (a
    :class:`BenchChunks` / :class:`SequenceChunks` item); ``kwargs`` go to the module
    (``lbs_start``, ``dynamic_layer``, ...)."""
    if not isinstance(seed, int):
        raise ValueError(f"`seed`: expected an int, got {seed!r}")
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        module = GarTransModule(GarTrans(num_joints=item["rest_joints"].shape[0],
                                         num_body_vertices=item["body_joint_dists"].shape[0],
                                         nystrom_dim=item["nystrom"].shape[1], **kwargs))
    return module.eval()


def lbs_predictor() -> Tuple[Predictor, Dict[str, Any]]:
    """``LBS only`` as a bench method: the rest garment skinned to each frame."""
    def make_batch(item: GarmentInputs, b: int) -> Callable[[], Any]:
        return item.cycled(b).skinned

    return Predictor(lambda ds, i, item: item.skinned(), make_batch,
                     "one call skinning `batch` frames"), \
        {"epochs": 0, "train_seconds": 0.0, "resumed_from_epoch": 0,
         "config": {"weights": "the skinning weights stored with each sequence"}}
