"""Batch size at equal wall time and at equal epochs: the learning curves of one method
trained by several ``garmentgnn bench`` runs that differ only in ``--batch-size`` /
``--lr-factor``, on one figure against epochs and against training wall time.

Run the bench once per setting, each in its own ``--out`` (the same preset, dataset,
``--minutes`` and method, one after another on an otherwise idle machine), then::

    python benchmarks/batch_size.py --method 'GarTrans (SAT)' \\
        --run 'batch 1'=~/.cache/garmentgnn/bench/b1 \\
        --run 'batch 16'=~/.cache/garmentgnn/bench/b16 --commit

An epoch is the dataset's training chunks (``train_chunks`` of the first run's dataset at
the bench's chunk length), the curve's ``chunks`` the chunks trained on so far.  Reports,
per run: steps, epochs (steps x batch size) and training minutes (validation excluded);
the validation E_dist at the end of the budget (equal wall time), at the epochs every run
reached (equal epochs, linearly interpolated between curve points) and its best; the test
E_dist at the end, and a paired Wilcoxon test of each run's test sequences against the
first run's.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any, Dict, List, Tuple

import numpy as np

from garmentgnn._argparse import (Accumulate, ArgumentParser, HelpFormatter, add_output_args,
                                  command_line, output_path)
from garmentgnn._plotting import pyplot
from garmentgnn.data import SequenceChunks
from garmentgnn.bench import scoring
from garmentgnn.bench.methods import DATA
from garmentgnn.bench.tables import save_figure, table
from garmentgnn._files import atomic_write_bytes, atomic_write_json

COMMITTED = (Path(__file__).resolve().parents[1] / "docs" / "results" / "batch_size"
             / "batch_size")


def labelled_run(text: str) -> Tuple[str, Path]:
    """An argparse type: ``LABEL=DIR``, a bench output folder with ``results.json``."""
    label, sep, folder = text.partition("=")
    path = Path(folder).expanduser()
    if not sep or not label or not (path / "results.json").is_file():
        raise argparse.ArgumentTypeError(f"expected LABEL=DIR with DIR/results.json (a "
                                         f"`garmentgnn bench` output folder), got {text!r}")
    return label, path


def record_of(folder: Path, method: str) -> Dict[str, Any]:
    """The first-seed ``learned`` record of ``method`` in a bench folder, with a curve."""
    recs = [r for r in json.loads((folder / "results.json").read_text())["records"]
            if r.get("kind") == "learned" and r.get("method") == method and r.get("curve")
            and r.get("status") == "ok"]
    if not recs:
        raise SystemExit(f"error: {folder}: no finished run of {method!r} with a learning "
                         "curve; run the bench there first (a preset with curve_every)")
    return min(recs, key=lambda r: r["seed"])


def at(x: List[float], y: List[float], x0: float) -> float:
    """``y`` at ``x0``, linear between the points (``x`` increasing)."""
    return float(np.interp(x0, x, y))


def compare(runs: List[Tuple[str, Dict[str, Any]]], train_chunks: int) -> Dict[str, Any]:
    rows, first = [], runs[0][1]
    ref = {s["sequence"]: s["metrics"]["E_dist"] for s in first["per_sequence"]}
    common = min(r["curve"]["points"][-1]["chunks"] for _, r in runs) / train_chunks
    for label, r in runs:
        pts = r["curve"]["points"]
        ep = [p["chunks"] / train_chunks for p in pts]
        err = [p["E_dist"] for p in pts]
        mine = {s["sequence"]: s["metrics"]["E_dist"] for s in r["per_sequence"]}
        p = None if r is first else scoring.wilcoxon(ref, mine)["p"]
        batch = r["config"].get("batch_size", 1)
        rows.append({"label": label, "batch_size": batch,
                     "lr_factor": r["config"].get("lr_factor", 1.0), "steps": r["steps"],
                     "epochs": r["steps"] * batch / train_chunks,
                     "minutes": r["train_seconds"] / 60.0,
                     "val_end": err[-1], "val_equal_epochs": at(ep, err, common),
                     "val_best": min(err), "test_end": r["metrics"]["E_dist"], "p": p,
                     "epochs_curve": ep, "minutes_curve": [q["seconds"] / 60 for q in pts],
                     "val_curve": err})
    return {"equal_epochs": common, "train_chunks": train_chunks,
            "lbs_val": first["curve"].get("lbs_E_dist"), "rows": rows}


def markdown(res: Dict[str, Any], method: str, command: str, dataset: str) -> str:
    body = [[r["label"], str(r["batch_size"]), f"{r['lr_factor']:g}", str(r["steps"]),
             f"{r['epochs']:.2f}", f"{r['minutes']:.1f}", f"{r['val_end']:.3f}",
             f"{r['val_equal_epochs']:.3f}", f"{r['val_best']:.3f}", f"{r['test_end']:.3f}",
             "—" if r["p"] is None else f"{r['p']:.3g}"] for r in res["rows"]]
    lbs = res["lbs_val"]
    return "\n".join([
        f"# Batch size: {method} at equal wall time and equal epochs", "", f"`{command}`", "",
        f"Dataset `{dataset}`; an epoch is {res['train_chunks']} training chunks. Validation "
        "E_dist (cm) at the end of each run's budget (equal wall time), at "
        f"{res['equal_epochs']:.2f} epochs (the most every run reached: equal epochs) and its "
        "best; test E_dist at the end; p: paired two-sided Wilcoxon over the test sequences "
        "against the first row." + (f" LBS on the validation sequences: {lbs:.3f} cm." if lbs
                                      else ""), "",
        *table(["run", "batch", "lr x", "steps", "epochs", "train min", "val, equal time",
                f"val at {res['equal_epochs']:.2f} epochs", "val best", "test, equal time",
                "p (test)"], body),
        "", "![curves](batch_size.png)", ""])


def plot(res: Dict[str, Any], method: str, path: Path) -> Path:
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(12.0, 4.8), sharey=True)
    for i, r in enumerate(res["rows"]):
        style = dict(color=plt.get_cmap("tab10")(i), marker=".", lw=1.4)
        axes[0].plot(r["epochs_curve"], r["val_curve"], label=r["label"], **style)
        axes[1].plot(r["minutes_curve"], r["val_curve"], **style)
    for ax, xlabel in zip(axes, ("epochs (training chunks / train split's chunks)",
                                 "training wall time (min)")):
        if res["lbs_val"]:
            ax.axhline(res["lbs_val"], color="black", ls="--", lw=1,
                       label="LBS" if ax is axes[0] else None)
        ax.set_xlabel(xlabel)
        ax.grid(True, alpha=0.3)
    axes[0].axvline(res["equal_epochs"], color="grey", ls=":", lw=1)
    axes[0].set_ylabel("validation E_dist (cm)")
    axes[0].set_title("against epochs")
    axes[1].set_title("against wall time")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{method}: batch size at equal epochs and equal wall time")
    fig.tight_layout()
    return save_figure(fig, path)


def main(argv=None) -> None:
    ap = ArgumentParser(description=__doc__.splitlines()[0],
                        formatter_class=HelpFormatter)
    ap.add_argument("--run", dest="runs", nargs="+", required=True, type=labelled_run,
                    action=Accumulate, metavar="LABEL=DIR",
                    help="bench output folders, the first the reference")
    ap.add_argument("--method", default="GarTrans (SAT)", help="the learned method compared")
    add_output_args(ap, COMMITTED, "writes OUT.json, OUT.md and OUT.png")
    a = ap.parse_args(argv)
    if len({label for label, _ in a.runs}) != len(a.runs):
        ap.error("--run: a label given twice")
    out = output_path(a, COMMITTED)
    runs = [(label, record_of(folder, a.method)) for label, folder in a.runs]
    data = {r["dataset"]["content_sha256"] for _, r in runs}
    if len(data) != 1:
        ap.error(f"--run: the runs trained on different datasets ({sorted(map(str, data))})")
    root = runs[0][1]["dataset"]["root"]
    chunks = len(SequenceChunks(root, "train", DATA["chunk"], DATA["history"],
                                DATA["nystrom_dim"], DATA["num_landmarks"]))
    res = compare(runs, chunks)
    command = command_line("benchmarks/batch_size.py", argv)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out.with_suffix(".json"), dict(res, command=command, method=a.method,
                                                     dataset=data.pop()))
    text = markdown(res, a.method, command, runs[0][1]["dataset"]["content_sha256"])
    atomic_write_bytes(out.with_suffix(".md"), text.encode())
    plot(res, a.method, out.with_suffix(".png"))
    print(text)


if __name__ == "__main__":
    main()
