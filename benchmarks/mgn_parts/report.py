"""The MGN-style benchmark's report: the score table (per held-out group, paired tests)
and the error per frame (``benchmarks/mgn_learn.py score``)."""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any, Dict, Optional, Sequence

import numpy as np

from garmentgnn._plotting import pyplot
from garmentgnn.bench.scoring import GROUPS, aggregate, wilcoxon
from garmentgnn.data.store import read_json

#: the frames a rollout is given (not scored, for any method)
GIVEN = 2
#: the columns of the score table
METRICS = ("E_dist", "E_vnorm", "E_fnorm", "E_len", "E_curv", "collision_rate")

__all__ = ["GIVEN", "METRICS", "combined", "merge_scores", "plot_per_frame", "read_scores",
           "score_table", "write_score"]


def _by_seq(records, metric="E_dist") -> Dict[str, float]:
    return {r["sequence"]: r["metrics"][metric] for r in records}


def read_score(path: str) -> Dict[str, Any]:
    """A ``score.json`` of an earlier ``score`` run (for ``--merge``); exits with one
    ``error:`` line naming the file when it is missing or is not one."""
    fix = "give a score.json written by `python benchmarks/mgn_learn.py score`"
    try:
        doc = read_json(path, fix)
    except (OSError, ValueError) as e:
        sys.exit(f"error: --merge: {e if isinstance(e, ValueError) else f'{path}: no such file'}")
    lbs = (doc.get("methods") or {}).get("LBS only") if isinstance(doc.get("methods"), dict) \
        else None
    if not isinstance(lbs, list) or not all(isinstance(doc.get(k), dict)
                                            for k in ("per_frame", "seconds")):
        sys.exit(f"error: --merge: {path}: no 'methods' with 'LBS only', 'per_frame' and "
                 f"'seconds'; {fix}")
    return doc


def read_scores(paths: Sequence[str], names: Optional[Sequence[str]] = None
                ) -> Dict[str, Dict[str, Any]]:
    """``{path: score}`` of the ``--merge`` files; one ``error:`` line where a file is
    not a score or where one of ``names`` (``--merge-names``) is in none of them."""
    docs = {path: read_score(path) for path in paths}
    have = {name for doc in docs.values() for name in doc["methods"]}
    missing = [n for n in names or () if n not in have]
    if missing:
        sys.exit(f"error: --merge-names: {missing[0]!r} is in no --merge file; give one of "
                 f"{sorted(have)}")
    return docs


def merge_scores(results: Dict[str, Any], earlier: Dict[str, Dict[str, Any]],
                 names: Optional[Sequence[str]] = None) -> None:
    """Adds to ``results`` the methods (``names``; default all) of ``earlier``'s scores,
    which must have scored the same sequences of the same dataset (one ``error:`` line
    where one did not); a method ``results`` holds already keeps its own rows."""
    for path, other in earlier.items():
        if (other.get("content_sha256"), other.get("split")) != (
                results["content_sha256"], results["split"]) or \
                _by_seq(other["methods"]["LBS only"]) != _by_seq(results["methods"]["LBS only"]):
            sys.exit(f"error: --merge: {path} scored other sequences or another dataset")
        for key in ("methods", "per_frame", "seconds"):
            for name, v in other[key].items():
                if names is None or name in names:
                    results[key].setdefault(name, v)


def combined(earlier: Dict[str, Dict[str, Any]],
             names: Optional[Sequence[str]] = None) -> Dict[str, Any]:
    """One score of the ``--merge`` files alone, nothing rolled out: the first file's
    methods (``names``; default all) with the others' added (:func:`merge_scores`)."""
    (path, first), *_ = earlier.items()
    results = {k: first[k] for k in ("data", "content_sha256", "split", "valid") if k in first}
    results.update(methods={"LBS only": first["methods"]["LBS only"]},
                   per_frame={"LBS only": first["per_frame"]["LBS only"]}, seconds={})
    merge_scores(results, earlier, names)
    return results


def write_score(results: Dict[str, Any], out: Path, extra: str = "") -> str:
    """``out/score.json``, ``score.md`` (:func:`score_table`, then ``extra``) and
    ``per_frame.png`` of ``results``; returns the markdown."""
    text = score_table(results) + extra
    (out / "score.json").write_text(json.dumps(results, indent=1))
    (out / "score.md").write_text(text)
    plot_per_frame(results, out / "per_frame.png")
    return text


