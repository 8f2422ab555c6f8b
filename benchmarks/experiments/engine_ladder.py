"""The physics engines' error against run time on a dataset's test sequences
(:mod:`garmentgnn.bench.engines`): one sequence per held-out group (motion, body,
garment), each simulated again by every setting of
:func:`~garmentgnn.bench.engines.default_settings` and by the dataset's own engine at
its own settings (the oracle: its error must be ~0), for the first ``--frames`` frames.

Prints a markdown table (seconds per simulated frame, E_dist in cm, collision rate,
non-converged frames of the torch simulator) and writes ``engine_ladder.{json,md}`` into a
cache folder (``--out`` elsewhere; ``--commit``: the committed ``docs/results/benchmarks/``)::

    OMP_NUM_THREADS=1 python benchmarks/experiments/engine_ladder.py \
        --data ~/.cache/garmentgnn/datasets/medium-blender
"""
from __future__ import annotations

import json
import platform
import time
from pathlib import Path

import torch

from garmentgnn._argparse import (ArgumentParser, HelpFormatter, add_output_args, int_at_least,
                                  output_path)
from garmentgnn.data.store import dataset_dir
from garmentgnn.bench.engines import (DEFAULT_FRAMES, EngineSetting, dataset_items,
                                      default_settings, engine_record, item_engine,
                                      pick_sequences)

HERE = Path(__file__).resolve().parent
RESULTS = HERE.parents[1] / "docs" / "results" / "benchmarks" / "engine_ladder"


def main(argv=None) -> None:
    ap = ArgumentParser(description=__doc__.splitlines()[0],
                        formatter_class=HelpFormatter)
    ap.add_argument("--data", required=True, type=dataset_dir,
                    help="a generated dataset folder")
    ap.add_argument("--frames", type=int_at_least(2), default=DEFAULT_FRAMES,
                    help="frames of each sequence (after the pre-roll)")
    ap.add_argument("--per-group", type=int_at_least(1), default=1,
                    help="test sequences per held-out group")
    ap.add_argument("--engine", choices=("blender", "torch"), default=None,
                    help="run only this engine's settings (and the oracle); default both")
    add_output_args(ap, RESULTS, "writes OUT.json and OUT.md")
    a = ap.parse_args(argv)
    a.out = str(output_path(a, RESULTS))
    picks = pick_sequences(dataset_items(a.data), a.per_group)
    if not picks:
        raise SystemExit(f"error: --data {a.data}: no ok test items held out for one part "
                         f"only")
    t0 = time.perf_counter()
    records = []
    for item in picks:
        oracle = EngineSetting(item_engine(item), "dataset's own settings (oracle)")
        ladder = [s for s in default_settings() if a.engine in (None, s.engine)]
        for setting in [oracle] + ladder:
            frames = min(a.frames, item["motion"]["num_frames"])
            rec = engine_record(a.data, item, setting, frames=frames)
            rec.pop("traceback", None)
            records.append(rec)
            e = rec.get("metrics", {}).get("E_dist")
            print(f"{rec['held_out'][0]:8s} {rec['method']:34s} {rec['status']:6s} "
                  f"{rec.get('seconds_per_frame') or float('nan'):7.3f} s/frame  "
                  f"E_dist {float('nan') if e is None else e:.4f} cm", flush=True)
    write(records, Path(a.out),
          f"Dataset `{Path(a.data).name}`, first {a.frames} frames of each sequence"
          f"{'' if a.engine is None else f', {a.engine} settings only'}, "
          f"{torch.get_num_threads()} torch thread(s), {platform.machine()}; "
          f"{time.perf_counter() - t0:.0f} s in all.")


def write(records, out: Path, header: str) -> None:
    """``out.json`` (the records) and ``out.md`` (``header`` and the table); prints the table."""
    lines = [header, "",
             "| held out | sequence | method | s / simulated frame | E_dist (cm) | "
             "collision (%) | non-converged frames | status |",
             "|---|---|---|---:|---:|---:|---:|---|"]

    def num(x, fmt):
        return "-" if x is None else format(x, fmt)

    for r in records:
        m = r.get("metrics", {})
        lines.append(f"| {', '.join(r['held_out'])} | {r['case']} | {r['method']} | "
                     f"{num(r.get('seconds_per_frame'), '.3f')} | {num(m.get('E_dist'), '.4f')} | "
                     f"{num(m.get('collision_rate'), '.2f')} | "
                     f"{r.get('nonconverged_frames', '-')} | {r['status']} |")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(records, indent=1) + "\n")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
