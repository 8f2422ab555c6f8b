"""Held-out evaluation of a trained GarTrans against the simulated ground truth and the
"LBS only" coarse garment (the paper's Tables 1 and 3 metrics, :func:`garmentgnn.metrics.evaluate`).

Modes, each over whole sequences of a split:

* ``"gartrans"``: frame-parallel inference (one ``encode_static`` per sequence, every
  frame in one batch -- the mode the paper trains and batches);
* ``"gartrans_ar"``: autoregressive rollout (:meth:`GarTrans.rollout`), the dynamic
  graph's velocity from the model's previous prediction;
* ``"lbs"``: the rest garment skinned with the simulator's transferred weights (Eq. 1),
  no learning.

Metrics are frame-weighted means over the split's valid ground-truth frames
(:meth:`garmentgnn.data.SequenceChunks.valid`: the engine converged and the body is not
through the cloth; ``excluded_frames`` counts the others, which are still predicted and
timed); ``ms_per_frame`` is wall time per frame of each mode (static branch
included), measured in the same loop.
"""
from __future__ import annotations

import time
from typing import Dict, Optional, Sequence

import torch

from garmentgnn.models.inputs import HISTORY, NUM_LANDMARKS, NYSTROM_DIM
from garmentgnn.metrics import METRIC_UNITS, evaluate_inputs
from garmentgnn.models.inputs import GarmentInputs
from garmentgnn.data import SequenceChunks

MODES = ("gartrans", "gartrans_ar", "lbs")


def predict(module, item: GarmentInputs, mode: str) -> torch.Tensor:
    """``[B, V, 3]`` garment of every frame of ``item`` (a :class:`SequenceChunks` item):
    the module's held-out evaluation (``predict_garment``), its rollout on its own output
    (``gartrans_ar``: ``predict_rollout``, a method that has one) or LBS."""
    if mode == "lbs":
        return item.skinned()
    if mode not in MODES:
        raise ValueError(f"`mode`: expected one of {MODES}, got {mode!r}")
    if mode == "gartrans_ar":
        rollout = getattr(module, "predict_rollout", None)
        if rollout is None:
            raise ValueError(f"`mode`: {type(module).__name__} has no rollout on its own "
                             f"output ('gartrans_ar'); use 'gartrans'")
        return rollout(item)
    return module.predict_garment(item)


@torch.no_grad()
def evaluate_split(module, root, split: str = "test", modes: Optional[Sequence[str]] = None,
                   history: Optional[int] = None, nystrom_dim: Optional[int] = None,
                   num_landmarks: int = NUM_LANDMARKS) -> Dict[str, Dict[str, float]]:
    """``{mode: {metric: frame-weighted mean, ..., "frames": n, "ms_per_frame": t}}``
    over every sequence of ``split`` under ``root``; ``modes`` default: every mode the
    module has."""
    if modes is None:  # every mode the module has
        modes = [m for m in MODES if m != "gartrans_ar" or hasattr(module, "predict_rollout")]
    for mode in modes:
        if mode not in MODES:
            raise ValueError(f"`modes`: unknown {mode!r}; choose from {MODES}")
    ds = SequenceChunks(root, split, chunk=10 ** 9, history=history or HISTORY,
                        nystrom_dim=nystrom_dim or module.nystrom_dim or NYSTROM_DIM,
                        num_landmarks=num_landmarks)
    if not len(ds):
        raise ValueError(f"`split`: no {split!r} sequences under {root}")
    was_training = module.training
    module.eval()
    sums: Dict[str, Dict[str, float]] = {m: {} for m in modes}
    frames, predicted, seconds = 0, 0, {m: 0.0 for m in modes}
    try:
        for idx in range(len(ds)):
            item = ds[idx]
            keep = ds.valid(idx)
            B = int(keep.sum())
            frames += B
            predicted += item["gt"].shape[0]
            for mode in modes:
                t0 = time.perf_counter()
                pred = predict(module, item, mode)
                seconds[mode] += time.perf_counter() - t0
                if B:
                    res = evaluate_inputs(pred, item, keep)
                    for k, v in res.items():
                        sums[mode][k] = sums[mode].get(k, 0.0) + v * B
    finally:
        module.train(was_training)
    if not frames:
        raise ValueError(f"`split`: no valid ground-truth frame in the {split!r} sequences "
                         f"under {root}")
    out = {}
    for mode in modes:
        out[mode] = {k: v / frames for k, v in sums[mode].items()}
        out[mode].update(frames=frames, excluded_frames=predicted - frames,
                         ms_per_frame=1e3 * seconds[mode] / predicted)
    return out


#: the paper's metrics (Tables 1 and 3), in the order of their columns
TABLE_METRICS = ("E_dist", "E_vnorm", "E_fnorm", "E_len", "E_curv", "collision")


def markdown_table(results: Dict[str, Dict[str, float]]) -> str:
    """The output of :func:`evaluate_split` (or any ``{row: {metric: value}}``) as a
    markdown table, one row per mode; the ``ms/frame`` column when every row has
    ``ms_per_frame``, a missing metric as ``-``."""
    timed = all("ms_per_frame" in res for res in results.values())
    head = [f"{m} ({METRIC_UNITS.get(m, '')})" for m in TABLE_METRICS]
    head += ["ms/frame"] if timed else []
    lines = ["| method | " + " | ".join(head) + " |", "|---" * (len(head) + 1) + "|"]
    for mode, res in results.items():
        cells = [f"{res[m]:.4g}" if m in res else "-" for m in TABLE_METRICS]
        cells += [f"{res['ms_per_frame']:.1f}"] if timed else []
        lines.append(f"| {mode} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
