"""The "Held-out test split" section of the bench report: the learned methods' records
(:mod:`garmentgnn.bench.learned`) as a table shaped like the paper's Tables 1 and 3, and
their error-against-run-time plot; on a dataset with an ensemble ground truth, their
scores against it (:mod:`garmentgnn.bench.ensemble_report`)."""
from __future__ import annotations

import statistics
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

from garmentgnn.bench import ensemble_report, scoring
from garmentgnn.bench.learned import KIND
from garmentgnn.bench.methods import (DA, FULL, GARTRANS, HOOD, LBS, LONG, METHOD_NAMES, MGN,
                                      NCS)
from garmentgnn.bench.tables import (METRICS, UNITS, fmt, mean_std, plot_points, plot_summary,
                                     table)

__all__ = ["comparison_markdown", "engine_points", "ensemble_markdown", "ensemble_methods",
           "markdown", "per_sequence", "plot", "plot_engines", "plot_ensemble", "summary"]

#: the record kind of :mod:`garmentgnn.bench.engines`
ENGINE_KIND = "engine"
BASELINES_ORDER = (DA, HOOD, NCS, MGN)


def _ordered(records: Sequence[Dict[str, Any]]) -> List[str]:
    seen = [m for m in METHOD_NAMES + (LONG,) if any(r["method"] == m for r in records)]
    return seen + sorted({r["method"] for r in records} - set(seen))


def _scored(rs: Sequence[Dict[str, Any]]) -> str:
    """What the learned records were scored on, in words."""
    n = {len(r["per_sequence"]) for r in rs if r.get("per_sequence")}
    frames = {r.get("test_frames") for r in rs if r.get("per_sequence")}
    excluded = {sum(s.get("excluded_frames", 0) for s in r["per_sequence"])
                for r in rs if r.get("per_sequence")}
    if len(n) == 1 and len(frames) == 1:
        left = excluded.pop() if len(excluded) == 1 else None
        return (f"the same {n.pop()} test sequences ({frames.pop()} frames"
                + (f"; {left} frames the engine did not converge on left out" if left else "")
                + ")")
    return "every test sequence"


def summary(records: Sequence[Dict[str, Any]]) -> Dict[str, Dict[str, Any]]:
    """Per method: mean / std over seeds of the metrics, latency, throughput and train
    time of its ok ``learned`` records."""
    rs = [r for r in records if r["kind"] == KIND]
    out: Dict[str, Dict[str, Any]] = {}
    for method in _ordered(rs):
        mine = [r for r in rs if r["method"] == method]
        ok = [r for r in mine if r["status"] == "ok"]
        entry: Dict[str, Any] = {"records": len(mine), "failed": len(mine) - len(ok)}
        vals = {m: [r["metrics"][m] for r in ok] for m in METRICS}
        vals.update({t: [r["timing"][t] for r in ok] for t in ("latency_ms", "throughput_fps")})
        vals["train_seconds"] = [r["train_seconds"] for r in ok]
        for k, v in vals.items():
            if v:
                entry[k] = dict(zip(("mean", "std"), mean_std(v)), n=len(v))
        out[method] = entry
    return out


