"""Benchmark report: ``results.json``, ``report.md`` (tables shaped like the paper's
Tables 1 and 3, mean +- std over seeds; a stability table; scaling, leave-out,
precision and long-sequence sections), ``pareto.png`` and ``scaling.png``.

A **record** is a JSON-able dict:

* common: ``kind`` (one of :data:`KINDS`), ``method``, ``case``, ``seed``,
  ``status`` (``"ok"`` or ``"failed"``), ``message``.
* accuracy: ``metrics`` with ``E_dist`` (cm), ``E_vnorm``, ``E_fnorm`` (deg), ``E_len``
  (%), ``E_curv`` (rad), ``collision_rate`` (%); ``timing`` with ``latency_ms`` (one
  frame at batch 1), ``throughput_fps`` (at ``best_batch``), ``peak_mem_mb``,
  ``threads``; optionally ``reference: true`` (the ground truth's own run).
* stability: ``verdict`` (stable / degraded / failed), ``reason``, ``metrics`` from
  :func:`garmentgnn.bench.stability.stability_metrics`.
* learned: a method trained and scored on a generated dataset's test split
  (:mod:`garmentgnn.bench.learned`): ``metrics`` as accuracy, ``timing``,
  ``train_seconds``, ``epochs``.
* scaling / leaveout / precision / long_sequence: see :mod:`garmentgnn.bench.scaling`,
  :mod:`~garmentgnn.bench.leaveout`, :mod:`~garmentgnn.bench.precision` (an ok record
  holds the field :data:`EXTRA_REQUIRED` names).

Every number of a record must be finite unless its ``status`` is ``"failed"``;
non-finite numbers of failed records are written as ``null`` and shown as failed.
"""
from __future__ import annotations

import json
import math
import statistics
from pathlib import Path
from typing import Any, Dict, Iterable, List, Optional, Sequence, Tuple

from garmentgnn.bench import (curves, learned_report, leaveout, noise_floor, precision,
                              scaling)
from garmentgnn.bench.page import write_media
from garmentgnn.bench.records import NOT_RUN, STATUSES
from garmentgnn.bench.tables import METRICS, UNITS, fmt, mean_std, plot_summary, table
from garmentgnn._files import atomic_write_bytes, atomic_write_json

KINDS = ("accuracy", "stability", "scaling", "leaveout", "precision", "long_sequence",
         "learned", "learned_stability", "engine")
STABILITY_KINDS = ("stability", "learned_stability")
#: the field an ok record of each extra kind must hold (their modules document the rest)
EXTRA_REQUIRED = {"scaling": "timing", "leaveout": "scenes", "precision": "rows",
                  "long_sequence": "verdict"}


# --------------------------------------------------------------------------- validation
def _walk(obj: Any, path: str) -> Iterable[Tuple[str, Any]]:
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _walk(v, f"{path}.{k}")
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            yield from _walk(v, f"{path}[{i}]")
    else:
        yield path, obj


def _nonfinite(obj: Any) -> List[str]:
    return [p for p, v in _walk(obj, "") if isinstance(v, float) and not math.isfinite(v)]


