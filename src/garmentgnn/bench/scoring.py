"""Scoring the learned methods on a dataset's test split, sequence by sequence.

:func:`score` runs a method on every test sequence and keeps, per sequence, the table
metrics (:func:`garmentgnn.metrics.evaluate_inputs`) and the static / dynamic split
(:func:`garmentgnn.metrics.split_inputs`), with what the sequence holds out (the
manifest's ``held_out``: its motion, body and/or garment are absent from the train
split).  :func:`aggregate` turns those into frame-weighted means over the whole split
and over each held-out group (:data:`GROUPS`); :func:`wilcoxon` compares two methods
sequence by sequence (a paired test over the same test sequences).
:func:`score_ensemble` scores a method against a dataset's ensemble ground truth
(:mod:`garmentgnn.bench.ensemble`, :mod:`garmentgnn.data.ensemble`) on the sequences it
holds.
"""
from __future__ import annotations

from typing import Any, Callable, Dict, List, Optional, Sequence

import torch
from scipy.stats import wilcoxon as _wilcoxon
from torch import Tensor

from garmentgnn.bench.ensemble import EARLY, sequence_record
from garmentgnn.metrics import evaluate_inputs, split_inputs

__all__ = ["GROUPS", "SPLIT_METRICS", "aggregate", "group_of", "score", "score_ensemble",
           "stratified", "wilcoxon"]

#: held-out groups: a sequence is in ``unseen X`` when X is the only thing it holds out,
#: in ``several unseen`` when it holds out more than one
GROUPS = ("unseen motion", "unseen body", "unseen garment", "several unseen")
#: the static / dynamic split's columns (cm)
SPLIT_METRICS = ("E_static", "E_dynamic")


def group_of(held_out: Sequence[str]) -> Optional[str]:
    """The :data:`GROUPS` entry of a sequence holding out ``held_out``; ``None`` for a
    sequence that holds out nothing."""
    held = sorted(set(held_out))
    if not held:
        return None
    if len(held) > 1:
        return GROUPS[3]
    if held[0] not in ("motion", "body", "garment"):
        raise ValueError(f"`held_out`: unknown factor {held[0]!r}")
    return f"unseen {held[0]}"


def stratified(records: Sequence[Dict[str, Any]], n: int) -> List[str]:
    """The ids of ``n`` of ``records`` (manifest items), taken in turn from each held-out
    group (:data:`GROUPS`, then sequences holding out nothing), each group in id order:
    a deterministic subset with every group as evenly represented as it can be."""
    if not isinstance(n, int) or n < 1:
        raise ValueError(f"`n`: expected a positive int, got {n!r}")
    pools: Dict[Optional[str], List[str]] = {}
    for r in sorted(records, key=lambda r: r["id"]):
        pools.setdefault(group_of(r.get("held_out", [])), []).append(r["id"])
    order = [g for g in (*GROUPS, None) if g in pools]
    out: List[str] = []
    while len(out) < min(n, len(records)):
        for g in order:
            if pools[g] and len(out) < n:
                out.append(pools[g].pop(0))
    return out


def score(predict: Callable[[int, Any], Tensor], test) -> List[Dict[str, Any]]:
    """Per test sequence: ``predict(i, item)`` (the garment ``[T, V, 3]`` of item ``i``
    of ``test``, a whole-sequence :class:`~garmentgnn.data.SequenceChunks`) scored
    against its simulation.  Metrics are frame means over the sequence's valid
    ground-truth frames (:meth:`~garmentgnn.data.SequenceChunks.valid`: converged, the
    body not through the cloth; ``frames``; the others are counted in ``excluded_frames``;
    a sequence with none is left out), ``collision`` renamed ``collision_rate``; raises
    ``RuntimeError`` for a prediction of the wrong shape or with non-finite coordinates."""
    out = []
    for i in range(len(test)):
        item = test[i]
        with torch.no_grad():
            P = predict(i, item)
        T, V = item.gt.shape[:2]
        if tuple(P.shape) != (T, V, 3):
            raise RuntimeError(f"predicted {tuple(P.shape)} for {item.seq_id}, expected "
                               f"{(T, V, 3)}")
        if not torch.isfinite(P).all():
            raise RuntimeError(f"{int((~torch.isfinite(P)).sum())} non-finite coordinates "
                               f"predicted for {item.seq_id}")
        keep = test.valid(i)  # frames that are not valid ground truth are left out
        if not bool(keep.any()):
            continue
        m = evaluate_inputs(P, item, keep)  # per-frame metrics averaged over kept frames
        m["collision_rate"] = m.pop("collision", float("nan"))
        split = split_inputs(P, item, keep)
        m.update({k: split[k] for k in SPLIT_METRICS})
        rec = test.records[test.index[i][0]]
        out.append({"sequence": item.seq_id, "frames": int(keep.sum()),
                    "excluded_frames": T - int(keep.sum()),
                    "held_out": list(rec.get("held_out", [])), "metrics": m})
    return out


