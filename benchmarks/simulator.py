"""Simulator cost: simulated frames per second and vertex-steps per second.

A square sheet pinned along one edge swings under gravity (no body, so the numbers
isolate the cloth solve): thread counts and stiffness multipliers at the smallest
size, vertex counts at the largest thread count.  Each configuration simulates
``--frames`` frames at 30 fps after one warm-up frame; the table reports seconds per
frame, frames per second, vertex-substeps per second, mean Newton iterations per frame
and whether every frame converged.  Writes ``simulator.{json,md}``
into a cache folder (``--out`` elsewhere; ``--commit``: the committed ``docs/results/benchmarks/``).

    python benchmarks/simulator.py                       # 1K, 5K, 10K vertices
    python benchmarks/simulator.py --sizes 1000 --frames 2
"""
from __future__ import annotations

import json
import math
import os
import platform
import time
from pathlib import Path

import torch

from garmentgnn._argparse import (Accumulate, ArgumentParser, HelpFormatter, add_output_args,
                                  check_unique, float_above, int_at_least, output_path)
from garmentgnn.garments import Garment
from garmentgnn.geometry import grid_mesh
from garmentgnn.motion import Motion
from garmentgnn.physics import material
from garmentgnn.sim import SimSettings, simulate

HERE = Path(__file__).resolve().parent
RESULTS = HERE.parent / "docs" / "results" / "benchmarks"


def hanging_sheet(num_vertices: int, size: float = 0.5) -> Garment:
    n = max(2, int(round(math.sqrt(num_vertices))))
    pos, faces = grid_mesh(n, n, (size, size))
    uv = pos[:, :2].clone()
    # hang in the xz plane, pinned along the top edge
    pos = torch.stack([pos[:, 0], torch.zeros_like(pos[:, 0]), pos[:, 1] + 1.0], 1)
    pinned = pos[:, 2] > pos[:, 2].max() - 1e-6
    # a small initial tilt so the sheet swings instead of hanging still
    pos[:, 1] += 0.2 * (pos[:, 2].max() - pos[:, 2])
    return Garment(pos, faces, uv, pinned=pinned)


def run(num_vertices: int, threads: int, stiffness: float, frames: int, substeps: int) -> dict:
    torch.set_num_threads(threads)
    g = hanging_sheet(num_vertices)
    mat = material("silk").scaled(stiffness)
    motion = Motion(torch.zeros(frames + 1, 1, 3), torch.zeros(frames + 1, 3), ["root"], 30.0)
    settings = SimSettings(fps=30.0, substeps=substeps)
    t0 = time.perf_counter()
    res = simulate(g, None, motion, mat, settings)
    seconds = time.perf_counter() - t0
    per_frame = seconds / frames
    V = g.vertices.shape[0]
    return dict(vertices=V, threads=threads, stiffness=stiffness, frames=frames,
                substeps=substeps, seconds_per_frame=per_frame, fps=1.0 / per_frame,
                vertex_steps_per_s=V * substeps / per_frame,
                newton_per_frame=float(res.newton_iterations[1:].float().mean()),
                converged=bool(res.converged.all()), ok=res.ok, message=res.message)


def main(argv=None) -> None:
    ap = ArgumentParser(description=__doc__.splitlines()[0],
                        formatter_class=HelpFormatter)
    ap.add_argument("--sizes", type=int_at_least(4), nargs="+", default=[1000, 5000, 10000],
                    action=Accumulate,
                    help="sheet sizes (vertices)")
    ap.add_argument("--threads", type=int_at_least(1), nargs="+", default=[1, 2],
                    action=Accumulate,
                    help="torch thread counts, measured at the smallest size")
    ap.add_argument("--stiffness", type=float_above(0.0), nargs="+", default=[1.0, 1000.0],
                    action=Accumulate,
                    help="stiffness multipliers, measured at the smallest size")
    ap.add_argument("--frames", type=int_at_least(1), default=3,
                    help="simulated frames per row")
    ap.add_argument("--substeps", type=int_at_least(1), default=4,
                    help="simulator substeps per frame")
    add_output_args(ap, RESULTS, "folder for simulator.json and simulator.md")
    args = ap.parse_args(argv)
    for flag in ("sizes", "threads", "stiffness"):
        check_unique(ap, getattr(args, flag), "--" + flag)
    args.out = output_path(args, RESULTS)
    rows = []
    small, most = min(args.sizes), max(args.threads)
    # thread scaling and stiffness at the smallest size; vertex scaling at most threads
    configs = [(small, t, 1.0) for t in args.threads]
    configs += [(n, most, 1.0) for n in args.sizes if n != small]
    configs += [(small, most, s) for s in args.stiffness if s != 1.0]
    for n, t, s in configs:
        row = run(n, t, s, args.frames, args.substeps)
        rows.append(row)
        print(f"V={row['vertices']:>6} threads={t} stiffness x{s:g}: "
              f"{row['seconds_per_frame']:.2f} s/frame, {row['vertex_steps_per_s']:.0f} "
              f"vertex-steps/s, {row['newton_per_frame']:.1f} Newton it/frame, "
              f"converged={row['converged']}", flush=True)
    report = dict(machine=dict(platform=platform.platform(), cpus=os.cpu_count(),
                               torch=torch.__version__), rows=rows)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "simulator.json").write_text(json.dumps(report, indent=2))
    lines = ["# Simulator benchmark", "",
             f"Pinned hanging silk sheet, no body, {args.substeps} substeps at 30 fps, "
             f"{args.frames} simulated frames per row (time includes set-up).", "",
             "| vertices | threads | stiffness | s/frame | frames/s | vertex-steps/s | "
             "Newton it/frame | converged |", "|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        lines.append(f"| {r['vertices']} | {r['threads']} | x{r['stiffness']:g} | "
                     f"{r['seconds_per_frame']:.2f} | {r['fps']:.3f} | "
                     f"{r['vertex_steps_per_s']:.0f} | {r['newton_per_frame']:.1f} | "
                     f"{r['converged']} |")
    (args.out / "simulator.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
