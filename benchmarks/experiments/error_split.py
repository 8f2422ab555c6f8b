"""How much of LBS's error is a static drape and how much is dynamics: oracles on a
generated dataset (no learning; ground truth used where an oracle says so).

For every ok sequence (``--split``; default all), with ``M_v(t) = sum_j W_vj A_j(t)`` the
blended skinning transform of vertex ``v`` (Eq. 1,
``GarmentInputs.skinning_transforms``) and ``x_v(t)`` the simulated garment:

* ``lbs``: the rest garment skinned (``GarmentInputs.skinned``);
* ``static oracle (in-sample)``: each vertex's simulated position un-skinned into the
  rest frame, ``M_v(t)^-1 x_v(t)``, averaged over the sequence's frames and skinned
  again -- the best "fixed drape in the skinned local frame"; an upper bound on what a
  static model can remove;
* ``static oracle (other motion)``: the same time-mean rest-frame shape taken from the
  *other* sequences of the same garment on the same body (e.g. its ``walk``) and applied
  to this one (e.g. its held-out ``arm_swing``) -- what a static drape learned elsewhere
  transfers;
* ``previous frame + LBS motion``: ``x(t-1) + lbs(t) - lbs(t-1)`` over frames ``t >= 1``
  -- a dynamic oracle that knows the true previous state;
* ``lbs, frame 0``: how far the simulated first frame already is from the skinned one.

The "LBS error removed" column compares with ``lbs`` over all frames (the previous-frame
oracle covers frames 1.. only).

Prints a markdown table of frame-weighted E_dist (cm) and the fraction of LBS's error
each removes, and writes ``error_split.{json,md}`` into a cache folder (``--out`` elsewhere;
``--commit``: the committed ``docs/results/benchmarks/``)::

    python benchmarks/experiments/error_split.py --data ~/.cache/garmentgnn/datasets/tiny-torch
"""
from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import torch

from garmentgnn._argparse import ArgumentParser, HelpFormatter, add_output_args, output_path
from garmentgnn.data.store import dataset_dir, read_manifest
from garmentgnn.data.keys import body_key, garment_key
from garmentgnn.metrics import vertex_distance
from garmentgnn.metrics.split import posed, to_rest_frame
from garmentgnn.data import SequenceChunks

RESULTS = Path(__file__).resolve().parents[2] / "docs" / "results" / "benchmarks"


def main(argv=None) -> None:
    ap = ArgumentParser(description=__doc__.splitlines()[0],
                        formatter_class=HelpFormatter)
    ap.add_argument("--data", required=True, type=dataset_dir,
                    help="a generated dataset folder")
    ap.add_argument("--split", default=None, help="train / val / test (default: every split)")
    add_output_args(ap, RESULTS, "folder for error_split.json and error_split.md")
    args = ap.parse_args(argv)
    splits = sorted({str(r.get("split")) for r in read_manifest(args.data)["items"]
                     if r.get("status") == "ok"})
    if args.split is not None and args.split not in splits:
        ap.error(f"--split {args.split}: no ok sequences of that split in {args.data}; "
                 f"name one of {', '.join(splits)}, or leave it out for every split")
    out = output_path(args, RESULTS)
    ds = SequenceChunks(args.data, split=None, chunk=10 ** 9, history=1)
    seqs = []
    with torch.no_grad():
        for i in range(len(ds)):
            inp = ds[i]
            rec = ds.records[ds.index[i][0]]
            M = inp.skinning_transforms()
            gt = inp.gt.double()
            seqs.append({"id": rec["id"], "split": rec["split"], "M": M, "gt": gt,
                         "lbs": inp.skinned().double(),
                         "key": (garment_key(rec["garment"]), body_key(rec["body"])),
                         "rest_mean": to_rest_frame(M, gt).mean(0)})
    groups = defaultdict(list)
    for s in seqs:
        groups[s["key"]].append(s)
    methods = ("lbs", "lbs, frame 0", "static oracle (in-sample)",
               "static oracle (other motion)", "previous frame + LBS motion")
    sums, frames = defaultdict(float), defaultdict(int)
    rows = []
    for s in seqs:
        if args.split is not None and s["split"] != args.split:
            continue
        T = s["gt"].shape[0]
        preds = {"lbs": s["lbs"], "static oracle (in-sample)": posed(s["M"], s["rest_mean"])}
        others = [o["rest_mean"] for o in groups[s["key"]] if o is not s]
        if others:
            preds["static oracle (other motion)"] = posed(s["M"], torch.stack(others).mean(0))
        row = {"id": s["id"], "split": s["split"], "frames": T}
        for m, P in preds.items():
            e = float(vertex_distance(P, s["gt"]).mean())  # cm
            row[m] = e
            sums[m] += e * T
            frames[m] += T
        # frames 1.. only: frame 0 has no previous frame
        prev = s["gt"][:-1] + s["lbs"][1:] - s["lbs"][:-1]
        e = float(vertex_distance(prev, s["gt"][1:]).mean())
        row["previous frame + LBS motion"] = e
        sums["previous frame + LBS motion"] += e * (T - 1)
        frames["previous frame + LBS motion"] += T - 1
        e0 = float(vertex_distance(s["lbs"][:1], s["gt"][:1]).mean())
        row["lbs, frame 0"] = e0
        sums["lbs, frame 0"] += e0
        frames["lbs, frame 0"] += 1
        rows.append(row)
    lbs = sums["lbs"] / frames["lbs"]
    summary = {m: {"E_dist_cm": sums[m] / frames[m], "removed": 1 - sums[m] / frames[m] / lbs,
                   "frames": frames[m]} for m in methods if frames[m]}
    lines = [f"Dataset `{args.data}`, split {args.split or 'all'}: {len(rows)} sequences.", "",
             "| method | E_dist (cm) | LBS error removed | frames |", "|---|---|---|---|"]
    lines += [f"| {m} | {v['E_dist_cm']:.3f} | "
              f"{'—' if m == 'lbs, frame 0' else format(v['removed'], '.0%')} | {v['frames']} |"
              for m, v in summary.items()]
    prev = summary.get("previous frame + LBS motion")
    if prev:  # frame 0 counted as known, i.e. zero error there
        lines += ["", f"Previous frame + LBS motion with frame 0 counted as known: "
                  f"{prev['E_dist_cm'] * prev['frames'] / frames['lbs']:.3f} cm over all frames."]
    text = "\n".join(lines) + "\n"
    print(text)
    out.mkdir(parents=True, exist_ok=True)
    (out / "error_split.md").write_text(text)
    (out / "error_split.json").write_text(json.dumps(
        {"data": str(args.data), "split": args.split, "summary": summary, "sequences": rows},
        indent=1))


if __name__ == "__main__":
    main()