def markdown(records: Sequence[Dict[str, Any]], png: Optional[str] = None) -> List[str]:
    """The "Held-out test split" section of ``report.md`` (empty without records)."""
    rs = [r for r in records if r["kind"] == KIND]
    if not rs:
        return []
    ds = next((r.get("dataset") for r in rs if r.get("dataset")), {}) or {}
    devices = sorted({r["device"] for r in rs if r.get("device")})
    lines = ["## Held-out test split (learned methods; shaped like Tables 1 and 3)", "",
             f"Dataset `{ds.get('name')}` (`{ds.get('root')}`, fingerprint "
             f"{str(ds.get('fingerprint'))[:8]}, content SHA-256 "
             f"`{str(ds.get('content_sha256'))[:16]}`): "
             f"{ds.get('sequences', {}).get('train')} train / "
             f"{ds.get('sequences', {}).get('test')} test sequences, "
             f"{ds.get('frames', {}).get('test')} test frames. Every method is trained on "
             "the train split (NCS-style: one model per test garment, on that garment's own "
             "test poses, physics terms only -- never its simulated positions) and scored "
             f"on the valid ground-truth frames of {_scored(rs)} against the simulation "
             "(frame-weighted means). A different case set from the simulator tables above: "
             "these rows are not comparable with them. Mean ± std over training seeds. "
             "latency: ms per frame at batch 1; throughput: frames/s at the best batch; "
             "train: wall time of the training epochs."
             + (f" Trained on: {', '.join(devices)}." if devices else ""), ""]
    rows = []
    for method in _ordered(rs):
        mine = [r for r in rs if r["method"] == method]
        ok = [r for r in mine if r["status"] == "ok"]
        label = method + (" (reference, no learning)" if method == LBS else "")
        if len(ok) < len(mine):
            label += f" ({len(mine) - len(ok)}/{len(mine)} failed)"
        if not ok:
            rows.append([label] + ["failed"] * (len(METRICS) + 5))
            continue

        def cell(get: Callable[[Dict[str, Any]], float]) -> str:
            return fmt([get(r) for r in ok])
        epochs = sorted({int(r.get("epochs", 0)) for r in ok})
        phases = sorted({int(r["phase"]) for r in ok if "phase" in r})
        rows.append([label] + [cell(lambda r, m=m: r["metrics"][m]) for m in METRICS]
                    + [cell(lambda r: r["timing"]["latency_ms"]),
                       cell(lambda r: r["timing"]["throughput_fps"]),
                       cell(lambda r: r["train_seconds"]),
                       "/".join(map(str, epochs)), "/".join(map(str, phases)) or "—",
                       str(len(ok))])
    hdr = ["method"] + [f"{m} ({UNITS[m]})" for m in METRICS] + [
        "latency (ms)", "throughput (fps)", "train (s)", "epochs", "final phase", "seeds"]
    lines += table(hdr, rows) + [""]
    if png:
        lines += ["Error against run time of these methods: a separate plot from the "
                  "simulator budgets' (other cases).", "", f"![Pareto, learned]({png})", ""]
    return lines


def plot(records: Sequence[Dict[str, Any]], path,
         bands: Sequence[Tuple[str, float]] = ()) -> Optional[Path]:
    """``pareto_learned.png``: log latency (batch 1) against E_dist of the learned
    methods' means, ``bands`` (the ground truth's noise floors) shaded; ``None`` without
    ok records."""
    return plot_summary(summary(records), path, "Held-out test split: error against run time",
                        bands=bands)


# --------------------------------------------------------------------------- comparison
#: the significance level of the targets
ALPHA = 0.05


def per_sequence(records: Sequence[Dict[str, Any]], method: str,
                 metric: str = "E_dist") -> Dict[str, float]:
    """``{sequence: metric}`` of ``method``, the mean over its ok seeds' records."""
    vals: Dict[str, List[float]] = {}
    for r in records:
        if r["kind"] == KIND and r["method"] == method and r["status"] == "ok":
            for s in r.get("per_sequence") or ():
                vals.setdefault(s["sequence"], []).append(s["metrics"][metric])
    return {k: statistics.fmean(v) for k, v in vals.items()}


def _ok(records: Sequence[Dict[str, Any]], method: str) -> List[Dict[str, Any]]:
    return [r for r in records if r["kind"] == KIND and r["method"] == method
            and r["status"] == "ok" and r.get("groups") is not None]


def _mean(rs: Sequence[Dict[str, Any]], get: Callable[[Dict[str, Any]], Optional[float]]
          ) -> Optional[float]:
    v = [x for x in (get(r) for r in rs) if x is not None]
    return statistics.fmean(v) if v else None


def _verdict(p: float) -> str:
    return f"significant (p < {ALPHA})" if p < ALPHA else "not significant"


