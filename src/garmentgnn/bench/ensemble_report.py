"""The report of methods scored against an ensemble ground truth (:mod:`garmentgnn.bench.
ensemble`, :func:`garmentgnn.bench.scoring.score_ensemble`): its table, its paired tests
and gaps, and the spread-skill figure; the bench's learned report and
``benchmarks/mgn_learn.py score`` show it (docs/bench.md, "Scores against an ensemble
ground truth").

A gap between two methods is **one chaos explains** when its sign depends on which member
is taken as the ground truth: scored against member ``k`` alone the gap is ``g_k``
(frame-weighted over the sequences), and the ``g_k`` do not all have one sign.  Such a gap
is what scoring against one simulated sequence cannot decide.
"""
from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np

from garmentgnn._plotting import pyplot
from garmentgnn.bench import scoring
from garmentgnn.bench.ensemble import EARLY, summary
from garmentgnn.bench.tables import save_figure, table
from garmentgnn.data.perturb import PERTURB_M

__all__ = ["gap", "markdown", "plot", "results", "seed_mean"]

Records = Mapping[str, Sequence[Dict[str, Any]]]


def gap(a: Sequence[Dict[str, Any]], b: Sequence[Dict[str, Any]]) -> Dict[str, Any]:
    """Method ``a`` against ``b`` over the sequences both scored: ``gap`` (cm, ``a`` minus
    ``b`` of the frame-weighted error to the ensemble mean), ``gap_each`` (the same against
    each member alone), ``chaos`` (the ``gap_each`` differ in sign: the gap is one chaos
    explains), ``flipped`` (the sequences on which the same holds: which method is ahead
    there depends on the member) and the paired Wilcoxon test of the per-sequence errors
    to the ensemble mean (:func:`garmentgnn.bench.scoring.wilcoxon`; ``None`` under 2
    sequences)."""
    ra = {r["sequence"]: r for r in a if r.get("all")}
    rb = {r["sequence"]: r for r in b if r.get("all")}
    common = sorted(set(ra) & set(rb))
    if not common:
        return {"sequences": 0}
    n = sum(ra[s]["all"]["frames"] for s in common)

    def pooled(get) -> float:
        return sum(get(s) * ra[s]["all"]["frames"] for s in common) / n
    K = min(len(ra[s]["all"]["E_each"]) for s in common)
    each = [pooled(lambda s, k=k: ra[s]["all"]["E_each"][k] - rb[s]["all"]["E_each"][k])
            for k in range(K)]
    test = scoring.wilcoxon({s: ra[s]["all"]["E_mean"] for s in common},
                            {s: rb[s]["all"]["E_mean"] for s in common}) \
        if len(common) >= 2 else None
    flipped = sum(min(d) < 0 < max(d) for d in (
        [x - y for x, y in zip(ra[s]["all"]["E_each"], rb[s]["all"]["E_each"])]
        for s in common))
    return {"sequences": len(common),
            "gap": pooled(lambda s: ra[s]["all"]["E_mean"] - rb[s]["all"]["E_mean"]),
            "gap_each": each, "chaos": min(each) < 0 < max(each),
            "flipped": flipped, "wilcoxon": test}


def _mean_tree(xs: Sequence[Any]) -> Any:
    x = xs[0]
    if isinstance(x, dict):
        return {k: _mean_tree([y[k] for y in xs]) for k in x}
    if isinstance(x, list):
        return [_mean_tree([y[i] for y in xs]) for i in range(len(x))]
    if isinstance(x, bool) or not isinstance(x, (int, float)) or any(y is None for y in xs):
        return x if all(y == x for y in xs) else None
    return float(np.mean(xs))


def seed_mean(per_seed: Sequence[Sequence[Dict[str, Any]]]) -> List[Dict[str, Any]]:
    """One method's records of several training seeds as one record per sequence, every
    number the mean over the seeds (so paired tests stay paired over sequences)."""
    by_seq: Dict[str, List[Dict[str, Any]]] = {}
    for recs in per_seed:
        for r in recs:
            by_seq.setdefault(r["sequence"], []).append(r)
    return [_mean_tree(rs) for _, rs in sorted(by_seq.items())]


def results(per_method: Records) -> Dict[str, Any]:
    """Per method its :func:`~garmentgnn.bench.ensemble.summary` and per-sequence skill;
    per pair of methods its :func:`gap`."""
    out: Dict[str, Any] = {"methods": {}, "pairs": {}}
    for m, recs in per_method.items():
        out["methods"][m] = dict(summary(recs), skill_per_sequence={
            r["sequence"]: r["all"]["skill"] for r in recs if r.get("all")})
    for a, b in itertools.combinations(per_method, 2):
        out["pairs"][f"{a} vs {b}"] = gap(per_method[a], per_method[b])
    return out


def _f(x: Optional[float], digits: int = 3) -> str:
    return "—" if x is None or not np.isfinite(x) else f"{x:.{digits}g}"


