"""The "Held-out test split" section of the bench report: the learned methods' records
(:mod:`garmentgnn.bench.learned`) as a table shaped like the paper's Tables 1 and 3, and
their error-against-run-time plot."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence

from garmentgnn.bench.learned import KIND
from garmentgnn.bench.methods import LBS, METHOD_NAMES
from garmentgnn.bench.tables import METRICS, UNITS, fmt, mean_std, plot_summary, table

__all__ = ["markdown", "plot", "summary"]


def _ordered(records: Sequence[Dict[str, Any]]) -> List[str]:
    seen = [m for m in METHOD_NAMES if any(r["method"] == m for r in records)]
    return seen + sorted({r["method"] for r in records} - set(seen))


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
    lines = ["## Held-out test split (learned methods; shaped like Tables 1 and 3)", "",
             f"Dataset `{ds.get('name')}` (`{ds.get('root')}`, fingerprint "
             f"{str(ds.get('fingerprint'))[:8]}): {ds.get('sequences', {}).get('train')} train / "
             f"{ds.get('sequences', {}).get('test')} test sequences, "
             f"{ds.get('frames', {}).get('test')} test frames. Every method is trained on "
             "the train split (NCS-style: one model per test garment, on that garment's own "
             "test poses, physics terms only -- never its simulated positions) and scored "
             "on every frame of every test sequence against the simulation (frame-weighted "
             "means). A different case set from the simulator tables above: these rows are "
             "not comparable with them. Mean ± std over training seeds. latency: ms per "
             "frame at batch 1; throughput: frames/s at the best batch; train: wall time of "
             "the training epochs.", ""]
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


def plot(records: Sequence[Dict[str, Any]], path) -> Optional[Path]:
    """``pareto_learned.png``: log latency (batch 1) against E_dist of the learned
    methods' means; ``None`` without ok records."""
    return plot_summary(summary(records), path, "Held-out test split: error against run time")
