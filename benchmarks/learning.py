"""Do the learned methods learn?  Step-0 gradients, one-chunk overfit, equal-step curves.

Its parts, each on a generated dataset (``--data``, e.g. ``garmentgnn generate --preset
small --engine blender``), every method built from its packaged recipe
(:func:`garmentgnn.training.load_recipe`) the way ``garmentgnn bench`` builds it
(:mod:`garmentgnn.bench.methods`) and trained through the recipe's Lightning ``Trainer``:

* ``grad``: one backward pass of each method's phase-1 training loss on the first
  training chunk; per branch the trainable parameter tensors, how many got a non-zero
  gradient and the gradient norm (:func:`garmentgnn.training.diagnostics.branch_gradients`).
* ``overfit``: each method trained on that one chunk alone for ``--steps`` steps; its
  E_dist on the chunk against steps, and LBS's.
* ``curves``: GarTrans settings and the DA- and HOOD-style baselines (``--variants``,
  :data:`VARIANTS`; NCS-style trains per garment on test poses) trained for the same
  ``--steps`` on the training split; E_dist on the valid frames of the training and test
  sequences every ``--every`` steps, as a ratio to LBS's on the same frames, and per
  held-out group at the end (``--surface``: the normal, edge-length and curvature errors
  too); with several ``--seed``, the mean over seeds and a paired Wilcoxon test of each
  variant against the first.  Each finished (variant, seed) run is kept in
  ``curves.done.json``, so the same command run again after an interruption goes on
  where it stopped.
* ``energy``: the HOOD- and NCS-style models a ``garmentgnn bench`` run trained
  (``--bench``): their own objective, the physics terms they were trained on, on their
  test predictions against the same objective on the LBS garment, beside E_dist.
* ``oracle``: what those methods could reach at best: the trajectory that minimises a
  physics objective exactly, frame by frame (the objectives of the HOOD-style
  ``--variants``, default its recipe's, which NCS-style's shares, and the silk
  energies), on the test sequences, against LBS.

Each writes ``<part>.json`` and ``<part>.md`` (curves also ``<part>.png``) into
``~/.cache/garmentgnn/benchmarks/learning``, ``--out``, or with ``--commit`` the committed
copy ``docs/results/learning``::

    python benchmarks/learning.py grad overfit curves \
        --data ~/.cache/garmentgnn/datasets/small-blender
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Optional, Sequence

import torch

from garmentgnn._argparse import (Accumulate, ArgumentParser, HelpFormatter, add_output_args,
                                  check_unique, command_line, existing_file, int_at_least,
                                  output_path)
from garmentgnn.data.store import read_manifest

#: the folder of this script and its parts (``learning_parts``): on ``sys.path`` when it is
#: run, added when it is loaded by path (``runpy.run_path``)
HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.append(str(HERE))
from learning_parts.curves import (curves_markdown, merge_curves, plot_curves,  # noqa: E402
                                   read_curves)
from learning_parts.objective import (objective_rollout, own_objective,  # noqa: E402
                                      part_energy, part_oracle)
from learning_parts.train import (Probe, evenly, frame_errors,  # noqa: E402
                                  part_curves, part_grad, part_overfit)
from learning_parts.variants import VARIANTS  # noqa: E402

#: the functions this script offers to code that loads it (``runpy.run_path``)
__all__ = ["Probe", "VARIANTS", "curves_markdown", "evenly", "frame_errors", "main", "merge_curves",
           "objective_rollout", "own_objective", "parse_args", "part_curves", "part_energy",
           "part_grad", "part_oracle", "part_overfit", "plot_curves"]

RESULTS = HERE.parent / "docs" / "results" / "learning"


def parse_args(argv: Optional[Sequence[str]] = None) -> argparse.Namespace:
    """The command line, checked: a repeated list flag (``--seed 0 --seed 1``) adds up,
    a value given twice, a count below 1, ``--every`` over ``--steps``, a missing
    dataset or ``--curves`` file end in one ``error:`` line (exit status 2)."""
    ap = ArgumentParser(description=__doc__.splitlines()[0],
                        formatter_class=HelpFormatter)
    ap.add_argument("parts", nargs="+", choices=("grad", "overfit", "curves", "energy", "oracle",
                                                  "merge"),
                    help="what to run (merge: the `curves` results of --curves as one table)")
    ap.add_argument("--data", default=None,
                    help="a generated dataset folder (every part but merge)")
    ap.add_argument("--curves", nargs="+", default=None, action=Accumulate, type=existing_file,
                    help="merge: curves.json files of the same dataset and steps (other "
                         "variants, or other seeds of a variant)")
    ap.add_argument("--bench", default=None,
                    help="energy: the output folder of a `garmentgnn bench` run on --data")
    add_output_args(ap, RESULTS, "folder for <part>.json, .md and .png")
    ap.add_argument("--steps", type=int_at_least(1), default=300,
                    help="optimizer steps (overfit, curves)")
    ap.add_argument("--every", type=int_at_least(1), default=50,
                    help="steps between measurements (at most --steps)")
    ap.add_argument("--variants", nargs="+", default=None, choices=list(VARIANTS),
                    action=Accumulate,
                    help="GarTrans settings compared by `curves` (default: all), added to "
                         "`grad` and `overfit` (default: none), kept by `merge` (default: "
                         "all); the HOOD-style objectives of `oracle` (default: its "
                         "recipe's and the silk energies)")
    ap.add_argument("--methods", nargs="+", default=None, action=Accumulate,
                    help="the methods `grad` and `overfit` run (default: every learned "
                         "method of the bench)")
    ap.add_argument("--train-sequences", type=int_at_least(1), default=6,
                    help="training sequences measured by `curves` (evenly spaced)")
    ap.add_argument("--test-sequences", type=int_at_least(1), default=None,
                    help="test sequences measured by `curves` (from each held-out group in "
                         "turn) and `oracle` (evenly spaced); default: all")
    ap.add_argument("--seed", type=int, nargs="+", default=[0], action=Accumulate,
                    help="training seeds (curves: each variant once per seed; repeat the "
                         "flag or list several); the bench run's seed (energy: one)")
    ap.add_argument("--surface", action="store_true",
                    help="curves: also the normal, edge-length and curvature errors")
    ap.add_argument("--threads", type=int_at_least(1), default=1, help="torch threads")
    args = ap.parse_args(argv)
    for flag in ("parts", "seed", "variants", "methods", "curves"):
        check_unique(ap, getattr(args, flag), "--" + flag if flag != "parts" else "parts")
    if args.every > args.steps and set(args.parts) & {"overfit", "curves"}:
        ap.error(f"--every {args.every}: more than --steps {args.steps}; nothing would be "
                 f"measured after step 0")
    if args.data is None and set(args.parts) - {"merge"}:
        raise SystemExit("error: give --data DIR, the generated dataset to train on")
    if args.data is not None and set(args.parts) - {"merge"}:
        try:
            read_manifest(Path(args.data).expanduser())
        except (OSError, ValueError) as err:
            raise SystemExit(f"error: --data {err}") from None
    if "merge" in args.parts and not args.curves:
        raise SystemExit("error: merge: give --curves FILE FILE ..., `curves` results")
    for f in (args.curves or []) if "merge" in args.parts else []:
        try:
            read_curves(Path(f))
        except (OSError, ValueError) as err:
            raise SystemExit(f"error: {_curves_message(err)}") from None
    return args


def _curves_message(err: Exception) -> str:
    """An error of :func:`merge_curves` with the flag named."""
    msg = str(err).replace("`files`", "--curves")
    return msg if msg.startswith("--") else "--curves " + msg


def main(argv: Optional[Sequence[str]] = None) -> None:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    root, out = Path(args.data or "."), output_path(args, RESULTS)
    out.mkdir(parents=True, exist_ok=True)
    command = command_line("benchmarks/learning.py", argv)
    for part in args.parts:
        if part == "grad":
            r = part_grad(root, args.methods, args.variants or ())
        elif part == "overfit":
            r = part_overfit(root, args.steps, args.every, args.methods,
                             args.variants or ())
        elif part == "energy":
            if args.bench is None:
                raise SystemExit("error: `energy` reads a bench run's models: give --bench DIR")
            if len(args.seed) != 1:
                raise SystemExit("error: `energy` reads one bench run's models: give one --seed")
            r = part_energy(root, Path(args.bench).expanduser(), args.seed[0])
        elif part == "oracle":
            try:
                r = part_oracle(root, args.variants or ["HOOD-style",
                                                        "HOOD-style, silk energies"],
                                args.test_sequences)
            except ValueError as err:
                raise SystemExit(f"error: {err}") from None
        elif part == "merge":
            try:
                res = merge_curves([Path(f).expanduser() for f in args.curves],
                                   args.variants)
            except (OSError, ValueError) as err:
                raise SystemExit(f"error: {_curves_message(err)}") from None
            r = {"results": res, "markdown": [
                "Merged from:", ""] + [f"- `{src['command']}`" for src in res["sources"]]
                + [""] + curves_markdown(res, "lbs_metrics" in res)}
            plot_curves(res, out / f"{part}.png")
        else:
            r = part_curves(root, args.steps, args.every, args.variants or list(VARIANTS),
                            args.train_sequences, args.seed, args.surface,
                            args.test_sequences, done=out / "curves.done.json")
            plot_curves(r["results"], out / f"{part}.png")
        (out / f"{part}.json").write_text(json.dumps({"command": command, **r["results"]},
                                                     indent=1))
        (out / f"{part}.md").write_text(f"# {part}\n\n`{command}`\n\n" +
                                        "\n".join(r["markdown"]) + "\n")
        print("\n".join(r["markdown"]), flush=True)


if __name__ == "__main__":
    main()
