"""``garmentgnn bench --preset NAME --out DIR [--seeds N] [--data DATASET] [--no-learned |
--learned-only] [--minutes M] [--batch-size N] [--lr-factor F] [--methods NAME ...]
[--shard I/N] [--backend ray [--address HOST:PORT | --workers N] [--gpus G]
[--ship-data]]``.

:mod:`garmentgnn.cli` adds it with ``add_parser(subparsers)`` and calls ``main(args)``
for ``args.command == "bench"``.
"""
from __future__ import annotations

import argparse
import shlex
import sys
from dataclasses import replace

from garmentgnn._argparse import (Accumulate, HelpFormatter, nonempty_path)
from garmentgnn._ray import check_address, import_ray
from garmentgnn.bench.ray_backend import RayBackend, add_cluster_args
from garmentgnn.bench.runner import run
from garmentgnn.bench.methods import METHOD_NAMES
from garmentgnn.bench.presets import PRESET_NAMES, Preset, preset
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
    b.add_argument("--out", required=True, type=nonempty_path,
                   help="output folder (rerun to resume)")
    b.add_argument("--seeds", type=int, default=None,
                   help="number of seeds, of the simulated cases and of the learned methods' "
                        "training (default: the preset's)")
    b.add_argument("--data", default=None, type=nonempty_path,
                   help="an existing generated dataset folder for the learned methods "
                        "(default: generate the preset's dataset under OUT/data)")
    b.add_argument("--no-learned", action="store_true",
                   help="do not train/evaluate the learned methods (no dataset needed)")
    b.add_argument("--learned-only", action="store_true",
                   help="run only the learned methods (and their stability suite), not the "
                        "simulator's cases: e.g. a new recipe beside GarTrans")
    b.add_argument("--minutes", type=float, default=None,
                   help="training minutes of every learned run, instead of the preset's "
                        "(e.g. an hours-long budget on a GPU; use a new --out: finished "
                        "records in OUT are kept; default: the preset's)")
    b.add_argument("--batch-size", type=int, default=None, metavar="N",
                   help="training chunks per optimizer step of every learned run (chunks of "
                        "other sequences as one batch; use a new --out; default: the preset's)")
    b.add_argument("--lr-factor", type=float, default=None, metavar="F",
                   help="every learned method's learning rate multiplied by F (e.g. the square "
                        "root of --batch-size; use a new --out; default: the preset's)")
    b.add_argument("--methods", nargs="+", default=None, metavar="NAME", action=Accumulate,
                   help="run only these learned methods (quote names with spaces): "
                        f"{', '.join(METHOD_NAMES)}, or any recipe, packaged (e.g. "
                        "ablations/paper) or a YAML file (a new layer's ablation); "
                        "default: the preset's")
    b.add_argument("--shard", default=None, metavar="I/N",
                   help="run only part I (0-based) of N interleaved parts of the tasks, with "
                        "the preset's threads divided by N: start N processes with the same "
                        "--out to share the cores; they wait for each other's first-seed "
                        "records before the seed plan, and the last to finish writes the "
                        "report (default: every task in this process)")
    b.add_argument("--backend", choices=("local", "ray"), default="local",
                   help="local: every task in this process; ray: each learned (method, seed) "
                        "run a Ray task, its record and checkpoints sent back here "
                        "(docs/bench.md, 'On a cluster')")
    add_cluster_args(b, "each learned run", "with --backend ray: ")
    b.add_argument("--retry-failed", action="store_true", help="rerun records marked failed")
    b.add_argument("--no-progress", action="store_true", help="no progress bar")
    return b


def _command(args: argparse.Namespace) -> str:
    """The ``garmentgnn bench`` command line that ``args`` stand for."""
    parts = ["garmentgnn", "bench", "--preset", args.preset, "--out", str(args.out)]
    for flag, value in (("--seeds", args.seeds), ("--data", args.data),
                        ("--minutes", args.minutes), ("--batch-size", args.batch_size),
                        ("--lr-factor", args.lr_factor), ("--shard", args.shard),
                        ("--address", args.address), ("--workers", args.workers)):
        if value is not None:
            parts += [flag, str(value)]
    if args.backend != "local":
        parts += ["--backend", args.backend] + (["--gpus", str(args.gpus)] if args.gpus else [])
        if args.ship_data is not None:
            parts.append("--ship-data" if args.ship_data else "--no-ship-data")
    if args.methods:
        parts += ["--methods"] + [shlex.quote(m) for m in args.methods]
    for flag, on in (("--no-learned", args.no_learned), ("--learned-only", args.learned_only),
                     ("--retry-failed", args.retry_failed),
                     ("--no-progress", args.no_progress)):
        if on:
            parts.append(flag)
    return " ".join(parts)