def comparison_markdown(records: Sequence[Dict[str, Any]],
                        engines_png: Optional[str] = None) -> List[str]:
    """Held-out groups, the static / dynamic split, paired significance tests, the
    targets and the engines (empty without learned records carrying per-sequence
    results)."""
    rs = [r for r in records if r["kind"] == KIND and r.get("per_sequence")]
    if not rs:
        return []
    methods = _ordered(rs)
    lines = ["### By held-out group", "",
             "E_dist (cm) per group of test sequences (frame-weighted; mean ± std over "
             "seeds); in brackets the change against LBS only. A sequence is in `unseen X` "
             "when X is the one thing the train split lacks; `several unseen` holds out "
             "more than one.", ""]
    groups = [g for g in scoring.GROUPS if any(g in (r.get("groups") or {}) for r in rs)]
    lbs = _ok(records, LBS)

    def of(r: Dict[str, Any], g: str) -> Dict[str, float]:
        return r["metrics"] if g == "all" else r["groups"].get(g, {})

    def group_cell(ok: List[Dict[str, Any]], g: str, metric: str = "E_dist") -> str:
        v = [of(r, g)[metric] for r in ok if metric in of(r, g)]
        if not v:
            return "—"
        ref = _mean(lbs, lambda r: of(r, g).get(metric))
        rel = f" [{100 * (statistics.fmean(v) / ref - 1):+.0f}%]" if ref else ""
        return fmt(v) + rel
    rows = [[m] + [group_cell(_ok(records, m), g) for g in ["all"] + groups]
            for m in methods if _ok(records, m)]
    lines += table(["method", "all test"] + groups, rows) + [""]
    lines += ["### Static drape and dynamics", "",
              "The error split of `garmentgnn.metrics.static_dynamic_split` (docs/bench.md, "
              "\"Where LBS's error is\"), frame-weighted over all test sequences; in brackets "
              "the share of LBS's error of that part the method removes.", ""]
    rows = []
    for m in methods:
        ok = _ok(records, m)
        if not ok or "E_static" not in ok[0]["metrics"]:
            continue
        row = [m]
        for k in scoring.SPLIT_METRICS:
            ref = _mean(lbs, lambda r: r["metrics"].get(k))
            v = [r["metrics"][k] for r in ok]
            row.append(fmt(v) + (f" [{100 * (1 - statistics.fmean(v) / ref):.0f}% removed]"
                                 if ref else ""))
        rows.append(row)
    lines += table(["method", "E_static (cm)", "E_dynamic (cm)"], rows) + [""]
    lines += _significance(records, methods)
    lines += _targets(records, groups)
    lines += _engines(records, engines_png)
    return lines


def _significance(records: Sequence[Dict[str, Any]], methods: Sequence[str]) -> List[str]:
    full = per_sequence(records, FULL)
    if len(full) < 2:
        return []
    lines = ["### Paired tests", "",
             f"Two-sided Wilcoxon signed-rank tests over the test sequences (per sequence: "
             f"the mean over each method's seeds), {FULL} against each other method; "
             f"median difference = {FULL} minus the other (negative: {FULL} lower).", ""]
    rows = []
    for m in methods:
        other = per_sequence(records, m)
        if m == FULL or len(set(full) & set(other)) < 2:
            continue
        w = scoring.wilcoxon(full, other)
        rows.append([m, "E_dist", str(w["n"]), f"{w['median_diff']:+.3g}",
                     f"{100 * w['wins']:.0f}%", f"{w['p']:.2g}", _verdict(w["p"])])
    if len(set(full) & set(per_sequence(records, LBS))) >= 2:
        for k in METRICS[1:5]:
            w = scoring.wilcoxon(per_sequence(records, FULL, k), per_sequence(records, LBS, k))
            rows.append([LBS, k, str(w["n"]), f"{w['median_diff']:+.3g}",
                         f"{100 * w['wins']:.0f}%", f"{w['p']:.2g}", _verdict(w["p"])])
    return lines + table(["against", "metric", "sequences", "median diff", f"{FULL} lower on",
                          "p", "verdict"], rows) + [""]


