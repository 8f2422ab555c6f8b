"""Steps or model: does GarTrans learn the static drape as fast as DA-style per optimizer
step?

In the `medium` bench (docs/results/bench_medium/) every method trains for 5 minutes of
wall time. DA-style takes about 1000 optimizer steps in that time and removes 16% of
LBS's static error (``E_static``, :func:`garmentgnn.metrics.static_dynamic_split`).
GarTrans takes about 500 steps and removes 5%. So does its supervised-only ablation
("w/o unsupervised loss", which never leaves phase 1, so no physics term and no down-scaled
supervision).

This script trains that ablation through the same bench path (``runner.run`` on the
`medium` preset: same data, chunks, cosine ``TimeBudget``, same 40 test sequences) with a
longer budget (``--minutes``, default 10: about as many steps as DA-style's 5 minutes).
It then prints the rows side by side with the 5-minute records of ``--reference`` (the
committed `medium` results).

* If the ablation now removes about DA-style's share, the step rate (throughput) is what
  held GarTrans back.
* If it stays near 5%, the model or its inputs learn the drape more slowly per step.

One training seed, so this is a pointer, not a significance claim. It writes
``static_drape_steps.{json,md}`` into ``--out`` (``--commit``: the committed
``docs/results/benchmarks/``)::

    python benchmarks/experiments/static_drape_steps.py \\
        --data ~/.cache/garmentgnn/datasets/medium-blender
"""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any, Dict, List

from garmentgnn._argparse import ArgumentParser, HelpFormatter, float_above
from garmentgnn.data.store import dataset_dir, read_json
from garmentgnn.bench import runner
from garmentgnn.bench.methods import DA, LBS
from garmentgnn.bench.presets import preset
from garmentgnn.bench.tables import table

WO_UNSUP = "GarTrans w/o unsupervised loss"
ROOT = Path(__file__).resolve().parents[2]
REFERENCE = ROOT / "docs" / "results" / "bench_medium" / "results.json"
RESULTS = ROOT / "docs" / "results" / "benchmarks"


def rows(records: List[Dict[str, Any]], minutes: str) -> List[Dict[str, Any]]:
    """The ok learned records of the compared methods as table rows."""
    out = []
    for r in records:
        if r["kind"] == "learned" and r["status"] == "ok" and r["method"] in (WO_UNSUP, DA, LBS):
            m = r["metrics"]
            out.append({"method": r["method"], "minutes": minutes, "seed": r["seed"],
                        "steps": r.get("steps"), "E_dist": m["E_dist"],
                        "E_static": m["E_static"], "E_dynamic": m["E_dynamic"],
                        "sequences": len(r["per_sequence"])})
    return out


def markdown(rows_: List[Dict[str, Any]]) -> List[str]:
    """The rows as a markdown table, with the share of LBS's error of each part removed."""
    lbs = next(r for r in rows_ if r["method"] == LBS)
    body = []
    for r in rows_:
        cells = [r["method"], r["minutes"], str(r["seed"]), str(r["steps"] or "—"),
                 f"{r['E_dist']:.3f}"]
        cells += [f"{r[k]:.3f} [{100 * (1 - r[k] / lbs[k]):.1f}%]"
                  for k in ("E_static", "E_dynamic")]
        body.append(cells)
    return table(["method", "budget (min)", "seed", "steps", "E_dist (cm)",
                  "E_static (cm) [LBS's removed]", "E_dynamic (cm) [LBS's removed]"], body)


def main(argv=None) -> None:
    ap = ArgumentParser(description=__doc__.splitlines()[0],
                        formatter_class=HelpFormatter)
    ap.add_argument("--data", required=True, type=dataset_dir,
                    help="the generated `medium` dataset folder")
    ap.add_argument("--out", default=str(Path.home() / ".cache" / "garmentgnn" / "bench" /
                                         "medium-static-steps"),
                    help="bench folder of this run (rerun to resume)")
    ap.add_argument("--minutes", type=float_above(0.0), default=10.0,
                    help="training budget of the ablation")
    ap.add_argument("--reference", default=str(REFERENCE),
                    help="results.json of the 5-minute `medium` run")
    ap.add_argument("--commit", action="store_true",
                    help=f"write the table into the committed {RESULTS} (default: into --out)")
    args = ap.parse_args(argv)
    ref_path = Path(args.reference).expanduser()
    if not ref_path.is_file():
        ap.error(f"--reference {ref_path}: no such file; pass the results.json of a "
                 "`garmentgnn bench --preset medium` run")
    fix = "pass the results.json of a `garmentgnn bench --preset medium` run"
    try:
        ref = read_json(ref_path, fix)
    except ValueError as err:
        ap.error(f"--reference {err}")
    if not isinstance(ref.get("records"), list):
        ap.error(f"--reference {ref_path}: no 'records'; {fix}")
    base = preset("medium")
    p = replace(base, engines=False, learned=replace(
        base.learned, seeds=1, minutes=args.minutes, methods=(WO_UNSUP,),
        seed_methods=None, long_minutes=None))
    command = ("python benchmarks/experiments/static_drape_steps.py --data " + args.data +
               f" --minutes {args.minutes:g}")
    summary = runner.run(p, args.out, data=args.data, command=command)
    print(summary)
    res = json.loads((Path(args.out) / "results.json").read_text())
    found = rows(ref["records"], "5 (medium)") + rows(res["records"], f"{args.minutes:g}")
    if not any(r["method"] == WO_UNSUP and r["minutes"] != "5 (medium)" for r in found):
        raise RuntimeError(f"no ok record of {WO_UNSUP!r} in {args.out}: see its report.md")
    lines = markdown(found)
    print("\n".join(lines))
    table = RESULTS if args.commit else Path(args.out)
    table.mkdir(parents=True, exist_ok=True)
    print(f"results: {table}")
    meta = {"command": command, "reference": str(ref_path.relative_to(ROOT))
            if ref_path.is_relative_to(ROOT) else str(ref_path),
            "code": res["meta"].get("code")}
    (table / "static_drape_steps.json").write_text(json.dumps({"meta": meta, "rows": found},
                                                                indent=1))
    (table / "static_drape_steps.md").write_text(
        f"# Static drape: steps or model\n\n`{command}`\n\n" + "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
