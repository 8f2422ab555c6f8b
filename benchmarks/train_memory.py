"""Resident memory of a training process against steps.

Trains a learned method of the bench (``--method``, built from its packaged recipe by
:func:`~garmentgnn.training.load_recipe`, with the bench's data settings) on a generated
dataset's training split through the recipe's Lightning ``Trainer`` and prints the
process's resident set size (``VmRSS`` of ``/proc/self/status``, Linux) every
``--every`` steps.  A process whose live tensors do not grow should not grow either; on
the `medium` dataset a reference cycle among the attention layers' sparse patterns once
made a GarTrans fit grow by about 23 MB a step (docs/bench.md, "Memory").  Writes
``train_memory.json`` into ``--out`` (``--commit``: the committed
``docs/results/benchmarks/``)::

    python benchmarks/train_memory.py --data ~/.cache/garmentgnn/datasets/medium-blender
"""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import lightning as L
import torch

from garmentgnn._argparse import (ArgumentParser, HelpFormatter, add_output_args, command_line,
                                  int_at_least, output_path)
from garmentgnn.bench.methods import FULL, GARTRANS
from garmentgnn.bench.timing import status_kb
from garmentgnn.data.store import code_version, dataset_dir
from garmentgnn.training import load_recipe

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results" / "benchmarks"


def rss_mb() -> float:
    """The process's resident set size (MB) from ``/proc/self/status``."""
    return status_kb("VmRSS") / 1024


class RSSProbe(L.Callback):
    """Records ``(step, RSS)`` every ``every`` optimizer steps."""

    def __init__(self, every: int) -> None:
        self.every = every
        self.rows: List[Dict[str, float]] = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        step = trainer.global_step
        if step % self.every == 0:
            self.rows.append({"step": step, "rss_mb": rss_mb()})
            print(f"step {step}: RSS {self.rows[-1]['rss_mb']:.0f} MB", flush=True)


def main(argv: Optional[Sequence[str]] = None) -> None:
    ap = ArgumentParser(description=__doc__.splitlines()[0],
                        formatter_class=HelpFormatter)
    ap.add_argument("--data", required=True, type=dataset_dir,
                    help="a generated dataset folder")
    ap.add_argument("--method", default=FULL, choices=list(GARTRANS),
                    help="a GarTrans variant of the bench")
    ap.add_argument("--steps", type=int_at_least(1), default=300, help="optimizer steps")
    ap.add_argument("--every", type=int_at_least(1), default=50,
                    help="steps between measurements (at most --steps)")
    ap.add_argument("--threads", type=int_at_least(1), default=1, help="torch threads")
    add_output_args(ap, RESULTS, "folder for train_memory.json")
    args = ap.parse_args(argv)
    if args.every > args.steps:
        ap.error(f"--every {args.every}: more than --steps {args.steps}; nothing would be "
                 f"measured")
    if not sys.platform.startswith("linux"):
        raise SystemExit("error: reads /proc/self/status: Linux only")
    out = output_path(args, RESULTS)
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(args.threads)
    recipe = load_recipe(GARTRANS[args.method],
                         args=["--data.root", str(args.data), "--data.val_split", "null",
                               "--data.cache_size", "64", "--seed_everything", "0"])
    probe = RSSProbe(args.every)
    recipe.trainer(max_steps=args.steps, max_epochs=-1, accelerator="cpu", devices=1,
                   logger=False, enable_checkpointing=False, enable_progress_bar=False,
                   enable_model_summary=False, limit_val_batches=0, num_sanity_val_steps=0,
                   callbacks=[probe]).fit(recipe.module, recipe.datamodule)
    result: Dict[str, Any] = {
        "command": command_line("benchmarks/train_memory.py", argv),
        "method": args.method, "threads": args.threads, "torch": torch.__version__,
        "code": code_version(), "rows": probe.rows}
    (out / "train_memory.json").write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