def _targets(records: Sequence[Dict[str, Any]], groups: Sequence[str]) -> List[str]:
    full, lbs = _ok(records, FULL), _ok(records, LBS)
    if not full or not lbs:
        return []

    def m(rs, key, g="all"):
        return _mean(rs, lambda r: (r["metrics"] if g == "all" else r["groups"].get(g, {}))
                     .get(key))
    lines = ["### Targets", ""]
    cuts = {g: 1 - m(full, "E_dist", g) / m(lbs, "E_dist", g) for g in groups
            if m(full, "E_dist", g) is not None and m(lbs, "E_dist", g)}
    ok30 = bool(cuts) and all(c >= 0.3 for c in cuts.values())
    lines.append(f"- E_dist at least 30% below LBS on every held-out group: "
                 f"**{'met' if ok30 else 'missed'}** ("
                 + ", ".join(f"{g}: {100 * c:.0f}%" for g, c in cuts.items()) + ")")
    better = [k for k in METRICS[:5] if m(full, k) < m(lbs, k)]
    pairs = {k: (per_sequence(records, FULL, k), per_sequence(records, LBS, k)) for k in better}
    sig = [k for k, (a, b) in pairs.items()
           if len(set(a) & set(b)) >= 2 and scoring.wilcoxon(a, b)["p"] < ALPHA]
    # met: lower on the mean of every metric, each by a significant paired difference
    met = ("missed" if len(better) < 5 else "met" if len(sig) == 5 else "not significant")
    lines.append(f"- lower than LBS on all five metrics: **{met}**"
                 f" (lower on {', '.join(better) or 'none'}; significantly, p < {ALPHA}, "
                 f"on {', '.join(sig) or 'none'})")
    for b in BASELINES_ORDER:
        rb = _ok(records, b)
        if rb:
            won = [k for k in METRICS[1:5] if m(full, k) < m(rb, k)]
            hit = m(full, "E_dist") < m(rb, "E_dist") and len(won) >= 3
            lines.append(f"- ahead of {b} on E_dist and at least 3 of the other four: "
                         f"**{'met' if hit else 'missed'}** (E_dist {m(full, 'E_dist'):.3g} vs "
                         f"{m(rb, 'E_dist'):.3g} cm; ahead on {', '.join(won) or 'none'})")
    per_full = per_sequence(records, FULL)
    for a in [x for x in GARTRANS if x != FULL and _ok(records, x)]:
        other = per_sequence(records, a)
        if len(set(per_full) & set(other)) < 2:
            continue
        w = scoring.wilcoxon(per_full, other)
        ahead = m(full, "E_dist") < m(_ok(records, a), "E_dist")
        word = ("shown" if ahead and w["p"] < ALPHA else
                "refuted" if not ahead and w["p"] < ALPHA else "not significant")
        lines.append(f"- Table 1 ordering, {FULL} ahead of {a} on E_dist: **{word}** "
                     f"({m(full, 'E_dist'):.4g} vs {m(_ok(records, a), 'E_dist'):.4g} cm, "
                     f"p = {w['p']:.2g})")
    coll = m(full, "collision_rate")
    lines.append(f"- collision rate at most 1% of vertices: **{'met' if coll <= 1 else 'missed'}**"
                 f" ({coll:.3g}%)")
    return lines + [""]