def score_table(results: Dict[str, Any]) -> str:
    meth = results["methods"]
    lbs = aggregate(meth["LBS only"])
    lines = [f"Dataset `{str(results.get('content_sha256'))[:12]}`, split "
             f"`{results['split']}`, {len(meth['LBS only'])} sequences, valid frames from "
             f"frame {GIVEN} on.", "",
             "| method | " + " | ".join(METRICS) + " | x LBS (E_dist) | s/sequence |",
             "|---|" + "---:|" * (len(METRICS) + 2)]
    for name, recs in meth.items():
        a = aggregate(recs)["all"]
        secs = results["seconds"].get(name)
        lines.append(f"| {name} | " + " | ".join(f"{a[m]:.4g}" for m in METRICS)
                     + f" | {a['E_dist'] / lbs['all']['E_dist']:.3f} | "
                     + (f"{secs / max(1, len(recs)):.2f}" if secs else "—") + " |")
    lines += ["", "Per held-out group, E_dist as a ratio to LBS's:", "",
              "| method | " + " | ".join(GROUPS) + " |", "|---|" + "---:|" * len(GROUPS)]
    lines.append("| LBS only (cm) | " + " | ".join(
        f"{lbs[g]['E_dist']:.2f}" if g in lbs else "—" for g in GROUPS) + " |")
    for name, recs in meth.items():
        if name == "LBS only":
            continue
        a = aggregate(recs)
        lines.append(f"| {name} | " + " | ".join(
            f"{a[g]['E_dist'] / lbs[g]['E_dist']:.3f}" if g in a and g in lbs else "—"
            for g in GROUPS) + " |")
    mgn = [n for n in meth if n.startswith("MGN-style")]
    lines += ["", "Paired Wilcoxon signed-rank tests over sequences (median difference "
              "in cm, negative: the first lower; wins: share of sequences where it is "
              "lower):", "", "| pair | metric | n | median diff | wins | p |",
              "|---|---|---:|---:|---:|---:|"]
    def apart(a: str, b: str) -> bool:  # two MGN-style rows of other models and starts
        (ma, _, sa), (mb, _, sb) = a.rpartition(" ("), b.rpartition(" (")
        return ma != mb and sa != sb

    for i, a in enumerate(mgn):
        for b in meth:  # every other method; a later MGN-style row of its model or start
            if b in mgn[:i + 1] or (b in mgn and apart(a, b)):
                continue
            for metric in ("E_dist", "E_len", "E_curv", "collision_rate"):
                try:
                    w = wilcoxon(_by_seq(meth[a], metric), _by_seq(meth[b], metric))
                except ValueError:
                    continue
                lines.append(f"| {a} vs {b} | {metric} | {w['n']} | {w['median_diff']:.4g} | "
                             f"{w['wins']:.2f} | {w['p']:.2g} |")
    return "\n".join(lines) + "\n"


def plot_per_frame(results: Dict[str, Any], path: Path) -> None:
    plt = pyplot()
    valid = results.get("valid") or {}
    fig, ax = plt.subplots(figsize=(10, 4.5))
    # a colour each (tab10 repeats after ten lines); LBS black and dashed, the reference
    names = [n for n in results["per_frame"] if n != "LBS only"]
    cmap = plt.get_cmap("tab20" if len(names) > 10 else "tab10")
    colours = {n: cmap(i % cmap.N) for i, n in enumerate(names)}
    colours["LBS only"] = "k"
    for name, frames in results["per_frame"].items():
        T = max(len(v) for v in frames.values())
        sums, counts = np.zeros(T), np.zeros(T)
        for seq, vals in frames.items():
            ok = valid.get(seq, [True] * len(vals))
            for t, (v, k) in enumerate(zip(vals, ok)):
                if k:
                    sums[t] += v
                    counts[t] += 1
        mean = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
        ax.plot(np.arange(T), mean, label=name, color=colours[name],
                ls="--" if name == "LBS only" else "-", lw=1.5 if "MGN" in name else 1.0)
    ax.set_xlabel("frame")
    ax.set_ylabel("E_dist (cm), mean over sequences")
    ax.set_title(f"error per frame, {results['split']} "
                 f"({str(results.get('content_sha256'))[:8]})")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # beside the curves
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# -- learning curves -------------------------------------------------------------------------