def markdown(per_method: Records, png: Optional[str] = None, heading: str = "###",
             members: Optional[int] = None) -> List[str]:
    """The section (empty without records): the table, the gaps and the figure."""
    res = results({m: r for m, r in per_method.items() if r})
    if not res["methods"]:
        return []
    seqs = max(v.get("all", {}).get("sequences", 0) for v in res["methods"].values())
    lines = [f"{heading} Against the ensemble ground truth", "",
             f"{seqs} test sequences, each simulated again "
             + (f"{members} times " if members else "")
             + f"with the rest garment moved by {PERTURB_M:g} m (`garmentgnn generate "
             "--ensemble`), "
             "scored on the frames valid in the dataset's sequence and every member. E_mean: "
             "error to the members' mean; E_members: mean error to a member; floor: a "
             "member's distance to the mean (a perfect simulator's E_mean); spread: the "
             "mean distance between two members; skill = (E_LBS - E_mean) / (E_LBS - "
             "floor), pooled over sequences (0: LBS, 1: a perfect simulator); early: the "
             f"first {EARLY} scored frames, late: the rest (cm; docs/bench.md).", ""]
    rows = []
    for m, v in res["methods"].items():
        a, e, late = v.get("all", {}), v.get("early", {}), v.get("late", {})
        sk = [x for x in v["skill_per_sequence"].values() if x is not None and np.isfinite(x)]
        rows.append([m, _f(a.get("E_mean")), _f(a.get("E_members")), _f(a.get("floor_mean")),
                     _f(a.get("spread")), _f(a.get("skill"), 2),
                     _f(float(np.median(sk)) if sk else None, 2), _f(e.get("E_mean")),
                     _f(e.get("floor_mean")), _f(late.get("E_mean")),
                     _f(late.get("floor_mean")), str(a.get("sequences", 0))])
    lines += table(["method", "E_mean", "E_members", "floor", "spread", "skill (pooled)",
                    "skill (median seq.)", "early E_mean", "early floor", "late E_mean",
                    "late floor", "sequences"], rows) + [""]
    rows = []
    for name, g in res["pairs"].items():
        if not g.get("sequences"):
            continue
        w = g["wilcoxon"]
        rows.append([name, f"{g['gap']:+.3g}", f"{min(g['gap_each']):+.3g} .. "
                     f"{max(g['gap_each']):+.3g}", "yes" if g["chaos"] else "no",
                     f"{g['flipped']} of {g['sequences']}",
                     "—" if w is None else f"{w['p']:.2g}"])
    if rows:
        lines += ["Gaps (first minus second, E_mean, cm): against each member alone the gap "
                  "ranges as shown; where its sign flips, chaos explains it. Sequences "
                  "decided by the member: those on which which method is ahead depends on "
                  "the member. p: paired Wilcoxon over the sequences.", ""]
        lines += table(["methods", "gap", "gap against one member", "chaos explains it",
                        "sequences decided by the member", "p"], rows) + [""]
    if png:
        lines += [f"![Spread and skill per frame]({png})", ""]
    return lines


def _per_frame(recs: Sequence[Dict[str, Any]], key: str) -> np.ndarray:
    """Per frame, the mean over sequences of ``key`` (NaN where no sequence scores it)."""
    T = max(len(r["per_frame"][key]) for r in recs)
    x = np.full((len(recs), T), np.nan)
    for i, r in enumerate(recs):
        v = [np.nan if y is None else y for y in r["per_frame"][key]]
        x[i, :len(v)] = v
    with np.errstate(all="ignore"):
        counts = np.isfinite(x).sum(0)
        return np.where(counts > 0, np.nansum(x, 0) / np.maximum(counts, 1), np.nan)


def plot(per_method: Records, path, title: str = "") -> Optional[Path]:
    """Spread-skill: per frame, each method's error to the ensemble mean (mean over
    sequences) with the floor and the members' spread (left); per sequence, each method's
    error against the floor, the diagonal being the floor (right).  ``None`` without
    records."""
    per_method = {m: [r for r in rs if r.get("all")] for m, rs in per_method.items()}
    per_method = {m: rs for m, rs in per_method.items() if rs}
    if not per_method:
        return None
    plt = pyplot()
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12.5, 4.6))
    any_recs = next(iter(per_method.values()))
    for m, recs in per_method.items():
        y = _per_frame(recs, "E_mean")
        ax.plot(np.arange(len(y)), y, lw=1.6, label=m)
        bx.scatter([r["all"]["floor_mean"] for r in recs], [r["all"]["E_mean"] for r in recs],
                   s=16, alpha=0.8, label=m)
    for key, style, name in (("floor_mean", "--", "floor (member to mean)"),
                             ("spread", ":", "spread (member to member)")):
        y = _per_frame(any_recs, key)
        ax.plot(np.arange(len(y)), y, color="black", ls=style, lw=1.4, label=name)
    ax.axvspan(*_early_span(any_recs), color="grey", alpha=0.12,
               label=f"first {EARLY} scored frames")
    ax.set(yscale="log", xlabel="frame", ylabel="cm (log), mean over sequences",
           title="Error to the ensemble mean per frame")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    floors = [r["all"]["floor_mean"] for rs in per_method.values() for r in rs]
    errs = [r["all"]["E_mean"] for rs in per_method.values() for r in rs]
    lo = max(min(floors + errs) * 0.8, 1e-6)
    hi = max(floors + errs) * 1.25
    bx.plot([lo, hi], [lo, hi], color="black", ls="--", lw=1, label="the floor (E = floor)")
    bx.set(xscale="log", yscale="log", xlabel="floor of the sequence (cm, log)",
           ylabel="error to the ensemble mean (cm, log)", xlim=(lo, hi), ylim=(lo, hi),
           title="Per sequence: error against the floor")
    bx.grid(True, which="both", alpha=0.3)
    bx.legend(fontsize=7)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)


def _early_span(recs: Sequence[Dict[str, Any]]) -> Tuple[float, float]:
    """From the first scored frame to the last of the first :data:`EARLY` scored frames
    (the earliest over sequences), each widened by a half frame."""
    spans = []
    for r in recs:
        scored = [t for t, y in enumerate(r["per_frame"]["E_mean"]) if y is not None]
        if scored:
            spans.append((scored[0], scored[min(EARLY, len(scored)) - 1]))
    if not spans:
        return -0.5, 0.5
    return min(a for a, _ in spans) - 0.5, min(b for _, b in spans) + 0.5
