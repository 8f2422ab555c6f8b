"""A learned simulator's validation rollouts against LBS over its training budget, and
the budget their trend says a target needs.

    python benchmarks/mgn_budget.py --log RUN/metrics.csv --ckpt CKPT --data DATA \\
        [--out OUT | --commit] [--last 3] [--targets 0.85 0.75 0.5]

``--log`` is the run's Lightning CSV log: ``val/E_dist`` at every validation, ``step``
counting batches (the module's ``stats_steps`` statistics batches included, which train
nothing).  ``--ckpt`` is a checkpoint of the run: its hyper-parameters give the windows
a step (``batch_size``) and the statistics batches, and its own ``test_step`` on the
validation split, limited to the validation's sequences (``--val``), scores LBS on the
same frames as the validation rollouts (``test_lbs/*``) and its weights again
(``test/*``: a check that the scoring is the validation's).

Garment-frames are optimizer steps x windows a step: each window trains one frame.  The
trend is the least-squares line of E_dist / LBS against log10(garment-frames) through
the last ``--last`` validations, and each target's budget is where that line crosses it
("never" where the line is flat or rising).  A line through a few points of a curve that
bends is a local trend, not a law: the report gives the slope of every interval beside
it.

Outputs: ``OUT/budget.json``, ``budget.md`` and ``budget.png`` (log axis); ``--commit``
writes them beside the 10^6 garment-frame run's log, ``docs/results/mgn_learn/million``.
"""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import lightning as L
import torch

from garmentgnn._plotting import pyplot
from garmentgnn._argparse import (ArgumentParser, HelpFormatter, add_output_args,
                                  output_path)
from garmentgnn.training import GarmentDataModule
from garmentgnn.training.checkpoints import load_checkpoint

COLUMNS = ("E_dist", "E_len", "E_curv", "collision")
#: the committed copy (``--commit``): beside the 10^6 garment-frame run's log
RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results" / "mgn_learn" / "million"


def read_validations(path: Path) -> List[Dict[str, float]]:
    """Every validation of a Lightning CSV log in step order: ``{"step", "E_dist", ...}``
    (``step``: batches run, the csv's 0-based step + 1); a step logged twice (a piece
    resumed from before it) keeps its last row."""
    rows: Dict[int, Dict[str, float]] = {}
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            if row.get("val/E_dist") in (None, ""):
                continue
            step = int(row["step"]) + 1
            rows[step] = {"step": step, **{k: float(row[f"val/{k}"]) for k in COLUMNS
                                           if row.get(f"val/{k}") not in (None, "")}}
    if not rows:
        raise ValueError(f"--log {path}: no val/E_dist row; give the CSV log of a run that "
                         f"validated")
    return [rows[k] for k in sorted(rows)]


def score_lbs(module, data: str, sequences: int) -> Dict[str, Dict[str, float]]:
    """LBS and the checkpoint's ``module`` on the first ``sequences`` validation
    sequences, on the frames its validation scores: ``{"lbs": {...}, "model": {...}}``."""
    hp = GarmentDataModule.settings(module.trained_data)
    dm = GarmentDataModule(**dict(hp, root=data, test_split=hp.get("val_split") or "val"))
    trainer = L.Trainer(accelerator="cpu", devices=1, logger=False, enable_progress_bar=False,
                        enable_model_summary=False, limit_test_batches=sequences)
    trainer.test(module, dm, verbose=False)
    got = {k: float(v) for k, v in trainer.callback_metrics.items()}
    return {"lbs": {k: got[f"test_lbs/{k}"] for k in COLUMNS},
            "model": {k: got[f"test/{k}"] for k in COLUMNS}}


def trend(points: Sequence[Dict[str, float]], targets: Sequence[float]) -> Dict[str, Any]:
    """The least-squares line of ``ratio`` against log10(``frames``) through ``points``,
    and the garment-frames where it reaches each target (``None``: never)."""
    x = torch.tensor([math.log10(p["frames"]) for p in points], dtype=torch.float64)
    y = torch.tensor([p["ratio"] for p in points], dtype=torch.float64)
    if len(points) < 2:
        raise ValueError(f"--last: a trend needs two validations or more, got {len(points)}")
    slope = float(((x - x.mean()) * (y - y.mean())).sum() / ((x - x.mean()) ** 2).sum())
    icept = float(y.mean() - slope * x.mean())
    reach = {}
    for t in targets:
        hit = 10 ** ((t - icept) / slope) if slope < 0 else None
        reach[str(t)] = hit if hit is None or hit >= points[0]["frames"] else points[0]["frames"]
    return {"slope_per_decade": slope, "intercept": icept,
            "through": [p["frames"] for p in points], "frames_to_target": reach}


