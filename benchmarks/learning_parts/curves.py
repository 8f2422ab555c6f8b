"""The results of ``curves``: their table (mean over seeds, paired tests against the first
variant), several runs' files merged into one result, and the plot of E_dist / LBS
against steps."""
from __future__ import annotations

import statistics
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

from garmentgnn._plotting import pyplot
from garmentgnn.data.store import read_json
from garmentgnn.bench import scoring
from garmentgnn.bench.tables import table

#: the surface metrics ``curves --surface`` adds (E_dist is always measured)
SURFACE = ("E_vnorm", "E_fnorm", "E_len", "E_curv")


def mean_curve(runs: List[Dict[str, Any]]) -> List[Dict[str, Any]]:
    """The runs' curves averaged over seeds, at the steps every run measured."""
    curves = [r["curve"] for r in runs if r["curve"]]
    n = min((len(c) for c in curves), default=0)
    return [{"step": curves[0][i]["step"],
             **{k: sum(c[i][k] for c in curves) / len(curves) for k in ("train", "test")}}
            for i in range(n)]


def curves_markdown(res: Dict[str, Any], surface: bool = False) -> List[str]:
    """The table of :func:`part_curves`' (or :func:`merge_curves`') results."""
    lbs, seeds = res["lbs"], res["seeds"]
    measured = next((run["curve"][-1] for r in res["variants"].values() for run in r["runs"]
                     if run["curve"]), {})  # none where every run failed at once
    count = {k: len(measured.get(f"{k}_sequences", ())) for k in ("train", "test")}

    def last_sequences(runs):  # {"seed/sequence": E_dist} of the test split, last step
        return {f"{r['seed']}/{q}": e for r in runs if r["curve"]  # (none in the first layout)
                for q, e in r["curve"][-1].get("test_sequences", {}).items()}

    def spread(values):
        m = sum(values) / len(values)
        if len(values) < 2:
            return f"{m:.3f}"
        return f"{m:.3f} ± {statistics.stdev(values):.3f}"

    names = list(res["variants"])
    ref = last_sequences(res["variants"][names[0]]["runs"]) if names else {}
    rows = []
    for name, r in res["variants"].items():
        ok = [run for run in r["runs"] if run["curve"]]
        failures = "; ".join(f"seed {run['seed']}: {run['status']}" for run in r["runs"]
                             if run["status"] != "ok")
        label = _label(name, r["runs"], seeds)
        if not ok:
            rows.append([label, "—", "—", "—", "—", "—", "—", failures])
            continue
        c = mean_curve(ok)
        best = min(c, key=lambda row: row["test"])
        p = "—"
        if name != names[0] and len(ok) == len(r["runs"]):
            try:
                w = scoring.wilcoxon(last_sequences(ok), ref)
                p = f"{w['p']:.2g} ({w['median_diff']:+.3f} cm)"
            except ValueError:
                pass
        rows.append([label, str(ok[0]["curve"][-1]["step"]),
                     spread([run["curve"][-1]["train"] / lbs["train"] for run in ok]),
                     spread([run["curve"][-1]["test"] / lbs["test"] for run in ok]),
                     f"{best['test'] / lbs['test']:.3f} @ {best['step']}", p,
                     _minutes(ok), failures])
    lines = [f"E_dist / LBS's (LBS: train {lbs['train']:.3f} cm over {count['train']} "
             f"sequences, test {lbs['test']:.3f} cm over {count['test']}); "
             f"{'seed' if len(seeds) == 1 else 'mean ± std over seeds'} "
             f"{', '.join(map(str, seeds))}; p: paired Wilcoxon test against "
             f"`{names[0] if names else ''}` over (seed, test sequence) at the last step, "
             "with the median difference:", ""]
    lines += table(["variant", "steps", "train", "test", "best test (seed mean)",
                    "p vs first", "minutes", "failure"], rows)
    lines += group_lines(res)
    phased = [(name, run["seed"], run["transitions"]) for name, r in res["variants"].items()
              for run in r["runs"] if "transitions" in run]
    if phased:
        def when(t):  # {phase: the epoch at whose end it began}; JSON keys are strings
            return ", ".join(f"phase {k} after epoch {t[k]}" for k in sorted(t, key=int))

        lines += ["", "Phase transitions: " + "; ".join(
            f"{name}, seed {s}: {when(t) or 'phase 1 only'}" for name, s, t in phased)]
    if surface:
        lm = res["lbs_metrics"]["test"]
        srows = [["LBS", "—"] + [f"{lm[k]:.4g}" for k in SURFACE]]
        for name, r in res["variants"].items():
            ok = [run["curve"][-1]["test_metrics"] for run in r["runs"]
                  if run["curve"] and "test_metrics" in run["curve"][-1]]
            if ok:
                srows.append([name, str(r["runs"][0]["curve"][-1]["step"])]
                             + [f"{sum(m[k] for m in ok) / len(ok):.4g}" for k in SURFACE])
        lines += ["", "Test split at the last step, mean over seeds (degrees, degrees, %, rad):",
                  ""]
        lines += table(["variant", "steps", *SURFACE], srows)
    return lines


