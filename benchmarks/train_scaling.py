"""Training throughput on the CPU's cores: GarTrans and DA-style vertex-frames/s through
``garmentgnn train fit``, per source tree x layout (processes x torch threads each) x
batch, side by side in one run.

A layout of ``P`` processes is Lightning's DDP (``--trainer.devices P --trainer.strategy
ddp``, gloo): ``P`` replicas, each training ``batch / P`` chunks a step on its own shard,
their gradients averaged (the single-process step of ``batch`` chunks, up to the input
normalisers' statistics: docs/model.md, "Distributed training").  ``--batches`` counts the
chunks of one optimizer step over all replicas, so that the rows of one batch do the
same work per step.  One process with ``T`` threads is today's default layout
(``--trainer.devices 1``).

Each configuration runs ``garmentgnn train fit`` of its tree in a fresh process
(``python -m garmentgnn.cli`` with ``PYTHONPATH=<tree>/src``: any revision with the
command line serves, e.g. a checkout of an older commit), on the ``throughput-small``
stand-in of ``train_throughput.py`` (4 garment kinds at ~400 vertices x 3 Anny bodies x 4
motions of 32 frames; chunks of 8 frames, history 3; no validation), with the recipe's
own callbacks (checkpoints) and data loading in the training process, as a user runs
it.  A callback (``scaling_parts.step_timer.StepTimer``) records every step's end; the first
``--warmup`` steps (start-up, ``torch.compile``) are not timed.  vertex-frames/s = the
vertex-frames of all replicas' timed steps over the longest replica's timed wall time.
Trees and configurations alternate within each of ``--repeats`` rounds (a busy machine
slows them alike); the table has each configuration's median.  Each run is kept as it
ends: the same command after an interruption starts where it stopped::

    python benchmarks/train_scaling.py --commit
    python benchmarks/train_scaling.py --against /path/to/old/checkout --methods gartrans

Every run gets the caller's environment (``OMP_NUM_THREADS`` set to the layout's
threads): measure on an otherwise idle machine.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import torch

from garmentgnn._argparse import (Accumulate, ArgumentParser, HelpFormatter, add_output_args,
                                  benchmark_cache, check_unique, command_line, existing_dir,
                                  int_at_least, output_path)
from garmentgnn.data import store
from garmentgnn.models.inputs import CHUNK, HISTORY

HERE = Path(__file__).resolve().parent
#: the folder of this script (its sibling scripts, ``scaling_parts``): on ``sys.path``
#: when it is run, not when it is loaded with ``runpy`` (the tests)
if str(HERE) not in sys.path:
    sys.path.append(str(HERE))
from scaling_parts.machine import cpu_name  # noqa: E402
from step_profile import _revision  # noqa: E402
from train_throughput import RECIPES, dataset  # noqa: E402

RESULTS = HERE.parent / "docs" / "results" / "train_scaling"
#: the runs so far, kept until the tables are written
PARTIAL = "train_scaling.partial.json"


def layout(text: str) -> Tuple[int, int]:
    """An argparse type: ``"PxT"``, ``P >= 1`` processes of ``T >= 1`` torch threads."""
    try:
        p, t = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected PROCESSESxTHREADS such as 2x1, got "
                                         f"{text!r}") from None
    if p < 1 or t < 1:
        raise argparse.ArgumentTypeError(f"expected PROCESSESxTHREADS >= 1, got {text!r}")
    return p, t


def fit_once(tree: Path, method: str, root: Path, procs: int, threads: int, batch: int,
             steps: int, warmup: int, timeout: float) -> Dict[str, Any]:
    """One ``garmentgnn train fit`` of ``tree``: vertex-frames/s of its timed steps."""
    with tempfile.TemporaryDirectory(prefix="train_scaling_") as tmp:
        times = Path(tmp) / "times"
        cmd = [sys.executable, "-m", "garmentgnn.cli", "train", "fit",
               "--config", RECIPES[method], "--data.root", str(root),
               "--data.chunk", str(CHUNK), "--data.history", str(HISTORY),
               "--data.val_split", "null",
               "--data.seed", "0", "--data.batch_size", str(batch // procs),
               "--seed_everything", "0", "--trainer.max_steps", str(steps),
               "--trainer.max_epochs", "-1", "--trainer.logger", "false",
               "--trainer.enable_progress_bar", "false", "--trainer.default_root_dir", tmp,
               "--trainer.accelerator", "cpu", "--trainer.devices", str(procs),
               "--trainer.callbacks+=scaling_parts.step_timer.StepTimer"]
        if procs > 1:
            cmd += ["--trainer.strategy", "ddp"]
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tree / "src"), str(HERE)]),
                   OMP_NUM_THREADS=str(threads),
                   GARMENTGNN_STEP_TIMES=str(times), PYTHONWARNINGS="ignore")
        t0 = time.perf_counter()
        try:
            proc = subprocess.run(cmd, env=env, cwd=tmp, capture_output=True, text=True,
                                  timeout=timeout)
        except subprocess.TimeoutExpired:
            return {"error": f"no end within --timeout {timeout} s"}
        wall = time.perf_counter() - t0
        recs = [json.loads(p.read_text()) for p in sorted(times.glob("rank*.json"))]
        if proc.returncode or len(recs) != procs:
            tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
            return {"error": f"exit {proc.returncode}, {len(recs)} of {procs} step records: "
                             + " | ".join(tail)}
    if min(len(r["ends"]) for r in recs) <= warmup:
        return {"error": f"fewer than {warmup + 1} steps"}
    seconds = max(r["ends"][-1] - r["ends"][warmup - 1] for r in recs)
    work = sum(sum(r["work"][warmup:]) for r in recs)
    return {"vertex_frames_per_s": work / seconds, "seconds": seconds,
            "timed_steps": len(recs[0]["ends"]) - warmup, "wall_s": wall,
            "threads": [r["threads"] for r in recs]}


def run(a: Any, out: Path) -> Dict[str, Any]:
    """Every run of ``a``'s configurations; each is kept in ``out/PARTIAL`` as it ends, so
    that an interrupted run of the same trees and settings starts where it stopped."""
    root = dataset("small", benchmark_cache())
    trees = [HERE.parent] + [Path(t).resolve() for t in a.against]
    labels = [_revision(t) for t in trees]
    configs = [(m, p, t, b) for m in a.methods for (p, t) in a.layouts for b in a.batches
               if b % p == 0]
    partial, key = out / PARTIAL, {"trees": labels, "steps": a.steps, "warmup": a.warmup}
    done = json.loads(partial.read_text()) if partial.is_file() else {}
    if done.get("key") != key:
        done = {"key": key, "runs": []}
    kept = {tuple(r[:6]): r[6] for r in done["runs"]}
    out.mkdir(parents=True, exist_ok=True)
    runs: Dict[Tuple[str, str, int, int, int], List[Dict[str, Any]]] = {}
    for i in range(a.repeats):
        for m, p, t, b in configs:
            for tree, label in zip(trees, labels):
                r = kept.get((i, label, m, p, t, b))
                if r is None:
                    r = fit_once(tree, m, root, p, t, b, a.steps, a.warmup, a.timeout)
                    done["runs"].append([i, label, m, p, t, b, r])
                    partial.write_text(json.dumps(done))
                runs.setdefault((label, m, p, t, b), []).append(r)
                print(label, m, f"{p}x{t}", b, r.get("error") or
                      f"{r['vertex_frames_per_s']:.0f} vf/s", flush=True)
    rows = []
    for (label, m, p, t, b), rs in runs.items():
        ok = [r for r in rs if "error" not in r]
        row = {"tree": label, "method": m, "processes": p, "threads": t, "batch": b,
               "runs": rs, "vertex_frames_per_s": statistics.median(
                   r["vertex_frames_per_s"] for r in ok) if ok else None}
        rows.append(row)
    base = labels[-1]
    for row in rows:
        ref = next((x for x in rows if x["tree"] == base and all(
            x[k] == row[k] for k in ("method", "processes", "threads", "batch"))), None)
        row["x_against"] = (row["vertex_frames_per_s"] / ref["vertex_frames_per_s"]
                            if ref and ref["vertex_frames_per_s"] and
                            row["vertex_frames_per_s"] else None)
    return {"command": command_line("benchmarks/train_scaling.py"),
            "cpu": cpu_name(), "cores": os.cpu_count(),
            "torch": torch.__version__, "trees": [{"label": lb, "path": str(t)} for lb, t in
                                                   zip(labels, trees)],
            "against": base, "steps": a.steps, "warmup": a.warmup,
            "dataset": {"root": str(root).replace(str(Path.home()), "~"),
                        "content_sha256": store.read_manifest(root).get("content_sha256")},
            "rows": rows}


def best(rows: List[Dict[str, Any]], method: str, tree: str, processes: Any = None
         ) -> Dict[str, Any]:
    """The fastest row of ``method`` on ``tree`` (of ``processes`` processes if given)."""
    cand = [r for r in rows if r["method"] == method and r["tree"] == tree
            and r["vertex_frames_per_s"] and processes in (None, r["processes"])]
    return max(cand, key=lambda r: r["vertex_frames_per_s"]) if cand else {}


def write(info: Dict[str, Any], out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "train_scaling.json").write_text(json.dumps(info, indent=1))
    base, rows = info["against"], info["rows"]
    lines = [f"# Training throughput on the CPU's cores ({info['cpu']}, {info['cores']} "
             f"cores, torch {info['torch']})", "", f"`{info['command']}`", "",
             f"`garmentgnn train fit` per tree, {info['steps']} steps of which the first "
             f"{info['warmup']} are not timed; layout: processes x threads each (DDP over "
             "gloo for 2+ processes); batch: chunks per optimizer step over all replicas; "
             f"x {base}: against that tree's same configuration, in the same run.  Dataset "
             f"`throughput-small`, content `{(info['dataset']['content_sha256'] or '?')[:12]}`.",
             "", f"| tree | method | layout | batch | vertex-frames/s | x {base} |",
             "|---|---|---|---:|---:|---:|"]
    for r in sorted(rows, key=lambda r: (r["method"], r["processes"], r["threads"],
                                         r["batch"], r["tree"])):
        vfs, x = r["vertex_frames_per_s"], r["x_against"]
        lines.append(f"| {r['tree']} | {r['method']} | {r['processes']}x{r['threads']} | "
                     f"{r['batch']} | {'failed' if vfs is None else f'{vfs:,.0f}'} | "
                     f"{'-' if x is None else f'{x:.2f}'} |")
    lines += ["", f"Best configuration of each tree, against {base}'s best (any layout, "
              f"any batch) and its best in one process:", ""]
    for m in sorted({r["method"] for r in rows}):
        ref, one = best(rows, m, base), best(rows, m, base, processes=1)
        for t in [x["label"] for x in info["trees"]]:
            b = best(rows, m, t)
            if not (b and ref):
                continue
            text = (f"* {m}, {t}: {b['vertex_frames_per_s']:,.0f} vertex-frames/s "
                    f"({b['processes']}x{b['threads']}, batch {b['batch']}), "
                    f"{b['vertex_frames_per_s'] / ref['vertex_frames_per_s']:.2f}x {base}'s "
                    f"best ({ref['processes']}x{ref['threads']}, batch {ref['batch']})")
            if one:
                text += (f", {b['vertex_frames_per_s'] / one['vertex_frames_per_s']:.2f}x "
                         f"its best in one process ({one['processes']}x{one['threads']}, "
                         f"batch {one['batch']})")
            lines.append(text)
    (out / "train_scaling.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def parse_args(argv: Optional[Sequence[str]] = None) -> argparse.Namespace:
    ap = ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    ap.add_argument("--methods", nargs="+", action=Accumulate, choices=sorted(RECIPES),
                    default=["gartrans", "da"], help="methods (their packaged recipes)")
    ap.add_argument("--layouts", nargs="+", action=Accumulate, type=layout,
                    default=[(1, 1), (1, 2), (2, 1)], metavar="PxT",
                    help="processes x torch threads each")
    ap.add_argument("--batches", nargs="+", action=Accumulate, type=int_at_least(1),
                    default=[4, 8], help="chunks per optimizer step (all replicas)")
    ap.add_argument("--steps", type=int_at_least(2), default=48, help="training steps per run")
    ap.add_argument("--warmup", type=int_at_least(1), default=8, help="untimed first steps")
    ap.add_argument("--repeats", type=int_at_least(1), default=3,
                    help="rounds over the configurations")
    ap.add_argument("--timeout", type=int_at_least(1), default=900, help="seconds per run")
    ap.add_argument("--against", nargs="*", action=Accumulate, type=existing_dir, default=[],
                    metavar="DIR",
                    help="other source trees of garmentgnn, run alternately with this one")
    add_output_args(ap, RESULTS, "the tables")
    a = ap.parse_args(argv)
    for flag in ("methods", "layouts", "batches"):
        check_unique(ap, getattr(a, flag), f"--{flag}")
    if a.steps <= a.warmup:
        ap.error(f"--steps {a.steps}: not more than --warmup {a.warmup}; nothing is timed")
    if not any(b % p == 0 for b in a.batches for p, _ in a.layouts):
        ap.error("--batches: none divides among the --layouts' processes")
    return a


def main(argv: Optional[Sequence[str]] = None) -> None:
    a = parse_args(argv)
    out = output_path(a, RESULTS)
    write(run(a, out), out)
    (out / PARTIAL).unlink(missing_ok=True)


if __name__ == "__main__":
    main()
