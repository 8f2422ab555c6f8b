"""``garmentgnn bench --preset tiny|small --out DIR [--seeds N] [--data DATASET] [--no-learned]``.

:mod:`garmentgnn.cli` adds it with ``add_parser(subparsers)`` and calls ``main(args)``
for ``args.command == "bench"``.
"""
from __future__ import annotations

import argparse
import sys

from garmentgnn._argparse import HelpFormatter
from garmentgnn.bench.harness import run
from garmentgnn.bench.presets import PRESET_NAMES, preset
from garmentgnn.data import SpecMismatch


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``bench`` sub-command to an ``argparse`` sub-parsers object."""
    b = subparsers.add_parser(
        "bench", help="benchmark: accuracy vs a reference simulation, run time, memory, "
                      "stability (resumable; writes OUT/report.md)",
        description="Benchmark: accuracy against a reference simulation, run time, memory "
                    "and stability of the simulator budgets, LBS and the learned methods "
                    "(resumable; writes OUT/report.md).", formatter_class=HelpFormatter)
    b.add_argument("--preset", choices=PRESET_NAMES, default="tiny", help="benchmark preset")
    b.add_argument("--out", required=True, help="output folder (rerun to resume)")
    b.add_argument("--seeds", type=int, default=None,
                   help="number of seeds, of the simulated cases and of the learned methods' "
                        "training (default: the preset's)")
    b.add_argument("--data", default=None,
                   help="an existing generated dataset folder for the learned methods "
                        "(default: generate the preset's dataset under OUT/data)")
    b.add_argument("--no-learned", action="store_true",
                   help="do not train/evaluate the learned methods (no dataset needed)")
    b.add_argument("--retry-failed", action="store_true", help="rerun records marked failed")
    b.add_argument("--no-progress", action="store_true", help="no progress bar")
    return b


def _command(args: argparse.Namespace) -> str:
    """The ``garmentgnn bench`` command line that ``args`` stand for."""
    parts = ["garmentgnn", "bench", "--preset", args.preset, "--out", str(args.out)]
    for flag, value in (("--seeds", args.seeds), ("--data", args.data)):
        if value is not None:
            parts += [flag, str(value)]
    for flag, on in (("--no-learned", args.no_learned), ("--retry-failed", args.retry_failed),
                     ("--no-progress", args.no_progress)):
        if on:
            parts.append(flag)
    return " ".join(parts)


def main(args: argparse.Namespace) -> int:
    """Run the bench sub-command; returns the exit status (0 when the run completed --
    failed records are results and are listed in the report; 2 for bad arguments)."""
    if args.seeds is not None and args.seeds < 1:
        print(f"error: --seeds must be positive, got {args.seeds}", file=sys.stderr)
        return 2
    if args.data is not None and args.no_learned:
        print("error: --data and --no-learned exclude each other", file=sys.stderr)
        return 2
    try:
        summary = run(preset(args.preset), args.out, seeds=args.seeds,
                      progress=not args.no_progress, retry_failed=args.retry_failed,
                      data=args.data, learned=not args.no_learned,
                      command=_command(args))
    except (ValueError, SpecMismatch) as err:  # bad arguments / a dataset folder of another spec
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(summary)
    return 0