def _label(name: str, runs: List[Dict[str, Any]], seeds: Sequence[int]) -> str:
    """A variant's name in a table, with its seeds where they are not all the table's
    (merged files where it ran fewer)."""
    own = [run["seed"] for run in runs]
    if own == list(seeds):
        return name
    return f"{name} (seed{'s' * (len(own) > 1)} {', '.join(map(str, own))})"


def _minutes(runs: List[Dict[str, Any]]) -> str:
    """The runs' mean wall time in minutes (training and its measurements)."""
    secs = [run["seconds"] for run in runs if "seconds" in run]
    return f"{statistics.mean(secs) / 60:.1f}" if secs else "—"


def group_lines(res: Dict[str, Any]) -> List[str]:
    """The test split's held-out groups at the last step: each variant's E_dist (mean
    over seeds, frame-weighted over the group's sequences) over LBS's on the same frames
    (results that record their ``sequences``; none before)."""
    facts = res.get("sequences", {}).get("test")
    if not facts:
        return []
    groups = sorted({f["group"] for f in facts.values()})

    def weighted(per_seq: Dict[str, float], group: str) -> Optional[float]:
        seqs = [q for q, f in facts.items() if f["group"] == group and q in per_seq]
        if not seqs:
            return None
        w = sum(facts[q]["frames"] for q in seqs)
        return sum(per_seq[q] * facts[q]["frames"] for q in seqs) / w

    lbs = {q: f["lbs"] for q, f in facts.items()}
    rows = [["LBS (cm)"] + [f"{weighted(lbs, g):.3f}" for g in groups]]
    for name, r in res["variants"].items():
        ok = [run for run in r["runs"] if run["curve"]]
        if not ok:
            continue
        mean = {q: statistics.mean(run["curve"][-1]["test_sequences"][q] for run in ok)
                for q in ok[0]["curve"][-1]["test_sequences"]}
        cells = []
        for g in groups:
            m = weighted(mean, g)
            # LBS on the very sequences the variant was scored on
            ref = weighted({q: lbs[q] for q in mean if q in lbs}, g)
            cells.append("—" if m is None or ref is None else f"{m / ref:.3f}")
        rows.append([_label(name, r["runs"], res["seeds"])] + cells)
    counts = ", ".join(f"{g} {sum(f['group'] == g for f in facts.values())}" for g in groups)
    return (["", "Test split by held-out group at the last step (E_dist / LBS's on the same "
             f"valid frames; sequences per group: {counts}):", ""]
            + table(["variant", *groups], rows))


def _errors(run: Dict[str, Any]) -> Dict[str, Any]:
    """A run without its timings: what a rerun must reproduce exactly."""
    def drop(d: Dict[str, Any]) -> Dict[str, Any]:
        return {k: v for k, v in d.items() if "seconds" not in k}
    return dict(drop(run), curve=[drop(p) for p in run.get("curve", [])])


def read_curves(path: Path) -> Dict[str, Any]:
    """A ``curves.json`` (``FileNotFoundError`` / ``ValueError`` naming ``path`` when it is
    missing, not JSON or not the results of ``curves``)."""
    if not path.is_file():
        raise FileNotFoundError(f"`files`: {path}: no such file (a curves.json written by "
                                f"`python benchmarks/learning.py curves`)")
    doc = read_json(path, "give a curves.json written by `python benchmarks/learning.py "
                          "curves`")
    if not isinstance(doc.get("variants"), dict):
        raise ValueError(f"`files`: {path}: no 'variants': not the results of `curves`")
    return as_runs(doc, path)


def as_runs(doc: Dict[str, Any], path: Path) -> Dict[str, Any]:
    """``doc`` in today's layout: each variant a list of ``runs`` (one per seed, with
    ``seed``, ``status``, ``seconds`` and ``curve``) under ``seeds``.  The first layout
    (one seed, ``seed`` at the top; a variant's ``status``, ``seconds`` and ``curve``
    beside its ``settings``) is read into it; anything else is a ``ValueError`` naming
    ``path`` and the variant."""
    doc = dict(doc, variants=dict(doc["variants"]))
    old = "seed" in doc and "seeds" not in doc
    for name, v in doc["variants"].items():
        if isinstance(v, dict) and old and isinstance(v.get("curve"), list):
            run = {"seed": doc["seed"], "status": v.get("status"), "seconds": v.get("seconds"),
                   "curve": v["curve"]}
            doc["variants"][name] = {"settings": v.get("settings"), "runs": [run]}
        elif not (isinstance(v, dict) and isinstance(v.get("runs"), list)
                  and all(isinstance(r, dict) and "seed" in r and isinstance(r.get("curve"),
                                                                               list)
                          for r in v["runs"])):
            raise ValueError(f"`files`: {path}: variant {name!r} holds no learning curve "
                             f"(no 'runs' with a seed and a 'curve'): not the results of "
                             f"`curves`")
    if old:
        doc["seeds"] = [doc.pop("seed")]
    return doc