def plot(points: List[Dict[str, float]], fit: Dict[str, Any], targets: Sequence[float],
         path: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    f = [p["frames"] for p in points]
    ax.plot(f, [p["ratio"] for p in points], "o-", color="C0", label="validation rollouts")
    hits = [h for h in fit["frames_to_target"].values() if h is not None]
    x_end = min(max(hits + [f[-1] * 10]), f[-1] * 1e3)
    xs = torch.logspace(math.log10(fit["through"][0]), math.log10(x_end), 50).tolist()
    ax.plot(xs, [fit["intercept"] + fit["slope_per_decade"] * math.log10(v) for v in xs],
            ":", color="C0", label=f"trend of the last {len(fit['through'])}")
    ax.axhline(1.0, color="k", lw=1, label="LBS")
    for t in targets:
        ax.axhline(t, color="C3", lw=0.8, ls="--")
        ax.annotate(f"{t}x", (f[0], t), textcoords="offset points", xytext=(2, 2),
                    color="C3", fontsize=8)
    ax.set_xscale("log")
    ax.set_xlabel("garment-frames trained")
    ax.set_ylabel("validation E_dist / LBS")
    ax.set_ylim(min(targets) - 0.05, max(1.1, max(p["ratio"] for p in points) + 0.05))
    ax.legend(loc="upper right", fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def report(points, fit, lbs, model, args) -> str:
    lines = [f"LBS on the same {args.val} validation sequences and frames: "
             f"E_dist {lbs['E_dist']:.3f} cm, E_len {lbs['E_len']:.3f} %, "
             f"collision {lbs['collision']:.4f}.",
             f"The checkpoint ({args.ckpt}) scored the same way: E_dist "
             f"{model['E_dist']:.3f} cm.", "",
             "| batches | garment-frames | E_dist (cm) | x LBS | slope since the last "
             "(x LBS per decade) |", "|---:|---:|---:|---:|---:|"]
    for i, p in enumerate(points):
        q = points[i - 1]
        d = "" if i == 0 else \
            f"{(p['ratio'] - q['ratio']) / math.log10(p['frames'] / q['frames']):+.3f}"
        lines.append(f"| {p['step']:,} | {p['frames']:,} | {p['E_dist']:.3f} | "
                     f"{p['ratio']:.3f} | {d} |")
    lines += ["", f"Trend through the last {len(fit['through'])}: "
              f"{fit['slope_per_decade']:+.3f} x LBS per decade of garment-frames.", "",
              "| target | garment-frames the trend needs |", "|---:|---:|"]
    for t, hit in fit["frames_to_target"].items():
        lines.append(f"| {t}x | {'never (flat or rising)' if hit is None else f'{hit:.3g}'} |")
    return "\n".join(lines) + "\n"


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter)
    ap.add_argument("--log", type=Path, required=True, help="the run's metrics.csv")
    ap.add_argument("--ckpt", required=True, help="a checkpoint of the run")
    ap.add_argument("--data", required=True, help="the dataset the run trained on")
    ap.add_argument("--val", type=int, default=16,
                    help="validation sequences the run's validation rolls out (its "
                         "limit_val_batches)")
    ap.add_argument("--last", type=int, default=3, help="validations the trend goes through")
    ap.add_argument("--targets", type=float, nargs="+", default=[0.85, 0.75, 0.5],
                    help="E_dist / LBS ratios whose budget the report gives")
    add_output_args(ap, RESULTS, "the report's folder")
    args = ap.parse_args(argv)
    if args.last < 2:
        ap.error(f"--last: a trend needs two validations or more, got {args.last}")
    try:
        rows = read_validations(args.log)
    except (OSError, ValueError) as e:
        raise SystemExit(f"error: {e}" if "--log" in str(e) else f"error: --log: {e}")
    try:
        module = load_checkpoint(args.ckpt)
    except (OSError, ValueError, TypeError) as e:
        raise SystemExit(f"error: --ckpt {args.ckpt}: {e}")
    args.out = output_path(args, RESULTS)
    if module.hparams.get("rollout_mode") == "per_frame":
        raise SystemExit(f"error: --ckpt {args.ckpt}: a per_frame run takes several optimizer "
                         f"steps a batch, which its log's batch count does not give; use a "
                         f"one-step or pushforward run")
    scored = score_lbs(module, args.data, args.val)
    windows = int(module.trained_data.get("batch_size", 1))
    stats = int(module.hparams.get("stats_steps", 0))
    lbs = scored["lbs"]
    points = [dict(r, frames=windows * (r["step"] - stats), ratio=r["E_dist"] / lbs["E_dist"])
              for r in rows if r["step"] > stats]
    fit = trend(points[-args.last:], args.targets)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "budget.json").write_text(json.dumps(
        {"log": str(args.log), "ckpt": str(args.ckpt), "val_sequences": args.val,
         "windows_per_step": windows, "stats_batches": stats, "lbs": lbs,
         "checkpoint": scored["model"], "validations": points, "trend": fit}, indent=1))
    text = report(points, fit, lbs, scored["model"], args)
    (args.out / "budget.md").write_text(text)
    plot(points, fit, args.targets, args.out / "budget.png")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
