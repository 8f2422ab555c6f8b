"""Scores against a chaotic ground truth: an ensemble of simulated members.

Cloth simulation is chaotic: re-simulating a sequence with its rest garment moved by
1e-7 m moves Blender's frames by about 1 cm on `learn` (docs/results/benchmarks/
gt_noise_learn.md).  With ``K`` such members of one sequence, a deterministic
prediction is scored as weather forecasts are (WeatherBench 2), per frame, in cm
(:func:`~garmentgnn.metrics.garment_metrics.vertex_distance`):

* ``E_mean``: its distance to the ensemble mean (a model trained on mean squared error
  tends toward that mean);
* ``E_members``: its mean distance to the members;
* the floor: ``floor_mean``, the mean distance of a member to the ensemble mean (what a
  perfect simulator, one more member, scores as ``E_mean``; the ``E_members`` of the
  mean itself), and ``spread``, the mean distance between two members;
* ``skill = (E_LBS - E_mean) / (E_LBS - floor_mean)``, with ``E_LBS`` the LBS garment's
  distance to the ensemble mean: 0 is LBS, 1 is the floor, below 0 worse than LBS (above
  1: closer to the mean than a simulation, smoother than the physics).

:func:`ensemble_scores` gives one sequence's numbers over its scored frames, and the same
over the first ``early`` of them and over the rest; :func:`pooled_skill` pools skill
over sequences (sums of errors, so a long or chaotic sequence weighs by its error, not
by one ratio each).  :func:`sequence_record` keeps one sequence's numbers with its
per-frame curves (the spread-skill plot's), :func:`summary` pools a method's records
(frame-weighted, the skill pooled).  The members come from ``garmentgnn generate
--ensemble K`` (:mod:`garmentgnn.data.ensemble`); the bench's report and
``benchmarks/mgn_learn.py score`` show these numbers
(:mod:`garmentgnn.bench.ensemble_report`).
"""
from __future__ import annotations

from typing import Any, Dict, Iterable, Mapping, Optional

import torch
from torch import Tensor

from garmentgnn.metrics.garment_metrics import vertex_distance

__all__ = ["EARLY", "FRAME_KEYS", "ensemble_frames", "ensemble_scores", "pooled_skill",
           "sequence_record", "summary"]

#: the first scored frames reported apart from the rest
EARLY = 10
#: the per-frame numbers of :func:`ensemble_frames` (cm)
FRAME_KEYS = ("E_mean", "E_members", "E_LBS", "floor_mean", "spread")


def _check(pred: Tensor, members: Tensor, lbs: Tensor) -> None:
    if members.dim() != 4 or members.shape[-1] != 3:
        raise ValueError(f"`members`: expected [K, T, V, 3], got {tuple(members.shape)}")
    if members.shape[0] < 2:
        raise ValueError(f"`members`: an ensemble needs K >= 2 members, got "
                         f"{members.shape[0]}; simulate more members")
    for name, x in (("pred", pred), ("lbs", lbs)):
        if tuple(x.shape) != tuple(members.shape[1:]):
            raise ValueError(f"`{name}`: expected the members' frames and vertices "
                             f"{tuple(members.shape[1:])}, got {tuple(x.shape)}")


def ensemble_frames(pred: Tensor, members: Tensor, lbs: Tensor) -> Dict[str, Tensor]:
    """Per frame ``[T]`` (cm): ``E_mean``, ``E_members``, ``E_LBS`` (LBS to the ensemble
    mean), ``floor_mean`` and ``spread`` (module doc) of a prediction ``pred [T, V, 3]``
    against members ``[K, T, V, 3]`` (``K >= 2``) with the LBS garment ``lbs [T, V, 3]``."""
    _check(pred, members, lbs)
    members = members.double()
    pred, lbs = pred.double(), lbs.double()
    K = members.shape[0]
    mean = members.mean(0)
    to_member = torch.stack([vertex_distance(pred, m) for m in members])
    member_mean = torch.stack([vertex_distance(m, mean) for m in members])
    pairs = [vertex_distance(members[i], members[j]) for i in range(K) for j in range(i + 1, K)]
    return {"E_mean": vertex_distance(pred, mean), "E_members": to_member.mean(0),
            "E_LBS": vertex_distance(lbs, mean), "floor_mean": member_mean.mean(0),
            "spread": torch.stack(pairs).mean(0)}