def merge_curves(files: Sequence[Path], only: Optional[Sequence[str]] = None) -> Dict[str, Any]:
    """The ``curves.json`` of runs made in separate processes (other variants or other
    seeds of the same dataset and steps) as one result; the first file's first variant
    kept is then the reference of every paired test.  ``only``: keep these variants alone.
    A variant in more than one file has its seeds joined where its settings agree; a seed
    in two files is kept once where its errors agree exactly (a rerun that reproduced it),
    and refused where they differ."""
    parts = [read_curves(Path(f)) for f in files]
    res = {k: v for k, v in parts[0].items() if k != "command"}
    res.update(variants={}, sources=[{"file": str(f), "command": p.get("command")}
                                     for f, p in zip(files, parts)])
    for f, part in zip(files, parts):
        for key in ("lbs", "steps", "sequences"):
            mine, first = part.get(key), res.get(key)
            if key == "sequences" and None in (mine, first):  # older results record none
                continue
            if mine != first:
                raise ValueError(f"`files`: {f} has another {key} ({mine} against {first}): "
                                 f"not runs that can be compared")
        for name, v in part["variants"].items():
            if only is not None and name not in only:
                continue
            if name not in res["variants"]:
                res["variants"][name] = dict(v, runs=list(v["runs"]))
                continue
            kept = res["variants"][name]
            if kept.get("settings") != v.get("settings"):
                raise ValueError(f"`files`: variant {name!r} is in more than one file, "
                                 f"with other settings")
            seeds = {run["seed"]: run for run in kept["runs"]}
            for run in v["runs"]:
                if run["seed"] not in seeds:
                    kept["runs"].append(run)
                elif _errors(seeds[run["seed"]]) != _errors(run):
                    raise ValueError(f"`files`: variant {name!r}, seed {run['seed']}, is in "
                                     f"more than one file, with other errors")
                # else: a rerun that reproduced it to the last digit: kept once
            kept["runs"].sort(key=lambda run: run["seed"])
    missing = [name for name in only or () if name not in res["variants"]]
    if missing:
        raise ValueError(f"`only`: {missing} in none of the files")
    res["seeds"] = sorted({run["seed"] for v in res["variants"].values() for run in v["runs"]}
                          or res["seeds"])
    return res


#: the curves plot's top (E_dist / LBS): a diverging variant is clipped there and says so
#: in the legend, so that it does not flatten the differences near 1
PLOT_TOP = 1.5


def plot_curves(res: Dict[str, Any], path: Path) -> None:
    """E_dist / LBS against steps, train and test.  Where some variant stays below
    :data:`PLOT_TOP` the axis is linear and diverging variants are clipped (so they do
    not flatten the differences near 1); where none does, the axis is logarithmic."""
    plt = pyplot()
    rows = len(res["variants"])  # legend lines, below each panel (not over its curves)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2 + 0.16 * rows), sharey=True)
    n = len(res.get("seeds", [0]))  # files written before the seeds: one run, "curve"

    def label(name: str, runs: List[Dict[str, Any]]) -> str:  # merged: seeds may differ
        ok = [run for run in runs if run["curve"]]
        if n == 1 or not ok:
            return name
        return (f"{name} (mean of {len(ok)} seeds)" if len(ok) > 1
                else f"{name} (seed {ok[0].get('seed')})")

    curves = {label(name, r.get("runs", [r])): mean_curve(r.get("runs", [r]))
              for name, r in res["variants"].items()}
    curves = {name: c for name, c in curves.items() if c}
    clip = any(max(row[s] / res["lbs"][s] for row in c) <= PLOT_TOP
               for c in curves.values() for s in ("train", "test"))
    low, high = PLOT_TOP, 1.0
    for ax, split in zip(axes, ("train", "test")):
        for name, c in curves.items():
            y = [row[split] / res["lbs"][split] for row in c]
            low, high = min(low, min(y)), max(high, min(max(y), PLOT_TOP))
            clipped = clip and max(y) > PLOT_TOP
            label = f"{name} (up to {max(y):.1f}x: clipped)" if clipped else name
            ax.plot([row["step"] for row in c], [min(v, PLOT_TOP) if clip else v for v in y],
                    marker=".", label=label)
        ax.axhline(1.0, color="k", lw=0.8, ls="--")
        ax.set_title(f"{split} sequences (LBS {res['lbs'][split]:.2f} cm = 1)")
        ax.set_xlabel("optimizer steps")
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14), frameon=False)
    if clip:
        pad = 0.05 * (high - low) + 0.005
        axes[0].set_ylim(max(0.0, low - pad), high + pad)
    else:
        axes[0].set_yscale("log")
    axes[0].set_ylabel("E_dist / LBS" + ("" if clip else " (log scale)"))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)

