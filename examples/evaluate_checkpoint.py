"""Score a trained GarTrans checkpoint on a held-out split (frame-parallel, autoregressive,
LBS only) and render simulated / GarTrans / LBS frames of one sequence.

    python examples/evaluate_checkpoint.py runs/gartrans/logs/version_0/checkpoints/last.ckpt \\
        --data data/small --split test --out docs/results/gartrans_small
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from garmentgnn.training import GarTransModule
from garmentgnn.training.evaluate import evaluate_split, markdown_table
from garmentgnn.viz.strip import render_strip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("ckpt", type=Path)
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--split", default="test")
    ap.add_argument("--history", type=int, default=3)
    ap.add_argument("--num-landmarks", type=int, default=64)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--render", type=int, default=0, help="index of the sequence to render")
    args = ap.parse_args()
    module = GarTransModule.load_from_checkpoint(args.ckpt, map_location="cpu").eval()
    res = evaluate_split(module, args.data, args.split, history=args.history,
                         num_landmarks=args.num_landmarks)
    args.out.mkdir(parents=True, exist_ok=True)
    table = markdown_table(res)
    (args.out / "metrics.json").write_text(json.dumps(res, indent=2))
    (args.out / "metrics.md").write_text(table + "\n")
    print(table)
    png, seq = render_strip(module, args.data, args.split, args.out / "strip.png",
                            index=args.render, history=args.history,
                            num_landmarks=args.num_landmarks)
    print(f"wrote {args.out}/metrics.{{json,md}} and {png} ({seq})")


if __name__ == "__main__":
    main()
