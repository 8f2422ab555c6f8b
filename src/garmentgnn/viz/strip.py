"""A still of a trained GarTrans on one held-out sequence: rows simulated / GarTrans /
LBS only, columns evenly spaced frames (:func:`render_strip`, a matplotlib PNG).

``viz`` consumes trained models: it imports :mod:`garmentgnn.training`, never the
other way round (``tests/test_architecture.py``).
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Tuple, Union

import torch

from garmentgnn.models.inputs import HISTORY, NUM_LANDMARKS, NYSTROM_DIM
from garmentgnn.training.base import GarmentModule
from garmentgnn.data import SequenceChunks
from garmentgnn.training.evaluate import predict
from garmentgnn.viz.mpl import render_grid

__all__ = ["render_strip"]


@torch.no_grad()
def render_strip(module: GarmentModule, root: Union[str, os.PathLike], split: str,
                 path: Union[str, os.PathLike], index: int = 0, history: int = HISTORY,
                 num_landmarks: int = NUM_LANDMARKS, num_frames: int = 4) -> Tuple[Path, str]:
    """PNG: rows simulated / GarTrans / LBS only, columns evenly spaced frames of the
    ``index``-th sequence of ``split``; returns ``(path, sequence id)``."""
    ds = SequenceChunks(root, split, chunk=10 ** 9, history=history,
                        nystrom_dim=module.nystrom_dim or NYSTROM_DIM, num_landmarks=num_landmarks)
    item = ds[index]
    was_training = module.training
    module.eval()
    try:
        rows = [("simulated", item["gt"], (0.30, 0.55, 0.35)),
                ("GarTrans", predict(module, item, "gartrans"), (0.25, 0.45, 0.80)),
                ("LBS only", predict(module, item, "lbs"), (0.60, 0.60, 0.60))]
    finally:
        module.train(was_training)
    T = item["gt"].shape[0]
    frames = sorted({round(1 + i * (T - 2) / max(1, num_frames - 1)) for i in range(num_frames)})
    body_rgb = (0.82, 0.70, 0.60)
    cells = [[[(item["body_pos"][t], item["body_faces"], body_rgb), (P[t], item["faces"], rgb)]
              for t in frames] for _, P, rgb in rows]
    titles = [[f"{name}, frame {t}" for t in frames] for name, _, _ in rows]
    return render_grid(cells, path, titles=titles, elev=12, azim=-70), item["seq_id"]