def _summary(frames: Mapping[str, Tensor], keep: Tensor) -> Dict[str, float]:
    if not bool(keep.any()):
        return {}
    out = {k: float(v[keep].mean()) for k, v in frames.items()}
    gap = out["E_LBS"] - out["floor_mean"]
    out["skill"] = (out["E_LBS"] - out["E_mean"]) / gap if gap > 0 else float("nan")
    out["frames"] = int(keep.sum())
    return out


def ensemble_scores(pred: Tensor, members: Tensor, lbs: Tensor,
                    valid: Optional[Tensor] = None, early: int = EARLY) -> Dict[str, Dict]:
    """One sequence's ensemble numbers (module doc), means over its scored frames
    (``valid [T]``, default all): ``{"all": ..., "early": the first early scored frames,
    "late": the rest}``, each with ``skill`` and ``frames`` (a part without frames is
    empty)."""
    return _parts(ensemble_frames(pred, members, lbs), members.shape[1], valid, early)


def _parts(frames: Mapping[str, Tensor], T: int, valid: Optional[Tensor], early: int
           ) -> Dict[str, Dict]:
    keep = torch.ones(T, dtype=torch.bool) if valid is None else valid.bool().cpu()
    if keep.shape != (T,):
        raise ValueError(f"`valid`: expected [{T}] flags, got {tuple(keep.shape)}")
    if not isinstance(early, int) or isinstance(early, bool) or early < 0:
        raise ValueError(f"`early`: expected frames >= 0, got {early!r}")
    order = torch.cumsum(keep.long(), 0)  # 1 for the first scored frame
    first = keep & (order <= early)
    return {"all": _summary(frames, keep), "early": _summary(frames, first),
            "late": _summary(frames, keep & ~first)}


def pooled_skill(records: Iterable[Mapping[str, float]]) -> float:
    """Skill pooled over sequences, ``sum(E_LBS - E_mean) / sum(E_LBS - floor_mean)``
    over the records of :func:`ensemble_scores` (one part of each, e.g. ``"all"``), each
    weighted by its frames."""
    num = den = 0.0
    for r in records:
        if not r:
            continue
        n = r["frames"]
        num += n * (r["E_LBS"] - r["E_mean"])
        den += n * (r["E_LBS"] - r["floor_mean"])
    return num / den if den > 0 else float("nan")


def sequence_record(pred: Tensor, members: Tensor, lbs: Tensor,
                    valid: Optional[Tensor] = None, early: int = EARLY) -> Dict[str, Any]:
    """:func:`ensemble_scores` with the per-frame numbers of :func:`ensemble_frames`
    (``per_frame``: lists of ``T`` floats, ``None`` on the frames not scored), the
    scored frames' count (``frames``), ``skill`` ``None`` where it is undefined, and, in
    ``all``, ``E_each``: the error to each
    member alone (cm, over the scored frames: the score if that member were the ground
    truth)."""
    frames = ensemble_frames(pred, members, lbs)
    T = members.shape[1]
    out: Dict[str, Any] = _parts(frames, T, valid, early)
    keep = torch.ones(T, dtype=torch.bool) if valid is None else valid.bool().cpu()
    out["frames"] = int(keep.sum())
    for part in ("all", "early", "late"):  # JSON has no NaN: no skill where LBS is at the floor
        if out[part] and out[part]["skill"] != out[part]["skill"]:
            out[part]["skill"] = None
    if out["all"]:
        out["all"]["E_each"] = [float(vertex_distance(pred.double(), m.double())[keep].mean())
                                for m in members]
    out["per_frame"] = {k: [float(x) if ok else None for x, ok in zip(v.tolist(), keep)]
                        for k, v in frames.items()}
    return out


def summary(records: Iterable[Mapping[str, Any]]) -> Dict[str, Dict[str, float]]:
    """One method's records of :func:`sequence_record` pooled: per part (``all``, ``early``,
    ``late``) the frame-weighted means of :data:`FRAME_KEYS` (cm), ``skill`` pooled
    (:func:`pooled_skill`), ``frames`` and ``sequences``."""
    records = list(records)
    out: Dict[str, Dict[str, float]] = {}
    for part in ("all", "early", "late"):
        rs = [r[part] for r in records if r.get(part)]
        n = sum(r["frames"] for r in rs)
        if not n:
            continue
        out[part] = {k: sum(r[k] * r["frames"] for r in rs) / n for k in FRAME_KEYS}
        out[part].update(skill=pooled_skill(rs), frames=n, sequences=len(rs))
    return out
