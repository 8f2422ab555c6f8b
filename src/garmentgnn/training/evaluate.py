"""Held-out evaluation of a trained GarTrans against the simulated ground truth and the
"LBS only" coarse garment (the paper's Tables 1 and 3 metrics, :func:`garmentgnn.metrics.evaluate`).

Modes, each over whole sequences of a split:

* ``"gartrans"``: frame-parallel inference (one ``encode_static`` per sequence, every
  frame in one batch -- the mode the paper trains and batches);
* ``"gartrans_ar"``: autoregressive rollout (:meth:`GarTrans.rollout`), the dynamic
  graph's velocity from the model's previous prediction;
* ``"lbs"``: the rest garment skinned with the simulator's transferred weights (Eq. 1),
  no learning.

Metrics are frame-weighted means over the split's frames the engine converged on (the
sequence files' ``converged``; ``excluded_frames`` counts the others, which are still
predicted and timed); ``ms_per_frame`` is wall time per frame of each mode (static branch
included), measured in the same loop.
"""
from __future__ import annotations

import time
from collections.abc import Sequence

import torch

from garmentgnn.metrics import evaluate_inputs
from garmentgnn.models.inputs import GarmentInputs
from garmentgnn.training.datamodule import SequenceChunks

MODES = ("gartrans", "gartrans_ar", "lbs")


def predict(module, item: GarmentInputs, mode: str) -> torch.Tensor:
    """``[B, V, 3]`` garment of every frame of ``item`` (a :class:`SequenceChunks` item)."""
    if mode == "lbs":
        return item.skinned()
    if mode not in MODES:
        raise ValueError(f"`mode`: expected one of {MODES}, got {mode!r}")
    return module(item, autoregressive=mode == "gartrans_ar")["final"]


@torch.no_grad()
def evaluate_split(module, root, split: str = "test", modes: Sequence[str] = MODES,
                   history: int | None = None, nystrom_dim: int | None = None,
                   num_landmarks: int = 64) -> dict[str, dict[str, float]]:
    """``{mode: {metric: frame-weighted mean, ..., "frames": n, "ms_per_frame": t}}``
    over every sequence of ``split`` under ``root``."""
    for mode in modes:
        if mode not in MODES:
            raise ValueError(f"`modes`: unknown {mode!r}; choose from {MODES}")
    hp = module.hparams
    ds = SequenceChunks(root, split, chunk=10 ** 9,
                        history=history or 3, nystrom_dim=nystrom_dim or hp.nystrom_dim,
                        num_landmarks=num_landmarks)
    if not len(ds):
        raise ValueError(f"`split`: no {split!r} sequences under {root}")
    was_training = module.training
    module.eval()
    sums: dict[str, dict[str, float]] = {m: {} for m in modes}
    frames, predicted, seconds = 0, 0, {m: 0.0 for m in modes}
    try:
        for idx in range(len(ds)):
            item = ds[idx]
            keep = ds.converged(idx)
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
        raise ValueError(f"`split`: no converged frame in the {split!r} sequences under {root}")
    out = {}
    for mode in modes:
        out[mode] = {k: v / frames for k, v in sums[mode].items()}
        out[mode].update(frames=frames, excluded_frames=predicted - frames,
                         ms_per_frame=1e3 * seconds[mode] / predicted)
    return out


def markdown_table(results: dict[str, dict[str, float]]) -> str:
    """The output of :func:`evaluate_split` as a markdown table (one row per mode)."""
    from garmentgnn.metrics import METRIC_UNITS
    metrics = ["E_dist", "E_vnorm", "E_fnorm", "E_len", "E_curv", "collision"]
    lines = ["| method | " + " | ".join(f"{m} ({METRIC_UNITS.get(m, '')})" for m in metrics)
             + " | ms/frame |", "|---" * (len(metrics) + 2) + "|"]
    for mode, res in results.items():
        lines.append(f"| {mode} | " + " | ".join(f"{res[m]:.4g}" for m in metrics if m in res)
                     + f" | {res['ms_per_frame']:.1f} |")
    return "\n".join(lines)


@torch.no_grad()
def render_strip(module, root, split: str, path, index: int = 0, history: int = 3,
                 num_landmarks: int = 64, num_frames: int = 4):
    """PNG: rows simulated / GarTrans / LBS only, columns evenly spaced frames of the
    ``index``-th sequence of ``split``; returns ``(path, sequence id)``."""
    from garmentgnn.viz import render_grid
    ds = SequenceChunks(root, split, chunk=10 ** 9, history=history,
                        nystrom_dim=module.hparams.nystrom_dim, num_landmarks=num_landmarks)
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
