"""What loading a training batch costs: milliseconds per batch of the data module's
training loader (:class:`~garmentgnn.training.GarmentDataModule`, in the training
process, as ``garmentgnn train fit`` loads by default) over several shuffled epochs, per
bound of the sequence-file cache (``--cache-sizes``: files kept; the byte bound
``cache_bytes`` at its default), side by side in one run.

A training step reads ``batch`` chunks; each chunk needs its sequence file (read, SHA-256
checked, arrays checked: ~2 ms for a ``throughput-small`` file) unless the cache holds
it, then poses the body for its frames and builds the model inputs.  Shuffled sampling
visits the sequences in random order, so a cache smaller than the dataset reloads files
in every epoch; one that holds the dataset reads each file once.

Dataset: the ``throughput-small`` stand-in of ``benchmarks/train_throughput.py`` (48
sequences of 32 frames).  The static inputs (Nyström features on disk) are warmed
before the clock starts; the configurations alternate within each of ``--repeats``
rounds::

    python benchmarks/data_loading.py --cache-sizes 4 4096 --commit
"""
from __future__ import annotations

import json
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Any, Dict, Optional, Sequence

import torch

from garmentgnn._argparse import (Accumulate, ArgumentParser, HelpFormatter, add_output_args,
                                  benchmark_cache, check_unique, command_line,
                                  int_at_least, output_path)
from garmentgnn.data import store
from garmentgnn.models.inputs import CHUNK, HISTORY
from garmentgnn.training import GarmentDataModule

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.append(str(HERE))
from train_throughput import dataset  # noqa: E402

RESULTS = HERE.parent / "docs" / "results" / "data_loading"


def load_epochs(root: Path, cache_size: int, batch: int, epochs: int) -> Dict[str, Any]:
    """Milliseconds per training batch over ``epochs`` shuffled epochs, and file loads."""
    dm = GarmentDataModule(root, chunk=CHUNK, history=HISTORY, val_split=None, batch_size=batch,
                           cache_size=cache_size)
    dm.setup("fit")
    train = dm.train_set
    for i in range(len(train.records)):  # static inputs built before the clock
        train.static(i)
    loads0, n = train.num_file_loads, 0
    t0 = time.perf_counter()
    for epoch in range(epochs):
        loader = dm.train_dataloader()
        loader.sampler.set_epoch(epoch)
        for _ in loader:
            n += 1
    seconds = time.perf_counter() - t0
    return {"ms_per_batch": 1e3 * seconds / n, "batches": n,
            "file_loads": train.num_file_loads - loads0, "sequences": len(train.records)}


def parse_args(argv: Optional[Sequence[str]] = None):
    ap = ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    ap.add_argument("--cache-sizes", nargs="+", action=Accumulate, type=int_at_least(1),
                    default=[4, 4096], help="sequence files the cache keeps")
    ap.add_argument("--batch", type=int_at_least(1), default=4, help="chunks per batch")
    ap.add_argument("--epochs", type=int_at_least(1), default=3, help="epochs per run")
    ap.add_argument("--repeats", type=int_at_least(1), default=2, help="rounds")
    add_output_args(ap, RESULTS, "results folder")
    a = ap.parse_args(argv)
    check_unique(ap, a.cache_sizes, "--cache-sizes")
    return a


def main(argv: Optional[Sequence[str]] = None) -> None:
    a = parse_args(argv)
    out = output_path(a, RESULTS)
    torch.set_num_threads(1)
    root = dataset("small", benchmark_cache())
    runs: Dict[int, list] = {c: [] for c in a.cache_sizes}
    for r in range(a.repeats):
        for c in a.cache_sizes:
            runs[c].append(load_epochs(root, c, a.batch, a.epochs))
            print(f"round {r + 1}: cache_size {c}: {runs[c][-1]['ms_per_batch']:.1f} ms a "
                  f"batch, {runs[c][-1]['file_loads']} file loads", flush=True)
    rows = [{"cache_size": c, "ms_per_batch": statistics.median(x["ms_per_batch"] for x in rs),
             "file_loads": rs[0]["file_loads"], "batches": rs[0]["batches"],
             "sequences": rs[0]["sequences"]} for c, rs in runs.items()]
    info = {"command": command_line("benchmarks/data_loading.py", argv),
            "cpu": platform.machine(), "torch": torch.__version__, "batch": a.batch,
            "epochs": a.epochs, "repeats": a.repeats,
            "dataset": {"name": "throughput-small", "content_sha256":
                        store.read_manifest(root).get("content_sha256")},
            "rows": rows, "rounds": {str(c): rs for c, rs in runs.items()}}
    out.mkdir(parents=True, exist_ok=True)
    (out / "data_loading.json").write_text(json.dumps(info, indent=1))
    lines = [f"# Loading a training batch ({info['cpu']}, one thread, torch {info['torch']})",
             "", f"`{info['command']}`", "",
             f"{a.epochs} shuffled epochs of batches of {a.batch} chunks (8 frames) of "
             f"`throughput-small` (content "
             f"`{(info['dataset']['content_sha256'] or '?')[:12]}`), medians of "
             f"{a.repeats} rounds.", "",
             "| cache_size (files) | ms a batch | file loads | batches | sequences |",
             "|---:|---:|---:|---:|---:|"]
    lines += [f"| {r['cache_size']} | {r['ms_per_batch']:.1f} | {r['file_loads']} | "
              f"{r['batches']} | {r['sequences']} |" for r in rows]
    (out / "data_loading.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
