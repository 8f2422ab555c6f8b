"""``garmentgnn sweep --recipe RECIPE --data DATASET --out DIR [--grid KEY=V1,V2 ...]
[--choice KEY=V1,V2 ...] [--uniform KEY=LO,HI ...] [--loguniform KEY=LO,HI ...]
[--randint KEY=LO,HI ...] [--samples N] [--asha] [--preset NAME] [--epochs N]
[--minutes M] [--seed S] [--address HOST:PORT | --workers N] [--gpus G] [--ship-data]``:
:mod:`garmentgnn.bench.sweep` on Ray Tune.

:mod:`garmentgnn.cli` adds it with ``add_parser(subparsers)`` and calls ``main(args)``
for ``args.command == "sweep"``.
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import replace

from garmentgnn._argparse import (Accumulate, HelpFormatter, float_above,
                                  int_at_least, nonempty_path)
from garmentgnn._ray import check_address, import_tune
from garmentgnn.bench.dataset import prepare_dataset
from garmentgnn.bench.presets import PRESET_NAMES, preset
from garmentgnn.bench.ray_backend import RayBackend, add_cluster_args
from garmentgnn.bench.sweep import DISTRIBUTIONS, check_space, parse_space, sweep


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``sweep`` sub-command to an ``argparse`` sub-parsers object."""
    s = subparsers.add_parser(
        "sweep", help="search a recipe's settings on Ray Tune (grid or random, optionally "
                      "ASHA), each trial scored like a bench run",
        description="Search a recipe's settings on Ray Tune: each trial is the recipe with "
                    "its values written in, trained with a bench preset's learned budget "
                    "and scored on the dataset's test split like `garmentgnn bench`; "
                    "writes OUT/sweep.md and each trial's recipe.yaml beside its "
                    "score.json (docs/bench.md, 'Sweeps').", formatter_class=HelpFormatter)
    s.add_argument("--recipe", required=True,
                   help="the recipe swept: a packaged name (gartrans, baselines/da, ...) or "
                        "a YAML file")
    s.add_argument("--data", required=True, type=nonempty_path,
                   help="a generated dataset folder (garmentgnn generate)")
    s.add_argument("--out", required=True, type=nonempty_path, help="output folder")
    for dist in DISTRIBUTIONS:
        s.add_argument(f"--{dist}", nargs="+", default=None, metavar="KEY=VALUES",
                       action=Accumulate, help={
                           "grid": "every one of these values (KEY=V1,V2,...; KEY a dotted "
                                   "setting of the recipe, e.g. model.init_args.lr)",
                           "choice": "one of these values drawn per sample (KEY=V1,V2,...)",
                           "uniform": "a number drawn uniformly per sample (KEY=LO,HI)",
                           "loguniform": "a number drawn log-uniformly per sample "
                                         "(KEY=LO,HI)",
                           "randint": "an integer LO <= n < HI drawn per sample (KEY=LO,HI)"
                       }[dist])
    s.add_argument("--samples", type=int_at_least(1), default=1,
                   help="Ray Tune's num_samples: each grid point this many times, the drawn "
                        "values anew each time")
    s.add_argument("--asha", action="store_true",
                   help="stop the worst trials early (ASHA on each epoch's training loss, "
                        "at most the budget's epochs)")
    s.add_argument("--preset", choices=PRESET_NAMES, default="tiny",
                   help="the bench preset whose learned budget (epochs, minutes, batch size, "
                        "timing) each trial gets")
    s.add_argument("--epochs", type=int_at_least(1), default=None,
                   help="epochs of each trial (default: the preset's)")
    s.add_argument("--minutes", type=float_above(0), default=None,
                   help="training minutes of each trial (default: the preset's)")
    s.add_argument("--seed", type=int, default=0, help="the training seed of every trial")
    add_cluster_args(s, "each trial")
    return s


def main(args: argparse.Namespace) -> int:
    """Run the sweep sub-command; the exit status (2 with one ``error:`` line for bad
    arguments, before anything is written)."""
    try:
        import_tune()
    except RuntimeError as err:  # the ray extra is not installed
        print(f"error: {err}", file=sys.stderr)
        return 2
    try:
        space = parse_space({d: getattr(args, d) for d in DISTRIBUTIONS})
        cluster = RayBackend(args.workers, args.address, args.gpus, args.ship_data)
        if args.address:
            check_address(args.address)
        p = preset(args.preset)
        budget = replace(p.learned, methods=(args.recipe,), stability_cases=(), **{
            k: v for k, v in (("epochs", args.epochs), ("minutes", args.minutes))
            if v is not None})
        data = prepare_dataset(args.data)
        check_space(args.recipe, space, data.root)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    res = sweep(args.recipe, data, args.out, space, budget, (p.batches, p.warmup, p.repeats),
                p.threads, samples=args.samples, asha=args.asha, seed=args.seed, on=cluster)
    best = next((t for t in res["trials"] if t["E_dist"] is not None), None)
    print(f"sweep: {len(res['trials'])} trials; best test E_dist "
          + ("none (every trial failed or stopped)" if best is None else
             f"{best['E_dist']:.4f} cm: {best['recipe']}")
          + f"; table: {args.out}/sweep.md")
    return 0