def _learned_overrides(p: Preset, minutes, methods, batch_size=None, lr_factor=None
                       ) -> Preset:
    """``p`` with its learned runs' ``minutes``, ``methods``, ``batch_size`` and
    ``lr_factor`` replaced (``None``: the preset's); the preset's seeded methods that are
    left out drop from its seed plan."""
    if minutes is None and methods is None and batch_size is None and lr_factor is None:
        return p
    if p.learned is None:
        raise ValueError(f"--minutes/--methods/--batch-size/--lr-factor: preset {p.name!r} "
                         "has no learned methods")
    for flag, v in (("--minutes", minutes), ("--lr-factor", lr_factor)):
        if v is not None and not 0 < v < float("inf"):
            raise ValueError(f"{flag} must be a positive number, got {v}")
    if batch_size is not None and batch_size < 1:
        raise ValueError(f"--batch-size must be a positive number of chunks, got {batch_size}")
    kw = {k: v for k, v in (("minutes", minutes), ("batch_size", batch_size),
                            ("lr_factor", lr_factor)) if v is not None}
    if methods is not None:
        kw["methods"] = tuple(dict.fromkeys(methods))
        if p.learned.seed_methods is not None:
            kw["seed_methods"] = tuple(m for m in p.learned.seed_methods if m in methods)
    return replace(p, learned=replace(p.learned, **kw))


def main(args: argparse.Namespace) -> int:
    """Run the bench sub-command; returns the exit status (0 when the run completed --
    failed records are results and are listed in the report; 2 for bad arguments)."""
    if args.seeds is not None and args.seeds < 1:
        print(f"error: --seeds must be positive, got {args.seeds}", file=sys.stderr)
        return 2
    if args.data is not None and args.no_learned:
        print("error: --data and --no-learned exclude each other", file=sys.stderr)
        return 2
    if args.learned_only and args.no_learned:
        print("error: --learned-only and --no-learned exclude each other", file=sys.stderr)
        return 2
    shard = None
    if args.shard is not None:
        try:
            i, n = (int(v) for v in args.shard.split("/"))
        except ValueError:
            i, n = -1, 0
        if not 0 <= i < n:
            print(f"error: --shard must be I/N with 0 <= I < N (e.g. 0/2), got {args.shard!r}",
                  file=sys.stderr)
            return 2
        shard = (i, n)
    ray_only = [f for f, v in (("--address", args.address), ("--workers", args.workers),
                               ("--gpus", args.gpus or None), ("--ship-data", args.ship_data))
                if v is not None]
    if args.backend != "ray" and ray_only:
        print(f"error: {', '.join(ray_only)} set(s) the Ray cluster; add --backend ray",
              file=sys.stderr)
        return 2
    if args.backend == "ray" and shard is not None:
        print("error: --shard splits the tasks by hand; --backend ray spreads them over the "
              "cluster: give one of them", file=sys.stderr)
        return 2
    if args.backend == "ray":
        try:
            import_ray()
        except RuntimeError as err:  # the ray extra is not installed
            print(f"error: {err}", file=sys.stderr)
            return 2
    try:
        backend = None if args.backend == "local" else RayBackend(
            args.workers, args.address, args.gpus, args.ship_data)
        if args.address:  # before anything is written
            check_address(args.address)
        if args.no_learned and (args.minutes is not None or args.methods or
                                args.batch_size is not None or args.lr_factor is not None):
            raise ValueError("--minutes/--methods/--batch-size/--lr-factor set the learned "
                             "runs; --no-learned runs none")
        p = _learned_overrides(preset(args.preset), args.minutes, args.methods,
                               args.batch_size, args.lr_factor)
        if args.learned_only:
            if p.learned is None:
                raise ValueError(f"--learned-only: preset {p.name!r} has no learned methods")
            p = p.learned_only()
        summary = run(p, args.out, seeds=args.seeds,
                      progress=not args.no_progress, retry_failed=args.retry_failed,
                      data=args.data, learned=not args.no_learned,
                      command=_command(args), shard=shard, backend=backend)
    except (ValueError, SpecMismatch) as err:  # bad arguments / a dataset folder of another spec
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(summary)
    return 0