def score_ensemble(predict: Callable[[int, Any], Tensor], test, ensemble: Dict[str, Any],
                   early: int = EARLY) -> List[Dict[str, Any]]:
    """Per sequence of ``test`` that ``ensemble`` holds (the ``sequences`` of
    :func:`garmentgnn.data.ensemble.load_ensemble`): ``predict(i, item)`` against its
    members, with the LBS garment (``item.skinned()``) as the skill's reference, as
    :func:`garmentgnn.bench.ensemble.sequence_record` (plus ``sequence`` and
    ``held_out``), on the frames that are valid ground truth in the dataset's sequence
    (``test.valid``) and in every member."""
    out = []
    for i in range(len(test)):
        entry = ensemble["sequences"].get(test.records[test.index[i][0]]["id"])
        if entry is None:
            continue
        item = test[i]
        with torch.no_grad():
            P = predict(i, item).detach().cpu()
            lbs = item.skinned().detach().cpu()
        keep = test.valid(i).cpu() & torch.as_tensor(entry["valid"])
        rec = sequence_record(P, torch.as_tensor(entry["positions"]), lbs, keep, early)
        held = test.records[test.index[i][0]].get("held_out", [])
        out.append(dict(rec, sequence=item.seq_id, held_out=list(held)))
    return out


def aggregate(per_sequence: Sequence[Dict[str, Any]],
              keep: Optional[Callable[[Dict[str, Any]], bool]] = None
              ) -> Dict[str, Dict[str, float]]:
    """Frame-weighted means of the per-sequence metrics: ``{"all": ..., <group>: ...}``
    (groups without sequences left out); ``keep`` filters the sequences first."""
    seqs = [s for s in per_sequence if keep is None or keep(s)]

    def mean(ss: Sequence[Dict[str, Any]]) -> Dict[str, float]:
        n = sum(s["frames"] for s in ss)
        keys = ss[0]["metrics"].keys()
        return {k: sum(s["metrics"][k] * s["frames"] for s in ss) / n for k in keys}

    out: Dict[str, Dict[str, float]] = {}
    if seqs:
        out["all"] = mean(seqs)
    for g in GROUPS:
        ss = [s for s in seqs if group_of(s["held_out"]) == g]
        if ss:
            out[g] = mean(ss)
    return out


def wilcoxon(a: Dict[str, float], b: Dict[str, float]) -> Dict[str, Any]:
    """Paired two-sided Wilcoxon signed-rank test of two methods' per-sequence errors
    ``{sequence: value}`` over the sequences both have (scipy); ``median_diff`` is the
    median of ``a - b`` (negative: ``a`` lower), ``wins`` the share of sequences where
    ``a`` is lower."""
    common = sorted(set(a) & set(b))
    if len(common) < 2:
        raise ValueError(f"`a`, `b`: need at least 2 common sequences, got {len(common)}")
    x = torch.tensor([a[s] for s in common], dtype=torch.float64)
    y = torch.tensor([b[s] for s in common], dtype=torch.float64)
    d = x - y
    if bool((d == 0).all()):
        p = 1.0
    else:
        p = float(_wilcoxon(x.numpy(), y.numpy()).pvalue)
    return {"n": len(common), "median_diff": float(d.median()), "p": p,
            "wins": float((d < 0).double().mean())}
