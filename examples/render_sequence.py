"""Render frames of a generated (simulated) sequence file as a PNG strip, with the body.

    python examples/render_sequence.py data/small/sequences/<id>.npz --out strip.png
    python examples/render_sequence.py SEQ.npz --frames 0 5 10 15 20 29 --views front side
"""
from __future__ import annotations

import argparse
from pathlib import Path

import torch

from garmentgnn.body.factory import build_body
from garmentgnn.data.store import load_sequence
from garmentgnn.data.validity import sequence_valid
from garmentgnn.viz import render_grid

BODY_RGB, CLOTH_RGB = (0.82, 0.70, 0.60), (0.30, 0.45, 0.75)
VIEWS = {"front": -90.0, "side": 0.0, "three-quarter": -60.0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seq", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--frames", type=int, nargs="+", default=None,
                    help="frame indices (default: six evenly spaced)")
    ap.add_argument("--views", nargs="+", default=["three-quarter"], choices=sorted(VIEWS))
    args = ap.parse_args()
    seq = load_sequence(args.seq)
    meta = seq["meta"]
    P = torch.from_numpy(seq["positions"])
    T = P.shape[0]
    frames = args.frames or sorted({round(i * (T - 1) / 5) for i in range(6)})
    bad = [t for t in frames if not 0 <= t < T]
    if bad:
        raise ValueError(f"`--frames`: {bad} out of range [0, {T})")
    body = build_body(meta["body"])
    rot = torch.from_numpy(seq["motion_rotations"]).to(body.vertices.dtype)
    tr = torch.from_numpy(seq["motion_translation"]).to(body.vertices.dtype)
    with torch.no_grad():
        bpos, _ = body.pose(rot[frames], tr[frames])
    faces = torch.from_numpy(seq["garment_faces"])
    valid = sequence_valid(seq)
    cells, titles = [], []
    for view in args.views:
        cells.append([[(bpos[i], body.faces, BODY_RGB), (P[t], faces, CLOTH_RGB)]
                      for i, t in enumerate(frames)])
        titles.append([f"frame {t}" + ("" if valid[t] else " (invalid)")
                       + f", {view}" for t in frames])
    png = render_grid(cells, args.out, titles=titles, elev=10, azim=VIEWS[args.views[0]])
    print(f"wrote {png}: {meta['id']} ({T} frames, {meta.get('material')}, "
          f"{P.shape[1]} vertices)")


if __name__ == "__main__":
    main()