def _engines(records: Sequence[Dict[str, Any]], png: Optional[str]) -> List[str]:
    eng = [r for r in records if r["kind"] == ENGINE_KIND and r["status"] == "ok"]
    if not eng:
        return []
    seqs = sorted({r["sequence"] for r in eng})
    lines = ["### Physics engines", "",
             f"Each engine setting re-simulates {len(seqs)} test sequences "
             f"({', '.join(f'`{s}`' for s in seqs)}) and is scored against the dataset's "
             "own simulation (the finest setting: ground truth) over the frames it "
             "simulated; the learned methods' rows are their errors on the same sequences "
             "(all their frames). time: seconds per frame (engines: the simulation per "
             "simulated frame, pre-roll included; learned: latency at batch 1).", ""]
    rows = []
    for name, e_dist, sec, n in engine_points(records):
        rows.append([name, f"{e_dist:.3g}", f"{sec:.3g}", str(n)])
    lines += table(["method", "E_dist (cm)", "time (s/frame)", "sequences"], rows) + [""]
    if png:
        lines += [f"![Engines and learned methods]({png})", ""]
    return lines


def engine_points(records: Sequence[Dict[str, Any]]) -> List[Tuple[str, float, float, int]]:
    """``(name, E_dist cm, seconds per frame, sequences)`` of every engine setting and
    every learned method on the engines' sequences (frame-weighted; an engine's time is
    per simulated frame, its pre-roll included in the count)."""
    eng = [r for r in records if r["kind"] == ENGINE_KIND and r["status"] == "ok"]
    seqs = {r["sequence"] for r in eng}
    pts = []
    for name in dict.fromkeys(r["method"] for r in eng):
        mine = [r for r in eng if r["method"] == name]
        n = sum(r["frames"] for r in mine)
        sim = sum(r.get("simulated_frames", r["frames"]) for r in mine)
        pts.append((name, sum(r["metrics"]["E_dist"] * r["frames"] for r in mine) / n,
                    sum(r["seconds"] for r in mine) / sim, len(mine)))
    for m in _ordered([r for r in records if r["kind"] == KIND]):
        ok = _ok(records, m)
        if not ok:
            continue
        agg = [scoring.aggregate(r["per_sequence"], lambda s: s["sequence"] in seqs)
               for r in ok]
        if agg and "all" in agg[0] and all("latency_ms" in r.get("timing", {}) for r in ok):
            pts.append((m, statistics.fmean(a["all"]["E_dist"] for a in agg),
                        statistics.fmean(r["timing"]["latency_ms"] for r in ok) / 1000.0,
                        len({s["sequence"] for s in ok[0]["per_sequence"]} & seqs)))
    return pts


def plot_engines(records: Sequence[Dict[str, Any]], path) -> Optional[Path]:
    """``pareto_engines.png``: seconds per frame against E_dist of the engines and the
    learned methods on the engines' sequences; ``None`` without engine records."""
    pts = engine_points(records)
    if not any(r["kind"] == ENGINE_KIND and r["status"] == "ok" for r in records):
        return None
    return plot_points([(n, 1000.0 * s, e) for n, e, s, _ in pts], path,
                       "Engines and learned methods on the same test sequences",
                       xlabel="time per frame (ms, log): engines per simulated frame, "
                              "learned methods' latency at batch 1")



# --------------------------------------------------------------------------- ensemble
def ensemble_methods(records: Sequence[Dict[str, Any]]) -> Dict[str, List[Dict[str, Any]]]:
    """Per method, its scores against the ensemble ground truth per sequence
    (:func:`garmentgnn.bench.scoring.score_ensemble`), the mean over its ok seeds."""
    rs = [r for r in records if r["kind"] == KIND and r["status"] == "ok" and r.get("ensemble")]
    return {m: ensemble_report.seed_mean([r["ensemble"] for r in rs if r["method"] == m])
            for m in _ordered(rs)}


def ensemble_markdown(records: Sequence[Dict[str, Any]], png: Optional[str] = None
                      ) -> List[str]:
    """The section on the ensemble ground truth (empty without one)."""
    return ensemble_report.markdown(ensemble_methods(records), png, "###")


def plot_ensemble(records: Sequence[Dict[str, Any]], path) -> Optional[Path]:
    """``ensemble.png``: the spread-skill figure (``None`` without an ensemble)."""
    return ensemble_report.plot(ensemble_methods(records), path,
                                "Held-out test split against the ensemble ground truth")