def _sanitize(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _sanitize(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_sanitize(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _stabilitytable(records: List[Dict[str, Any]]) -> List[str]:
    rows = []
    for r in records:
        m = r.get("metrics", {})

        def g(k: str, scale: float = 1.0, digits: int = 3) -> str:
            v = m.get(k)
            return "—" if v is None else f"{scale * v:.{digits}g}"
        rows.append([r["method"], r["case"], str(r["seed"]), f"**{r.get('verdict', 'failed')}**",
                     g("frames"), g("nonfinite"), g("max_speed"), g("body_max_speed"),
                     g("energy_growth"), g("max_energy_J"), g("max_penetration_m", 1e3),
                     g("nonconverged_frames"),
                     (r.get("reason") or r.get("message") or "").replace("|", "/")[:160]])
    return table(["method", "case", "seed", "verdict", "frames", "non-finite",
                   "max speed (m/s)", "body max speed (m/s)", "energy growth",
                   "max energy (J)", "penetration (mm)", "unconverged frames", "reason"],
                  rows) + [""]


def check_record(rec: Dict[str, Any]) -> Dict[str, Any]:
    """Validate one record (``ValueError`` naming ``records`` and the field); returns a
    JSON-safe copy (non-finite numbers of failed records become ``None``)."""
    if not isinstance(rec, dict):
        raise ValueError(f"`records`: expected dicts, got {type(rec).__name__}")
    for key in ("kind", "method", "case", "seed", "status"):
        if key not in rec:
            raise ValueError(f"`records`: a record lacks {key!r}: {sorted(rec)}")
    if rec["kind"] not in KINDS:
        raise ValueError(f"`records`: kind must be one of {KINDS}, got {rec['kind']!r}")
    if rec["status"] not in STATUSES:
        raise ValueError(f"`records`: status must be one of {STATUSES}, got {rec['status']!r}")
    where = f"{rec['kind']}/{rec['method']}/{rec['case']}/seed {rec['seed']}"
    bad = _nonfinite(rec)
    if bad and rec["status"] != "failed":
        raise ValueError(f"`records`: non-finite number(s) at {bad} in {where}; mark the "
                         "record failed (status='failed') if the method produced them")
    if rec["status"] == "ok" and rec["kind"] in ("accuracy", "learned", "engine"):
        missing = [m for m in METRICS if m not in rec.get("metrics", {})]
        if missing:
            raise ValueError(f"`records`: {rec['kind']} record {where} lacks metric(s) {missing}")
    if rec["status"] == "ok" and rec["kind"] in STABILITY_KINDS and "verdict" not in rec:
        raise ValueError(f"`records`: stability record {where} lacks a verdict")
    need = EXTRA_REQUIRED.get(rec["kind"])
    if rec["status"] == "ok" and need is not None and need not in rec:
        raise ValueError(f"`records`: {rec['kind']} record {where} lacks {need!r}")
    return _sanitize(rec)


# --------------------------------------------------------------------------- aggregation
def _order(names: Iterable[str]) -> List[str]:
    seen: List[str] = []
    for n in names:
        if n not in seen:
            seen.append(n)
    return seen


def summarize(records: Sequence[Dict[str, Any]]) -> Dict[str, Any]:
    """Per-method aggregates of the accuracy records (mean / std over seeds)."""
    acc = [r for r in records if r["kind"] == "accuracy"]
    out: Dict[str, Any] = {}
    for method in _order(r["method"] for r in acc):
        rs = [r for r in acc if r["method"] == method]
        ok = [r for r in rs if r["status"] == "ok"]
        entry: Dict[str, Any] = {"records": len(rs), "failed": len(rs) - len(ok),
                                 "reference": any(r.get("reference") for r in rs)}
        for m in METRICS:
            # per seed: mean over cases, then mean/std over seeds
            by_seed: Dict[Any, List[float]] = {}
            for r in ok:
                by_seed.setdefault(r["seed"], []).append(r["metrics"][m])
            vals = [statistics.fmean(v) for v in by_seed.values()]
            if vals:
                entry[m] = dict(zip(("mean", "std"), mean_std(vals)), n=len(vals))
        for t in ("latency_ms", "throughput_fps", "peak_mem_mb"):
            vals = [r["timing"][t] for r in ok if r.get("timing", {}).get(t) is not None]
            if vals:
                entry[t] = dict(zip(("mean", "std"), mean_std(vals)), n=len(vals))
        out[method] = entry
    return out


# --------------------------------------------------------------------------- markdown
def _cell(rs: List[Dict[str, Any]], metric: str, section: str = "metrics") -> str:
    ok = [r for r in rs if r["status"] == "ok" and r.get(section, {}).get(metric) is not None]
    failed = sum(r["status"] == "failed" for r in rs)
    if not rs:
        return "not run"
    if not ok:
        return "failed"
    s = fmt([r[section][metric] for r in ok])
    return s + (f" ({failed}/{len(rs)} failed)" if failed else "")


def _label(method: str, rs: List[Dict[str, Any]]) -> str:
    return method + (" (reference = ground truth)" if any(r.get("reference") for r in rs) else "")


def render_markdown(records: Sequence[Dict[str, Any]], not_run: Sequence[str] = (),
                    meta: Optional[Dict[str, Any]] = None, pareto_png: Optional[str] = None,
                    scaling_png: Optional[str] = None,
                    learned_png: Optional[str] = None,
                    engines_png: Optional[str] = None,
                    floor: Optional[Dict[str, Any]] = None) -> str:
    """The ``report.md`` text; ``floor``: a :func:`garmentgnn.bench.noise_floor.load_floor`
    result, printed beside the method rows and in its own section."""
    meta = meta or {}
    lines = ["# Benchmark report", ""]
    if meta:
        lines += [f"- {k}: {json.dumps(v) if not isinstance(v, str) else v}"
                  for k, v in meta.items()] + [""]
    acc = [r for r in records if r["kind"] == "accuracy"]
    methods = _order(r["method"] for r in acc)
    cases = _order(r["case"] for r in acc)
    metric_hdr = [f"{m} ({UNITS[m]})" for m in METRICS]
    lines += ["## Accuracy per case (shaped like Table 1)", ""]
    if acc:
        lines += ["Mean ± std over seeds (frames 1..T-1; frame 0 is the shared initial "
                  "state). Errors are against the reference row of the same case.", ""]
        for case in cases:
            lines += [f"### {case}", ""]
            rows = []
            for method in methods:
                rs = [r for r in acc if r["method"] == method and r["case"] == case]
                if rs:
                    rows.append([_label(method, rs)] + [_cell(rs, m) for m in METRICS])
            lines += table(["method"] + metric_hdr, rows) + [""]
        lines += ["## Accuracy and cost over all cases (shaped like Table 3)", "",
                  "Metrics: per seed the mean over cases, then mean ± std over seeds. "
                  "latency: ms per frame at batch 1; throughput: frames/s at the best batch; "
                  "peak memory: RSS increase during one prediction (see "
                  "`garmentgnn.bench.timing`).", ""]
        summ = summarize(records)
        rows = []
        for method in methods:
            rs = [r for r in acc if r["method"] == method]
            e = summ[method]
            row = [_label(method, rs)]
            for m in METRICS:
                row.append(f"{e[m]['mean']:.3g} ± {e[m]['std']:.2g}" if m in e else "failed")
            for t in ("latency_ms", "throughput_fps", "peak_mem_mb"):
                row.append(_cell(rs, t, "timing"))
            if e["failed"]:
                row[0] += f" ({e['failed']}/{e['records']} failed)"
            rows.append(row)
        for name, cm in noise_floor.bands(floor):  # E_dist below it: not decided by the GT
            rows.append([f"*{name}*"] + [f"{cm:.3g}" if m == "E_dist" else "—"
                                         for m in METRICS] + ["—"] * 3)
        lines += table(["method"] + metric_hdr + ["latency (ms)", "throughput (fps)",
                                                   "peak mem (MB)"], rows) + [""]
    else:
        lines += [NOT_RUN, ""]
    stab = [r for r in records if r["kind"] == "stability"]
    lines += ["## Stability", ""]
    th = next((r.get("thresholds") for r in records
               if r["kind"] in STABILITY_KINDS and r.get("thresholds")), None)
    if th:
        lines += ["Thresholds: " + ", ".join(f"{k}={v}" for k, v in th.items()) +
                  " (see `garmentgnn.bench.stability.Thresholds`).", ""]
    lines += (["The simulator on the bench's stability item (a garment on the capsule "
               "body), per motion seed.", ""] + _stabilitytable(stab) if stab
              else [NOT_RUN, ""])
    lstab = [r for r in records if r["kind"] == "learned_stability"]
    if lstab:
        seqs = sorted({str(r.get("sequence")) for r in lstab})
        lines += ["### Every method on a test sequence of the dataset", "",
                  f"The cases built on `{', '.join(seqs)}` (the first test sequence of the "
                  "learned methods' dataset: its anny body, garment and motion), predicted "
                  "by each learned method (the model of the seed in the table) and by the "
                  "simulator with the dataset's settings. No learned method takes the "
                  "material as input: `stiff_x1000` changes only how their output is "
                  "scored. Energy growth is relative to the first two frames, which a "
                  "frame-parallel model predicts near the rest garment (almost no elastic "
                  "energy), so for these methods it measures how far the later frames are "
                  "from rest (the cloth is stiff in stretch: a few % of edge strain is tens "
                  "of joules), not a blow-up over time; compare max energy with the "
                  "simulator's row.", ""] + _stabilitytable(lstab)
    lines += noise_floor.markdown(floor)
    lines += learned_report.markdown(records, learned_png)
    lines += learned_report.comparison_markdown(records, engines_png)
    lines += learned_report.ensemble_markdown(records, ENSEMBLE_PNG if any(
        r.get("ensemble") for r in records) else None)
    lines += curves.markdown(records, CURVES_PNG)
    lines += scaling.markdown(records, scaling_png)
    lines += leaveout.markdown(records)
    lines += precision.markdown(records)
    lines += precision.long_markdown(records)
    failed = [r for r in records if r["status"] == "failed"]
    if failed:
        lines += ["## Failures", ""]
        lines += [f"- {r['kind']} / {r['method']} / {r['case']} / seed {r['seed']}: "
                  f"{str(r.get('message', ''))[:300]}" for r in failed] + [""]
    lines += ["## Not run", ""]
    if not_run:
        lines += ["These methods are registered for this benchmark but produced no records "
                  "(no trained model or not part of this preset); no numbers are shown for "
                  "them.", ""]
        lines += [f"- {m}: not run" for m in not_run] + [""]
    else:
        lines += ["(none)", ""]
    if pareto_png:
        lines += ["## Error against run time", "", "The accuracy cases above (simulator "
                  "budgets and registered methods); learned methods on the dataset's test "
                  "split, if run, are plotted separately (`pareto_learned.png`, in their "
                  "section).", "", f"![Pareto]({pareto_png})", ""]
    return "\n".join(lines)


# --------------------------------------------------------------------------- plots
#: the learning curves' plot (:func:`garmentgnn.bench.curves.plot`), beside report.md
CURVES_PNG = "learning_curves.png"
#: the spread-skill figure of the ensemble ground truth
#: (:func:`garmentgnn.bench.learned_report.plot_ensemble`), beside report.md
ENSEMBLE_PNG = "ensemble.png"


def plot_pareto(records: Sequence[Dict[str, Any]], path: Path,
                floor: Optional[Dict[str, Any]] = None) -> Optional[Path]:
    """:func:`plot_summary` of the accuracy records (:func:`summarize`), with ``floor``'s
    engines as bands (:func:`garmentgnn.bench.noise_floor.bands`)."""
    return plot_summary(summarize(records), path, "Error against run time",
                        bands=noise_floor.bands(floor))


# --------------------------------------------------------------------------- entry point
def write_report(records: Sequence[Dict[str, Any]], out, not_run: Sequence[str] = (),
                 meta: Optional[Dict[str, Any]] = None, floor=None) -> Dict[str, Path]:
    """Validate ``records`` and write ``results.json``, ``report.md`` and ``pareto.png``
    (when there is something to plot) into ``out``, and the animation of a held-out
    sequence into ``out/media`` when the run trained GarTrans
    (:func:`garmentgnn.bench.page.write_media`); returns their paths.  ``floor``: the
    ground truth's noise floor, a ``benchmarks/gt_noise.py`` results file (default
    :func:`garmentgnn.bench.noise_floor.load_floor`'s: ``$GARMENTGNN_NOISE_FLOOR`` or the
    committed one of the records' dataset preset; none there: no floor shown)."""
    if isinstance(records, dict):
        raise ValueError("`records`: expected a list of records, got a dict")
    clean = [check_record(r) for r in records]
    names = {r["dataset"].get("name") for r in clean if isinstance(r.get("dataset"), dict)}
    loaded = noise_floor.load_floor(floor, next(iter(names)) if len(names) == 1 else None)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths: Dict[str, Path] = {}
    png = plot_pareto(clean, out / "pareto.png", loaded)
    if png is not None:
        paths["pareto"] = png
    scaling_png = scaling.plot(clean, out / "scaling.png")
    if scaling_png is not None:
        paths["scaling"] = scaling_png
    learned_png = learned_report.plot(clean, out / "pareto_learned.png",
                                      noise_floor.bands(loaded))
    if learned_png is not None:
        paths["pareto_learned"] = learned_png
    engines_png = learned_report.plot_engines(clean, out / "pareto_engines.png")
    if engines_png is not None:
        paths["pareto_engines"] = engines_png
    ensemble_png = learned_report.plot_ensemble(clean, out / ENSEMBLE_PNG)
    if ensemble_png is not None:
        paths["ensemble"] = ensemble_png
    curves_png = curves.plot(clean, out / CURVES_PNG)
    if curves_png is not None:
        paths["learning_curves"] = curves_png
    results = {"meta": meta or {}, "summary": summarize(clean), "not_run": list(not_run),
               "records": clean}
    paths["results"] = atomic_write_json(out / "results.json", results)
    text = render_markdown(clean, not_run, meta, "pareto.png" if png is not None else None,
                           "scaling.png" if scaling_png is not None else None,
                           "pareto_learned.png" if learned_png is not None else None,
                           "pareto_engines.png" if engines_png is not None else None,
                           loaded)
    # -- the animation of a held-out sequence (garmentgnn.bench.page), appended ----
    media = write_media(clean, out)
    if media:
        text += "\n" + "\n".join(media)
    # -- end of the animation ----------------------------------------------------------
    paths["report"] = atomic_write_bytes(out / "report.md", text.encode())
    return paths
